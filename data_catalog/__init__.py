"""The data catalog shipped with cornermap: ``datasets.yaml`` (package data, read with importlib.resources)."""
