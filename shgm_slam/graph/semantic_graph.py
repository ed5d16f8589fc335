"""The incremental semantic graph of one robot (Sec. III-A): nodes anchored to keyframes, merges, edges.

Each node is an object (label + 3D centre). A node is *anchored* to the keyframe that first saw it:
its position is stored in that keyframe's camera frame, so when the pose graph corrects keyframe
poses (``set_keyframe_poses``) the nodes move with them. A new observation merges into the nearest
node of the same label closer than ``merge_radius_m`` (paper: "nodes with the same semantic label
should be merged if they are highly close"; authors: 5 m) as a running mean in the anchor frame,
otherwise it becomes a new node. Edges join nodes closer than ``connectivity_m`` (paper: 10 m best).

Incremental cost: a hash grid of cell size max(connectivity, merge radius) over world positions finds
the nodes near a keyframe's objects, so merges and edge updates touch only the changed nodes and
their neighbourhoods; ``set_keyframe_poses`` moves everything and rebuilds grid and edges once.

The robot -> map-server boundary is ``GraphUpdate``: the keyframe pose and the full state of every
new or updated node. ``SemanticGraph.apply_update`` rebuilds an identical graph from these messages.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from shgm_slam.errors import GraphError
from shgm_slam.geometry.se3 import inverse
from shgm_slam.graph.extraction import ObjectObservations
from shgm_slam.types import GraphArrays

_CELL_BITS = 21  # cell coordinates packed into one int64 key: +-2^20 cells per axis
_CELL_OFFSETS = np.stack(np.meshgrid(*([np.arange(-1, 2)] * 3), indexing="ij"), -1).reshape(-1, 3)
_NOT_IN_GRID = -1
_PAIR_CHUNK = 1 << 18  # node pairs whose distance ``_pairs_near`` measures at once (bounds its memory: ~10 MB)


def _cell_keys(cells: np.ndarray) -> np.ndarray:
    """Pack (..., 3) integer cell coordinates into (...) int64 keys (>= 0)."""
    c = cells + (1 << (_CELL_BITS - 1))
    return (c[..., 0] << (2 * _CELL_BITS)) | (c[..., 1] << _CELL_BITS) | c[..., 2]


def _edge_keys(a: np.ndarray, b: np.ndarray) -> list[int]:
    """Edge keys ``min << 32 | max`` of row pairs (a, b)."""
    return ((np.minimum(a, b) << 32) | np.maximum(a, b)).tolist()


def edges_within_radius(positions_xyz: np.ndarray, radius_m: float) -> np.ndarray:
    """All pairs of points closer than ``radius_m`` (strictly).

    Args:
        positions_xyz: (N, 3) points, metres.
        radius_m: connectivity threshold, metres.

    Returns:
        (E, 2) int64 row-index pairs, i < j, sorted lexicographically.
    """
    p = np.asarray(positions_xyz, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = cKDTree(p).query_pairs(radius_m, output_type="ndarray").astype(np.int64)
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = pairs[np.linalg.norm(p[pairs[:, 0]] - p[pairs[:, 1]], axis=1) < radius_m]
    pairs = np.sort(pairs, axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


@dataclass(frozen=True)
class NodeState:
    """Full state of one node, as sent from a robot to the map server (plain, JSON-friendly values).

    ``position_kf`` is the node position (x, y, z metres) in the camera frame of keyframe ``anchor_kf``;
    ``size`` is the accumulated pixel count; ``num_observations`` counts the keyframes that saw it.
    """

    node_id: int
    label_id: int
    anchor_kf: int
    position_kf: tuple[float, float, float]
    size: float
    num_observations: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.node_id, "label": self.label_id, "anchor_kf": self.anchor_kf,
            "position_kf": list(self.position_kf), "size": self.size,
            "num_observations": self.num_observations,
        }  # fmt: skip

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> NodeState:
        try:
            x, y, z = (float(v) for v in d["position_kf"])
            return NodeState(
                int(d["id"]), int(d["label"]), int(d["anchor_kf"]), (x, y, z), float(d["size"]),
                int(d["num_observations"]),
            )  # fmt: skip
        except (KeyError, TypeError, ValueError) as exc:
            raise GraphError(f"malformed node state {dict(d)!r}: {exc!r}") from None


@dataclass(frozen=True, eq=False)
class GraphUpdate:
    """What one keyframe changed in a robot's graph: the message a front end sends to the map server.

    Attributes:
        kf_id: the keyframe's id.
        T_world_kf: (4, 4) keyframe pose (camera -> robot world) used when the update was made.
        new_nodes: nodes first seen (and anchored) at this keyframe.
        updated_nodes: existing nodes this keyframe re-observed (merged), with their new state.
    """

    kf_id: int
    T_world_kf: np.ndarray
    new_nodes: tuple[NodeState, ...]
    updated_nodes: tuple[NodeState, ...]

    @property
    def observed_node_ids(self) -> list[int]:
        """Ids of every node this keyframe observed (new and merged)."""
        return [s.node_id for s in self.new_nodes] + [s.node_id for s in self.updated_nodes]

    def to_dict(self) -> dict[str, Any]:
        return {
            "kf_id": self.kf_id,
            "T_world_kf": np.asarray(self.T_world_kf, dtype=np.float64).tolist(),
            "new_nodes": [s.to_dict() for s in self.new_nodes],
            "updated_nodes": [s.to_dict() for s in self.updated_nodes],
        }

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> GraphUpdate:
        try:
            T = np.asarray(d["T_world_kf"], dtype=np.float64)
            new = tuple(NodeState.from_dict(s) for s in d["new_nodes"])
            upd = tuple(NodeState.from_dict(s) for s in d["updated_nodes"])
            kf_id = int(d["kf_id"])
        except (KeyError, TypeError, ValueError) as exc:
            raise GraphError(f"malformed graph update: {exc!r}") from None
        return GraphUpdate(kf_id, T, new, upd)


@dataclass(frozen=True, eq=False)
class GraphState:
    """Everything a ``SemanticGraph`` holds, as plain arrays: what a map server's snapshot stores.
    ``SemanticGraph.from_state`` rebuilds a graph that behaves identically (same rows, edges, submaps).

    Attributes:
        merge_radius_m, connectivity_m: the graph's parameters (metres).
        next_node_id: the id the graph gives its next new node.
        node_ids: (N,) int64 in row order (creation order); label_ids: (N,) int64.
        anchor_slots: (N,) int64 index into ``kf_ids`` of each node's anchor keyframe.
        positions_kf: (N, 3) metres in the anchor keyframe's camera frame.
        positions_world: (N, 3) metres in the graph's world frame.
        sizes: (N,) accumulated pixel counts; num_observations: (N,) int64.
        kf_ids: (K,) int64 keyframe ids in insertion order; T_world_kf: (K, 4, 4) their poses.
        obs_rows, obs_slots: (M,) int64 observation log: node row seen from keyframe slot.
        edges: (E, 2) int64 row pairs i < j, sorted.
    """

    merge_radius_m: float
    connectivity_m: float
    next_node_id: int
    node_ids: np.ndarray
    label_ids: np.ndarray
    anchor_slots: np.ndarray
    positions_kf: np.ndarray
    positions_world: np.ndarray
    sizes: np.ndarray
    num_observations: np.ndarray
    kf_ids: np.ndarray
    T_world_kf: np.ndarray
    obs_rows: np.ndarray
    obs_slots: np.ndarray
    edges: np.ndarray


def _checked_state(s: GraphState) -> GraphState:
    """``s`` with every array in its dtype and shape, or ``GraphError`` naming the first inconsistency."""
    try:
        ids = np.asarray(s.node_ids, dtype=np.int64).reshape(-1)
        n = ids.size
        kf_ids = np.asarray(s.kf_ids, dtype=np.int64).reshape(-1)
        k = kf_ids.size
        out = GraphState(
            float(s.merge_radius_m), float(s.connectivity_m), int(s.next_node_id), ids,
            np.asarray(s.label_ids, dtype=np.int64).reshape(n),
            np.asarray(s.anchor_slots, dtype=np.int64).reshape(n),
            np.asarray(s.positions_kf, dtype=np.float64).reshape(n, 3),
            np.asarray(s.positions_world, dtype=np.float64).reshape(n, 3),
            np.asarray(s.sizes, dtype=np.float64).reshape(n),
            np.asarray(s.num_observations, dtype=np.int64).reshape(n),
            kf_ids, np.asarray(s.T_world_kf, dtype=np.float64).reshape(k, 4, 4),
            np.asarray(s.obs_rows, dtype=np.int64).reshape(-1), np.asarray(s.obs_slots, dtype=np.int64).reshape(-1),
            np.asarray(s.edges, dtype=np.int64).reshape(-1, 2),
        )  # fmt: skip
    except (TypeError, ValueError, OverflowError) as exc:
        raise GraphError(f"graph state arrays do not fit together: {exc}") from None
    floats = (out.positions_kf, out.positions_world, out.sizes, out.T_world_kf)
    problems = [
        (not all(np.isfinite(a).all() for a in floats), "non-finite positions, sizes or poses"),
        (np.unique(ids).size != n or np.unique(kf_ids).size != k, "repeated node or keyframe ids"),
        (n and int(ids.max()) >= out.next_node_id, "next_node_id not above every node id"),
        (((out.anchor_slots < 0) | (out.anchor_slots >= k)).any(), "an anchor keyframe slot out of range"),
        (out.obs_rows.size != out.obs_slots.size, "observation rows and slots differ in length"),
        (((out.obs_rows < 0) | (out.obs_rows >= n)).any() or ((out.obs_slots < 0) | (out.obs_slots >= k)).any(),
         "an observation out of range"),
        (((out.edges < 0) | (out.edges >= n)).any() or (out.edges[:, 0] >= out.edges[:, 1]).any(),
         "an edge out of range or not i < j"),
        (not (out.merge_radius_m >= 0 and out.connectivity_m > 0), "bad merge radius or connectivity"),
    ]  # fmt: skip
    for bad, what in problems:
        if bad:
            raise GraphError(f"graph state is inconsistent: {what}")
    return out


PoseLookup = Mapping[int, np.ndarray] | Sequence[np.ndarray] | np.ndarray | None
"""Keyframe poses by id: a mapping kf id -> (4, 4), or a list / (K, 4, 4) array indexed by kf id."""


def _lookup_pose(lookup: PoseLookup, kf_id: int, default: np.ndarray) -> np.ndarray:
    """Pose of ``kf_id`` from a mapping or an id-indexed list/array, else ``default``."""
    if lookup is None:
        return default
    if isinstance(lookup, Mapping):
        return lookup.get(kf_id, default)
    return lookup[kf_id] if 0 <= kf_id < len(lookup) else default


def _check_pose(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise GraphError(f"{what} must be a finite (4, 4) pose, got shape {T.shape}")
    return T


class SemanticGraph:
    """Incremental semantic graph of one robot (nodes anchored to keyframes, Sec. III-A).

    Args:
        merge_radius_m: a new object merges into the nearest same-label node closer than this (0: never).
        connectivity_m: nodes closer than this are joined by an edge.
        first_node_id: id of the first node created here (give robots disjoint id ranges if needed).
    """

    def __init__(self, merge_radius_m: float = 5.0, connectivity_m: float = 10.0, first_node_id: int = 0):
        if not (merge_radius_m >= 0 and connectivity_m > 0):
            raise GraphError(
                f"need merge_radius_m >= 0 and connectivity_m > 0, got {merge_radius_m} and {connectivity_m}"
            )
        self.merge_radius_m = float(merge_radius_m)
        self.connectivity_m = float(connectivity_m)
        self._cell_m = max(self.connectivity_m, self.merge_radius_m)
        self._next_id = int(first_node_id)
        # nodes (rows 0.._n-1 of capacity-doubling arrays)
        self._n = 0
        self._node_ids = np.zeros(0, np.int64)
        self._labels = np.zeros(0, np.int64)
        self._anchor_slot = np.zeros(0, np.int64)
        self._pos_kf = np.zeros((0, 3))
        self._pos_world = np.zeros((0, 3))
        self._sizes = np.zeros(0)
        self._num_obs = np.zeros(0, np.int64)
        self._cell_key = np.zeros(0, np.int64)  # grid cell key of each node, _NOT_IN_GRID before insertion
        self._row_of_id: dict[int, int] = {}
        # keyframes
        self._kf_slot: dict[int, int] = {}
        self._kf_ids: list[int] = []
        self._kf_poses = np.zeros((0, 4, 4))
        # observation log (node row, keyframe slot)
        self._obs_rows: list[np.ndarray] = []
        self._obs_slots: list[np.ndarray] = []
        # spatial hash and edges
        self._grid: dict[int, set[int]] = {}
        self._edge_keys: set[int] = set()  # row_i << 32 | row_j, i < j
        self._edges_sorted = np.zeros(0, np.int64)  # the edge keys at the last ``arrays()``, sorted...
        self._edges_added: set[int] = set()  # ...and the net changes since then
        self._edges_removed: set[int] = set()
        self._arrays_cache: GraphArrays | None = None
        self._version = 0

    # ------------------------------------------------------------------ queries
    def __len__(self) -> int:
        return self._n

    @property
    def version(self) -> int:
        """Bumped by every change of the nodes' positions, the nodes or the edges: equal versions of one
        graph, equal ``arrays``."""
        return self._version

    @property
    def num_edges(self) -> int:
        return len(self._edge_keys)

    @property
    def node_ids(self) -> np.ndarray:
        """(N,) int64 node ids in row order (creation order)."""
        return self._node_ids[: self._n].copy()

    @property
    def keyframe_ids(self) -> list[int]:
        """Keyframe ids in insertion order."""
        return list(self._kf_ids)

    def keyframe_pose(self, kf_id: int) -> np.ndarray:
        """(4, 4) current ``T_world_kf`` of a keyframe."""
        return self._kf_poses[self._slot(kf_id)].copy()

    def node_state(self, node_id: int) -> NodeState:
        """The current state of one node."""
        if node_id not in self._row_of_id:
            raise GraphError(f"node id {node_id} is not in this graph")
        return self._state(self._row_of_id[node_id])

    def anchor_keyframes(self, node_ids: Iterable[int]) -> np.ndarray:
        """(K,) int64 id of the keyframe each node is anchored to (the keyframe that first saw it)."""
        try:
            rows = [self._row_of_id[int(i)] for i in node_ids]
        except KeyError as exc:
            raise GraphError(f"node id {exc.args[0]} is not in this graph") from None
        kf_ids = np.asarray(self._kf_ids, dtype=np.int64)
        return kf_ids[self._anchor_slot[np.asarray(rows, dtype=np.int64)]] if rows else np.zeros(0, np.int64)

    def anchors(self) -> np.ndarray:
        """(N,) int64 id of the keyframe each node (row order) is anchored to: ``anchor_keyframes`` of all."""
        return np.asarray(self._kf_ids, dtype=np.int64)[self._anchor_slot[: self._n]]

    def arrays(self) -> GraphArrays:
        """The whole graph as arrays (positions in the world frame, edges as row indices i < j, sorted)."""
        if self._arrays_cache is None:
            n = self._n
            keys = self._sync_sorted_edges()
            edges = np.stack([keys >> 32, keys & 0xFFFFFFFF], axis=1).reshape(-1, 2)
            self._arrays_cache = GraphArrays(
                self._node_ids[:n].copy(), self._labels[:n].copy(), self._pos_world[:n].copy(),
                self._sizes[:n].copy(), edges,
            )  # fmt: skip
        c = self._arrays_cache
        return GraphArrays(
            c.node_ids.copy(), c.label_ids.copy(), c.positions_xyz.copy(), c.sizes.copy(), c.edges.copy()
        )

    def observed_rows(self, kf_ids: Iterable[int]) -> np.ndarray:
        """Sorted (M,) int64 rows (in ``arrays`` order) of the nodes *observed* from any of ``kf_ids``
        (anchored there or merged there)."""
        slots = np.array([self._slot(k) for k in kf_ids], dtype=np.int64)
        if not self._obs_rows or slots.size == 0:
            return np.zeros(0, np.int64)
        rows = np.concatenate(self._obs_rows)[np.isin(np.concatenate(self._obs_slots), slots)]
        return np.unique(rows).astype(np.int64)

    def submap(self, kf_ids: Iterable[int]) -> GraphArrays:
        """Induced subgraph of the nodes *observed* from any of ``kf_ids`` (``observed_rows``).

        Rows keep the graph's row order; edges are those of the whole graph between kept nodes.
        """
        return self.arrays().subset(self.observed_rows(kf_ids))

    def state(self) -> GraphState:
        """The whole graph as arrays (``GraphState``; copies)."""
        n, k = self._n, len(self._kf_ids)
        keys = self._sync_sorted_edges()
        empty = np.zeros(0, np.int64)
        return GraphState(
            self.merge_radius_m, self.connectivity_m, self._next_id, self._node_ids[:n].copy(),
            self._labels[:n].copy(), self._anchor_slot[:n].copy(), self._pos_kf[:n].copy(),
            self._pos_world[:n].copy(), self._sizes[:n].copy(), self._num_obs[:n].copy(),
            np.asarray(self._kf_ids, dtype=np.int64), self._kf_poses[:k].copy(),
            np.concatenate(self._obs_rows) if self._obs_rows else empty,
            np.concatenate(self._obs_slots) if self._obs_slots else empty,
            np.stack([keys >> 32, keys & 0xFFFFFFFF], axis=1).reshape(-1, 2),
        )  # fmt: skip

    @classmethod
    def from_state(cls, state: GraphState) -> SemanticGraph:
        """Rebuild a graph from ``state()`` (e.g. read back from a snapshot).

        Raises:
            GraphError: the arrays are inconsistent (shapes, ranges, non-finite values, repeated ids).
        """
        s = _checked_state(state)
        g = cls(s.merge_radius_m, s.connectivity_m, s.next_node_id)
        g._n = n = s.node_ids.size
        g._node_ids, g._labels, g._anchor_slot = s.node_ids.copy(), s.label_ids.copy(), s.anchor_slots.copy()
        g._pos_kf, g._pos_world, g._sizes = s.positions_kf.copy(), s.positions_world.copy(), s.sizes.copy()
        g._num_obs = s.num_observations.copy()
        g._row_of_id = {i: r for r, i in enumerate(s.node_ids.tolist())}
        g._kf_ids = s.kf_ids.tolist()
        g._kf_slot = {kf: slot for slot, kf in enumerate(g._kf_ids)}
        g._kf_poses = s.T_world_kf.copy()
        if s.obs_rows.size:
            g._obs_rows, g._obs_slots = [s.obs_rows.copy()], [s.obs_slots.copy()]
        g._cell_key = np.zeros(n, np.int64)
        g._index_grid(n)
        g._edges_sorted = np.sort((s.edges[:, 0] << 32) | s.edges[:, 1])
        g._edge_keys = set(g._edges_sorted.tolist())
        return g

    # ------------------------------------------------------------------ building
    def add_keyframe(self, kf_id: int, T_world_kf: np.ndarray, objects: ObjectObservations) -> GraphUpdate:
        """Insert one keyframe's objects; merge each into a close same-label node or create a node.

        Args:
            kf_id: new keyframe id (unique in this graph).
            T_world_kf: (4, 4) keyframe camera pose in the robot's world frame.
            objects: objects seen from the keyframe; ``objects.centroids_cam`` are in its camera frame.

        Returns:
            The update message (keyframe pose, new and merged node states), already applied here.
        """
        T = _check_pose(T_world_kf, f"pose of keyframe {kf_id}")
        if kf_id in self._kf_slot:
            raise GraphError(f"keyframe {kf_id} was already added to this graph; keyframe ids must be unique")
        M = len(objects)
        p_kf = np.asarray(objects.centroids_cam, dtype=np.float64).reshape(M, 3)
        p_world = p_kf @ T[:3, :3].T + T[:3, 3]
        labels = np.asarray(objects.label_ids, dtype=np.int64)
        pix = np.asarray(objects.pixel_counts, dtype=np.float64)

        # 1. nearest same-label existing node within the merge radius (vectorized over objects)
        target = np.full(M, -1, dtype=np.int64)
        cand = self._candidate_rows(p_world) if M else np.zeros(0, np.int64)
        if cand.size and self.merge_radius_m > 0:
            d = np.linalg.norm(p_world[:, None, :] - self._pos_world[cand][None], axis=2)
            d[labels[:, None] != self._labels[cand][None]] = np.inf
            best = np.argmin(d, axis=1)
            hit = d[np.arange(M), best] < self.merge_radius_m
            target[hit] = cand[best[hit]]

        # 2. the rest become new nodes; same-label objects of this keyframe within the radius share one
        fresh = np.flatnonzero(target < 0)
        fresh = fresh[np.argsort(-pix[fresh], kind="stable")]  # biggest objects found nodes first
        d = np.linalg.norm(p_kf[fresh][:, None] - p_kf[fresh][None], axis=2)
        close = ((d < self.merge_radius_m) & (labels[fresh][:, None] == labels[fresh][None])).tolist()
        leaders: list[int] = []  # positions in ``fresh`` of the objects that created a node
        for a in range(fresh.size):  # greedy, in Python: a keyframe has few objects
            leader = next((b for b in leaders if close[a][b]), None)
            if leader is None:
                leaders.append(a)
                target[fresh[a]] = self._n + len(leaders) - 1
            else:
                target[fresh[a]] = target[fresh[leader]]

        # 3. running means in each node's anchor frame
        rows, inv = np.unique(target, return_inverse=True)
        is_new = rows >= self._n
        old = rows[~is_new]
        T_anchor = np.broadcast_to(T, (rows.size, 4, 4)).copy()
        T_anchor[~is_new] = self._kf_poses[self._anchor_slot[old]]
        T_anchor_world = inverse(T_anchor)[inv]
        p_anchor = np.einsum("mij,mj->mi", T_anchor_world[:, :3, :3], p_world) + T_anchor_world[:, :3, 3]
        cnt = np.bincount(inv, minlength=rows.size)
        p_sum = np.stack([np.bincount(inv, p_anchor[:, k], minlength=rows.size) for k in range(3)], 1)
        size_sum = np.bincount(inv, pix, minlength=rows.size)
        n_prev = np.zeros(rows.size, np.int64)
        pos_prev = np.zeros((rows.size, 3))
        size_prev = np.zeros(rows.size)
        n_prev[~is_new], pos_prev[~is_new] = self._num_obs[old], self._pos_kf[old]
        size_prev[~is_new] = self._sizes[old]
        pos_new = (pos_prev * n_prev[:, None] + p_sum) / (n_prev + cnt)[:, None]
        label_of_row = np.zeros(rows.size, np.int64)
        label_of_row[inv] = labels

        new_states, upd_states = [], []
        for k, r in enumerate(rows.tolist()):
            if is_new[k]:
                nid, anchor = self._next_id + (r - self._n), kf_id
            else:
                nid, anchor = int(self._node_ids[r]), self._kf_ids[self._anchor_slot[r]]
            state = NodeState(
                nid, int(label_of_row[k]), int(anchor), tuple(pos_new[k].tolist()),
                float(size_prev[k] + size_sum[k]), int(n_prev[k] + cnt[k]),
            )  # fmt: skip
            (new_states if is_new[k] else upd_states).append(state)
        update = GraphUpdate(int(kf_id), T.copy(), tuple(new_states), tuple(upd_states))
        self.apply_update(update)
        return update

    def apply_update(self, update: GraphUpdate, T_world_kfs: PoseLookup = None) -> None:
        """Apply a ``GraphUpdate`` (e.g. a robot's message on the map server): register the keyframe and
        insert or overwrite the node states it carries, then refresh edges around them.

        Args:
            update: the message; node states are upserted by id.
            T_world_kfs: optional keyframe-pose lookup overriding ``update.T_world_kf``, e.g. the server's
                poses: a mapping kf id -> (4, 4), or a list / (K, 4, 4) array indexed by kf id. Keyframes
                the lookup lacks use the message's pose.
        """
        kf_id = int(update.kf_id)
        if kf_id in self._kf_slot:
            raise GraphError(f"keyframe {kf_id} is already in this graph; was the update applied twice?")
        T = _check_pose(_lookup_pose(T_world_kfs, kf_id, update.T_world_kf), f"pose of keyframe {kf_id}")
        states = list(update.new_nodes) + list(update.updated_nodes)
        for s in states:  # validate everything before changing anything
            if s.anchor_kf != kf_id and s.anchor_kf not in self._kf_slot:
                raise GraphError(
                    f"update of keyframe {kf_id}: node {s.node_id} is anchored to unknown keyframe "
                    f"{s.anchor_kf}; apply a robot's updates in order"
                )
        slot = self._add_keyframe_slot(kf_id, T)
        rows = np.array([self._upsert_row(s) for s in states], dtype=np.int64)
        if rows.size:
            self._obs_rows.append(rows)
            self._obs_slots.append(np.full(rows.size, slot, np.int64))
        self._refresh_rows(rows)

    def set_keyframe_poses(self, kf_ids: Iterable[int], T_world_kfs: np.ndarray) -> None:
        """Replace keyframe poses (e.g. pose-graph corrections); nodes move with their anchor keyframes.

        Args:
            kf_ids: K keyframe ids already in the graph.
            T_world_kfs: (K, 4, 4) their new poses. Edges and the spatial grid are rebuilt once.
        """
        ids = list(kf_ids)
        T = np.asarray(T_world_kfs, dtype=np.float64)
        if T.shape != (len(ids), 4, 4) or not np.isfinite(T).all():
            raise GraphError(f"need finite ({len(ids)}, 4, 4) poses for the keyframe ids, got {T.shape}")
        slots = np.array([self._slot(k) for k in ids], dtype=np.int64)
        self._kf_poses[slots] = T
        self._rebuild()

    # ------------------------------------------------------------------ internals
    def _slot(self, kf_id: int) -> int:
        try:
            return self._kf_slot[int(kf_id)]
        except KeyError:
            raise GraphError(f"keyframe {kf_id} is not in this graph (add it with add_keyframe)") from None

    def _state(self, r: int) -> NodeState:
        return NodeState(
            int(self._node_ids[r]), int(self._labels[r]), self._kf_ids[self._anchor_slot[r]],
            tuple(self._pos_kf[r].tolist()), float(self._sizes[r]), int(self._num_obs[r]),
        )  # fmt: skip

    def _add_keyframe_slot(self, kf_id: int, T: np.ndarray) -> int:
        slot = len(self._kf_ids)
        if slot == self._kf_poses.shape[0]:
            grown = np.zeros((max(16, 2 * slot), 4, 4))
            grown[:slot] = self._kf_poses
            self._kf_poses = grown
        self._kf_poses[slot] = T
        self._kf_slot[kf_id] = slot
        self._kf_ids.append(kf_id)
        return slot

    def _grow(self) -> None:
        cap = max(64, 2 * self._node_ids.shape[0])

        def grow(a: np.ndarray) -> np.ndarray:
            g = np.zeros((cap, *a.shape[1:]), dtype=a.dtype)
            g[: a.shape[0]] = a
            return g

        self._node_ids, self._labels = grow(self._node_ids), grow(self._labels)
        self._anchor_slot, self._pos_kf = grow(self._anchor_slot), grow(self._pos_kf)
        self._pos_world, self._cell_key = grow(self._pos_world), grow(self._cell_key)
        self._sizes, self._num_obs = grow(self._sizes), grow(self._num_obs)

    def _upsert_row(self, s: NodeState) -> int:
        r = self._row_of_id.get(s.node_id)
        if r is None:
            if self._n == self._node_ids.shape[0]:
                self._grow()
            r = self._n
            self._n += 1
            self._row_of_id[s.node_id] = r
            self._node_ids[r] = s.node_id
            self._cell_key[r] = _NOT_IN_GRID
            self._next_id = max(self._next_id, s.node_id + 1)
        self._labels[r] = s.label_id
        self._anchor_slot[r] = self._kf_slot[s.anchor_kf]
        self._pos_kf[r] = s.position_kf
        self._sizes[r] = s.size
        self._num_obs[r] = s.num_observations
        return r

    def _world_positions(self, rows: np.ndarray) -> np.ndarray:
        T = self._kf_poses[self._anchor_slot[rows]]
        return np.einsum("nij,nj->ni", T[:, :3, :3], self._pos_kf[rows]) + T[:, :3, 3]

    def _candidate_rows(self, points_world: np.ndarray) -> np.ndarray:
        """Rows of grid nodes in the 3x3x3 cells around each point (superset of all within one cell size)."""
        cells = np.floor(points_world / self._cell_m).astype(np.int64)
        keys = np.unique(_cell_keys(cells[:, None, :] + _CELL_OFFSETS[None]))
        found = [s for s in map(self._grid.get, keys.tolist()) if s]
        if not found:
            return np.zeros(0, np.int64)
        return np.fromiter((r for s in found for r in s), dtype=np.int64)

    def _pairs_near(self, rows: np.ndarray, points_world: np.ndarray) -> list[int]:
        """Edge keys between ``rows`` (at ``points_world``) and grid nodes closer than the connectivity."""
        cand = self._candidate_rows(points_world)
        p_cand = self._pos_world[cand]
        step = max(1, _PAIR_CHUNK // max(1, cand.size))  # rows per chunk: many nodes in one place stay in memory
        keys: list[int] = []
        for i in range(0, rows.size, step):
            d = np.linalg.norm(points_world[i : i + step, None, :] - p_cand[None], axis=2)
            ii, jj = np.nonzero((d < self.connectivity_m) & (rows[i : i + step, None] != cand[None]))
            keys += _edge_keys(rows[i + ii], cand[jj])
        return keys

    def _refresh_rows(self, rows: np.ndarray) -> None:
        """Move the changed ``rows`` to their new world positions: grid cells and incident edges.

        Edges are a pure function of positions, so a moved node's old edges are found geometrically
        at the old positions (all still in ``_pos_world``) and its new edges at the new ones.
        """
        self._arrays_cache = None
        self._version += 1
        if rows.size == 0:
            return
        old = rows[self._cell_key[rows] != _NOT_IN_GRID]
        if old.size:
            self._remove_edges(self._pairs_near(old, self._pos_world[old]))
        p = self._world_positions(rows)
        self._pos_world[rows] = p
        new_keys = _cell_keys(np.floor(p / self._cell_m).astype(np.int64))
        moves = zip(rows.tolist(), self._cell_key[rows].tolist(), new_keys.tolist(), strict=True)
        for r, before, after in moves:
            if before != after:
                if before != _NOT_IN_GRID:
                    cell = self._grid[before]
                    cell.discard(r)
                    if not cell:
                        del self._grid[before]
                self._grid.setdefault(after, set()).add(r)
        self._cell_key[rows] = new_keys
        self._add_edges(self._pairs_near(rows, p))

    def _rebuild(self) -> None:
        """Recompute every world position, the grid and all edges (after pose corrections)."""
        n = self._n
        self._arrays_cache = None
        self._version += 1
        p = self._world_positions(np.arange(n)) if n else np.zeros((0, 3))
        self._pos_world[:n] = p
        self._index_grid(n)
        edges = edges_within_radius(p, self.connectivity_m)
        self._edges_sorted = (edges[:, 0] << 32) | edges[:, 1]  # lexsorted rows -> sorted keys
        self._edge_keys = set(self._edges_sorted.tolist())
        self._edges_added, self._edges_removed = set(), set()

    def _index_grid(self, n: int) -> None:
        """Put the first ``n`` rows into the spatial hash grid by their world positions (from scratch)."""
        keys = _cell_keys(np.floor(self._pos_world[:n] / self._cell_m).astype(np.int64))
        self._cell_key[:n] = keys
        order = np.argsort(keys, kind="stable")
        uniq, starts = np.unique(keys[order], return_index=True)
        groups = np.split(order, starts[1:]) if n else []
        self._grid = {k: set(g.tolist()) for k, g in zip(uniq.tolist(), groups, strict=True)}

    def _remove_edges(self, keys: list[int]) -> None:
        gone = set(keys)
        self._edge_keys -= gone
        undo = gone & self._edges_added
        self._edges_added -= undo
        self._edges_removed |= gone - undo

    def _add_edges(self, keys: list[int]) -> None:
        new = set(keys) - self._edge_keys
        self._edge_keys |= new
        undo = new & self._edges_removed
        self._edges_removed -= undo
        self._edges_added |= new - undo

    def _sync_sorted_edges(self) -> np.ndarray:
        """Sorted (E,) edge keys, patched from the last sorted copy with the net changes (O(E) merges)."""
        keys = self._edges_sorted
        if self._edges_removed:
            gone = np.fromiter(self._edges_removed, dtype=np.int64, count=len(self._edges_removed))
            keys = keys[~np.isin(keys, gone)]
        if self._edges_added:
            new = np.sort(np.fromiter(self._edges_added, dtype=np.int64, count=len(self._edges_added)))
            keys = np.sort(np.concatenate([keys, new]), kind="stable")  # merges two sorted runs
        self._edges_sorted = keys
        self._edges_added, self._edges_removed = set(), set()
        return keys
