"""The cornermap engine: stage declarations, catalog, fingerprints, Parquet store, dask graph, publishing.

The engine knows nothing about LiDAR. Stages plug in through ``cornermap.stages`` entry points.
"""
