"""The published map format: what localizers, exports and ``evaluate`` consume.

A published map is ``ROOT/maps/NAME/vNNNN/`` with a manifest, per-tile corner Parquet, marking rasters and
trajectories (``layout``). ``loader.open_map`` is the one reader (verified, bounded); ``verify``, ``diff`` and
``export`` work on what it returns. The tiles stage writes this format; nothing here imports a stage other than
``stages.common``.
"""
