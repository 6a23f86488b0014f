"""Road-marking rasterization shared by the markings stage and the pose graph's survey marking anchors
(Kim et al. s.2.1): elevation grid -> traversable cells -> adaptive intensity threshold.

Each stage passes its own ``MarkingRasterSettings`` (a field of its params), so a settings override of one stage
never reaches the other, and both stages' code versions include this package's source digest
(``pipeline.declare.source_digest``): a change here re-runs both.
"""
