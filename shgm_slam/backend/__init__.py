"""Back end: robot keys (keys.py), closure consistency (consistency.py), the iSAM2 multi-robot pose graph
(pose_graph.py) with its records (records.py), snapshot (state.py), per-robot record (track.py), GTSAM
factor helpers (factors.py) and g2o export (g2o.py). The shared frame is the first robot's odometry frame.
"""
