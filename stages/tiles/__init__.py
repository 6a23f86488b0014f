"""Versioned map tiles: publish corners + marking rasters per tile, load, diff, export (docs/map-format.md)."""
