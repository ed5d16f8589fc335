"""Back end: robot keys (keys.py), closure consistency (consistency.py), the iSAM2 multi-robot pose graph
(pose_graph.py). The shared frame is the first robot's odometry frame.
"""
