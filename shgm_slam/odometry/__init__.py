"""Odometry stage: depth -> camera-frame cloud (clouds.py) -> KISS-ICP (kiss.py) or external poses
(sources.py). Every source reports ``T_odom_cam``; a robot's odometry frame is its first camera frame.
"""
