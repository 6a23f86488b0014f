"""Corner map stage: per-scan corner observations -> one record per physical corner (Im et al. 2016 s.3)."""
