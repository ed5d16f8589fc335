"""odometry stage."""
