"""A robot: its front end (perception -> odometry -> keyframes -> graph) and its node process."""
