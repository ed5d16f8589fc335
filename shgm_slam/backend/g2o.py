"""The pose graph as g2o text: VERTEX_SE3:QUAT lines for the estimates, EDGE_SE3:QUAT lines for the
odometry factors and closures (``MultiRobotPoseGraph.to_g2o``), and writing that text to a file.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import gtsam
import numpy as np

from shgm_slam.backend.factors import pose3


def g2o_pose(p: gtsam.Pose3) -> str:
    """``x y z qx qy qz qw`` of a pose, as g2o writes it."""
    t = p.translation()
    q = p.rotation().toQuaternion()
    return f"{t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {q.x():.9f} {q.y():.9f} {q.z():.9f} {q.w():.9f}"


def g2o_edge(k1: int, k2: int, T: np.ndarray, info_rot_trans: np.ndarray) -> str:
    """One EDGE_SE3:QUAT line: the measurement ``T`` (4, 4) from key ``k1`` to ``k2`` and the upper triangle of
    its information, given in gtsam order [rot, trans] and written in g2o order [trans, rot]."""
    perm = np.r_[3, 4, 5, 0, 1, 2]  # gtsam [rot, trans] -> g2o [trans, rot]
    I = info_rot_trans[np.ix_(perm, perm)]
    upper = I[np.triu_indices(6)]
    return f"EDGE_SE3:QUAT {k1} {k2} " + g2o_pose(pose3(T)) + " " + " ".join(f"{v:.6g}" for v in upper)


def g2o_text(
    values: gtsam.Values, edges: Iterable[tuple[int, int, np.ndarray, np.ndarray]], comments: Iterable[str] = ()
) -> str:
    """g2o text of a graph: a ``# `` line per comment (g2o and ``gtsam.readG2o`` skip them), a VERTEX_SE3:QUAT
    line per Pose3 in ``values`` (sorted by key), then an EDGE_SE3:QUAT line per ``(key_1, key_2, T (4, 4),
    information (6, 6) in gtsam order [rot, trans])`` in the order given."""
    lines = [f"# {c}" for c in comments]
    for k in sorted(values.keys()):
        lines.append(f"VERTEX_SE3:QUAT {k} " + g2o_pose(values.atPose3(k)))
    for k1, k2, T, info in edges:
        lines.append(g2o_edge(k1, k2, T, info))
    return "\n".join(lines) + "\n"


def write_g2o(path: Path | str, text: str) -> None:
    """Write g2o ``text`` to ``path`` (creating the parent folder)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
