"""The pose graph's factors: per-drive inputs and increments, odometry / wheel / span edges, GNSS and INS
attitude priors, and the GTSAM graph they are solved in."""
