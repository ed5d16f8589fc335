"""Graph nodes indexed for radius queries, same-label and any-label: labels are folded into a fourth
coordinate (``embed``) so that one KD-tree query finds same-label neighbours only."""

from __future__ import annotations

from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

LABEL_GAP_M = 1e6
"""Distance between label layers in the (x, y, z, label) embedding: same-label queries never cross."""


class LabelledTree:
    """Nodes of one graph indexed for same-label and any-label radius queries.

    Args:
        positions_xyz: (N, 3) node positions, metres.
        label_ids: (N,) train ids.
    """

    def __init__(self, positions_xyz: np.ndarray, label_ids: np.ndarray) -> None:
        self.positions_xyz = np.asarray(positions_xyz, dtype=np.float64)
        self.label_ids = np.asarray(label_ids, dtype=np.int64)

    @cached_property
    def any(self) -> cKDTree:
        """Tree of the (N, 3) positions (built on first use)."""
        return cKDTree(self.positions_xyz)

    @cached_property
    def same(self) -> cKDTree:
        """Tree of the (N, 4) ``embed`` points: same-label queries (built on first use)."""
        return cKDTree(embed(self.positions_xyz, self.label_ids))

    def __len__(self) -> int:
        return int(self.label_ids.shape[0])


def embed(positions_xyz: np.ndarray, label_ids: np.ndarray) -> np.ndarray:
    """(N, 4) points (x, y, z, label * gap): Euclidean distance is infinite-like across labels."""
    out = np.empty((np.shape(positions_xyz)[0], 4))
    out[:, :3] = positions_xyz
    np.multiply(label_ids, LABEL_GAP_M, out=out[:, 3])
    return out


def nearest_same_label(
    tree: LabelledTree, points_xyz: np.ndarray, label_ids: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest same-label node of ``tree`` within ``radius_m`` of each of (N, 3) points.

    Returns:
        (N,) distances (inf when none) and (N,) row indices (``len(tree)`` when none).
    """
    return tree.same.query(embed(points_xyz, label_ids), k=1, distance_upper_bound=radius_m)
