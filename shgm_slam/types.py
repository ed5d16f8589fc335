"""Core data types shared by every stage: intrinsics, frames, the sequence protocol, graph arrays.

Conventions (see ARCHITECTURE.md): poses are 4x4 float64 ``T_to_from``; the camera frame is KITTI's
(x right, y down, z forward); depth is metres (float32, 0 or non-finite = invalid); labels are
Cityscapes train ids (uint8, 255 = ignore).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Protocol, runtime_checkable

import numpy as np

Pose = np.ndarray
"""(4, 4) float64 rigid transform ``T_to_from``."""
Poses = np.ndarray
"""(N, 4, 4) float64 stack of rigid transforms."""
PointsXYZ = np.ndarray
"""(N, 3) float64/float32 points, frame given by the variable name."""


class DepthOrigin(str, Enum):
    """Where a sequence's depth comes from: it decides the odometry and whether the depth is rescaled."""

    MEASURED = "measured"  # a sensor or a renderer: KISS-ICP on it, never rescaled
    PREDICTED = "predicted"  # a network: visual odometry by default, scaled to the camera height above the road


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an undistorted camera, pixels.

    ``width``/``height`` are the image size the intrinsics belong to.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size_wh(self) -> tuple[int, int]:
        return (self.width, self.height)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics of the same camera resampled to ``width`` x ``height`` pixels."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, width, height
        )

    @staticmethod
    def from_K(K: np.ndarray, width: int, height: int) -> Intrinsics:
        """Build from a (3, 3) or (3, 4) projection matrix (KITTI ``P`` lines)."""
        K = np.asarray(K, dtype=np.float64)
        return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))


@dataclass
class Frame:
    """One camera frame of a sequence, loaded on demand.

    Attributes:
        index: frame index inside its sequence (after any frame-range slicing: 0-based).
        timestamp_s: time in seconds.
        intrinsics: pinhole intrinsics of ``image_rgb``.
        image_rgb: (H, W, 3) uint8 RGB (grayscale sequences are replicated to 3 channels).
        depth_m: (H, W) float32 metric depth, 0 = invalid; None when the sequence has no depth.
        label_ids: (H, W) uint8 Cityscapes train ids; None when the sequence has no labels.
        T_world_cam: (4, 4) ground-truth pose, or None when the sequence has no ground truth.
        source_index: index of the frame in the underlying files (before frame-range slicing).
        T_odom_cam: (4, 4) the robot's own odometry's pose (camera -> its odometry frame, metres), given with the
            frame (``OdometryKind.GIVEN``), or None.
    """

    index: int
    timestamp_s: float
    intrinsics: Intrinsics
    image_rgb: np.ndarray | None = None
    depth_m: np.ndarray | None = None
    label_ids: np.ndarray | None = None
    T_world_cam: np.ndarray | None = None
    source_index: int = -1
    T_odom_cam: np.ndarray | None = None


@runtime_checkable
class Sequence(Protocol):
    """A camera sequence: a sized, indexable source of ``Frame`` objects that loads frames lazily.

    ``gt_poses`` is (N, 4, 4) ``T_world_cam`` or None; ``timestamps_s`` is (N,) seconds.
    ``has_depth``/``has_labels`` tell whether frames carry ``depth_m``/``label_ids``.
    """

    name: str
    intrinsics: Intrinsics

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> Frame: ...

    @property
    def timestamps_s(self) -> np.ndarray: ...

    @property
    def gt_poses(self) -> np.ndarray | None: ...

    @property
    def has_depth(self) -> bool: ...

    @property
    def has_labels(self) -> bool: ...


MAX_COORDINATE_M = 1e9
"""Graph node coordinates beyond this (metres) are refused (graph files, ``GraphArrays`` given to a match): distances
and fits would overflow to inf."""

MIN_GRAPH_EXTENT_M = 1.0
"""A graph of three or more nodes that spans less than this, metres, along every axis is refused (graph files,
``GraphArrays`` given to a match): objects of a street lie metres apart, so its positions are in other units
(latitude and longitude in degrees span ~0.002 over 200 m), which would match nothing, or anything, without a word."""


def extent_problem(positions_xyz: np.ndarray) -> str | None:
    """Why (N, 3) graph node positions cannot be metres (``MIN_GRAPH_EXTENT_M``), or None."""
    if positions_xyz.shape[0] < 3:
        return None
    extent = float(np.ptp(positions_xyz, axis=0).max())
    if extent >= MIN_GRAPH_EXTENT_M:
        return None
    return (f"its {positions_xyz.shape[0]} nodes span only {extent:.3g} along every axis, where a street's objects "
            "lie metres apart: positions must be metres in a local frame (latitude and longitude? project them to "
            "UTM or a local east-north-up frame first)")  # fmt: skip


@dataclass
class GraphArrays:
    """Array view of a semantic graph, what descriptors and matching consume.

    Attributes:
        node_ids: (N,) int64 stable node ids (ids in graph files and match results).
        label_ids: (N,) int64 Cityscapes train ids.
        positions_xyz: (N, 3) float64 node positions in the graph's world frame, metres.
        sizes: (N,) float64 object size (pixel count or accumulated observations); weights Eq. 2.
        edges: (E, 2) int64 undirected edges as *row indices* into the arrays above, i < j.
    """

    node_ids: np.ndarray
    label_ids: np.ndarray
    positions_xyz: np.ndarray
    sizes: np.ndarray
    edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))

    def __len__(self) -> int:
        return int(self.node_ids.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edges.shape[0])

    def subset(self, rows: np.ndarray) -> GraphArrays:
        """The induced subgraph on ``rows`` (row indices or a boolean mask); edges are re-indexed."""
        rows = np.flatnonzero(rows) if np.asarray(rows).dtype == bool else np.asarray(rows, dtype=np.int64)
        remap = np.full(len(self), -1, dtype=np.int64)
        remap[rows] = np.arange(rows.size)
        e = remap[self.edges] if self.edges.size else np.zeros((0, 2), dtype=np.int64)
        e = e[(e >= 0).all(axis=1)] if e.size else e.reshape(0, 2)
        return GraphArrays(
            self.node_ids[rows], self.label_ids[rows], self.positions_xyz[rows], self.sizes[rows], e
        )

    def transformed(self, T_new_old: np.ndarray) -> GraphArrays:
        """The same graph with positions mapped by the (4, 4) transform ``T_new_old``."""
        T = np.asarray(T_new_old, dtype=np.float64)
        p = self.positions_xyz @ T[:3, :3].T + T[:3, 3]
        return GraphArrays(self.node_ids.copy(), self.label_ids.copy(), p, self.sizes.copy(), self.edges.copy())
