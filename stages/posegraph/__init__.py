"""Pose-graph optimization: ICP odometry, verified loop closures, robust GNSS priors, survey anchors (GTSAM)."""
