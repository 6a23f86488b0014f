"""ICP odometry between consecutive scans (per scan chunk)."""
