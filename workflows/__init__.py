"""The standard workflows shipped with cornermap (package data): ``demo``, ``tiny``, ``gangnam``, ``map_rebuild``.

Any command that takes a workflow accepts one of these names as well as a path to a workflow file.
"""
