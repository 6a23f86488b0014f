"""Per-scan vertical corner extraction (Im, Im & Jee 2016, section 2).

Upper layers only -> per-ring IEPF split-and-merge lines with total-least-squares refits -> the residual
variance outlier test (paper Figure 5) -> corner candidates from neighbouring lines -> the multi-layer
redundancy check. Algorithms are pure numpy (arrays in, arrays out); ``compute.py`` is the table adapter.
"""
