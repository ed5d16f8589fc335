"""The map server: mirrors every agent's graph from messages, matches agents, fuses them in iSAM2."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from shgm_slam.backend.confirmation import AgentPlacement, Placement, Support, placements
from shgm_slam.backend.pose_graph import PoseGraphState, make_pose_graph
from shgm_slam.config import ShgmConfig
from shgm_slam.descriptors import compute_descriptors
from shgm_slam.errors import BackendError, ConfigError
from shgm_slam.geometry import se3
from shgm_slam.geometry.ground import rotation_to_z
from shgm_slam.graph.semantic_graph import GraphState, SemanticGraph
from shgm_slam.matching import match_graphs
from shgm_slam.messages import KeyframeMessage
from shgm_slam.server.closures import SurfaceOffset, local_closures
from shgm_slam.server.records import MatchRecord
from shgm_slam.types import GraphArrays

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class MapServerState:
    """Everything a ``MapServer`` holds (``MapServer.state``, what a snapshot stores);
    ``MapServer.from_state`` rebuilds a server that matches, votes and answers as this one would.

    Attributes:
        agents: every agent in the order the server learnt of them (the reference first).
        graphs: agent -> its mirrored semantic graph.
        T_odom_kf: agent -> (K, 4, 4) keyframe poses in its odometry frame, as received.
        up: agent -> (3,) "up" in its odometry frame, or None.
        since_match: agent -> keyframes received since its last match.
        matches: every match attempt so far (the match log).
        closures: accepted closure keys ``(agent_a, kf_a, agent_b, kf_b)``.
        step, num_matches: keyframes received and successful matches so far.
        timings_ms: ``"match"`` / ``"backend"`` -> wall times so far, milliseconds.
        pose_graph: the pose graph's decisions and estimate.
        support: closure id -> agent -> the node ids behind it (confirmation of placements).
        surface_offset: the fleet's surface-to-centre offset estimate (``closures.SurfaceOffset.state``).
    """

    agents: tuple[str, ...]
    graphs: dict[str, GraphState]
    T_odom_kf: dict[str, np.ndarray]
    up: dict[str, np.ndarray | None]
    since_match: dict[str, int]
    matches: tuple[MatchRecord, ...]
    closures: tuple[tuple[str, int, str, int], ...]
    step: int
    num_matches: int
    timings_ms: dict[str, list[float]]
    pose_graph: PoseGraphState
    support: dict[int, dict[str, frozenset[int]]] = field(default_factory=dict)
    surface_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


class MapServer:
    """Mirrors every robot's graph from messages, matches robots periodically, fuses them in iSAM2.

    Every ``match_every_keyframes`` keyframes of a robot r, r's recent submap and r's whole graph are
    matched against every other robot's whole graph (robots here are agents: a robot's trajectory
    segments after odometry failures are agents of their own, added at run time); accepted matches become inter-robot
    relative-pose factors between keyframes. Shared frame = the first robot's odometry frame.

    Loop closure (``backend.loop_closure``): r's recent submap is also matched against r's *own* older
    graph (query ``"loop"``), with the same matching, verification and closure cutting; accepted
    closures join two keyframes of r in the pose graph. The older graph leaves out the stretch r just
    drove (``loop_exclusion_m``): objects seen from the submap lie within r's object range of it, so
    only nodes first seen from keyframes more than two object ranges of path (and at least a submap's
    worth of keyframes) before the submap can be shared with it through a revisit, never through the
    pass that is still in view.
    """

    def __init__(self, robot_names: list[str], cfg: ShgmConfig) -> None:
        if not robot_names:
            raise ConfigError("the map server needs at least the reference robot (whose frame is the shared frame)")
        self.cfg = cfg
        self._agents = list(robot_names)
        self._pose_graph = make_pose_graph(self._agents, cfg.backend)
        self._graphs = {r: SemanticGraph(cfg.graph.merge_radius_m, cfg.graph.connectivity_m) for r in robot_names}
        # the one home of keyframe poses on the server: each agent's keyframes in its odometry frame
        self._T_odom_kf: dict[str, list[np.ndarray]] = {r: [] for r in robot_names}
        self._path_m: dict[str, list[float]] = {r: [] for r in robot_names}  # odometry path length per keyframe
        self._up: dict[str, np.ndarray | None] = dict.fromkeys(robot_names)
        self._matches: list[MatchRecord] = []
        self._since_match = dict.fromkeys(robot_names, 0)
        self._closures: set[tuple[str, int, str, int]] = set()
        self._step = 0
        self._num_matches = 0  # successful graph matches so far (each closure's evidence id)
        self._surface_offset = SurfaceOffset()  # how far solid objects' centres lie behind what cameras see
        self._support: dict[int, Support] = {}  # closure id -> the matched objects (node ids) behind it
        self._placements: tuple[int, dict[str, AgentPlacement]] = (-1, {})  # (pose-graph version, cache)
        self.timings_ms: dict[str, list[float]] = {"match": [], "backend": []}

    def add_agent(self, agent: str) -> None:
        """Start mirroring a new agent (a robot's later trajectory segment): its own graph, unanchored
        in the pose graph, matched like any robot against every other agent, its robot's too."""
        self._pose_graph.add_robot(agent)
        self._agents.append(agent)
        self._graphs[agent] = SemanticGraph(self.cfg.graph.merge_radius_m, self.cfg.graph.connectivity_m)
        self._T_odom_kf[agent] = []
        self._path_m[agent] = []
        self._up[agent] = None
        self._since_match[agent] = 0

    def receive(self, msg: KeyframeMessage) -> list[MatchRecord]:
        """Ingest one keyframe message (a new agent is added on its first); returns the match attempts it
        triggered (possibly none).

        Idempotent: a keyframe the server already holds (a re-sent message) is ignored, and so is one
        that skips ahead (an earlier one was lost; the robot re-sends from ``received(agent)``).
        """
        if msg.kf_index != self.received(msg.robot):
            log.debug("%s keyframe %d ignored (the server holds %d)", msg.robot, msg.kf_index, self.received(msg.robot))
            return []
        t0 = time.perf_counter()
        self._step += 1
        if msg.robot not in self._graphs:
            self.add_agent(msg.robot)
        self._append_keyframe(msg.robot, msg.T_odom_kf)
        if msg.up_odom is not None:
            self._up[msg.robot] = msg.up_odom
        self._pose_graph.add_keyframe(msg.robot, msg.kf_index, msg.T_odom_kf)
        self._graphs[msg.robot].apply_update(msg.graph_update, self._T_odom_kf[msg.robot])
        self.timings_ms["backend"].append((time.perf_counter() - t0) * 1e3)
        self._since_match[msg.robot] += 1
        if self._since_match[msg.robot] < self.cfg.backend.match_every_keyframes:
            return []
        self._since_match[msg.robot] = 0
        return self.match_robot(msg.robot)

    def _append_keyframe(self, agent: str, T_odom_kf: np.ndarray) -> None:
        """Record ``agent``'s next keyframe pose and its odometry path length."""
        poses, path = self._T_odom_kf[agent], self._path_m[agent]
        path.append(path[-1] + float(np.linalg.norm(T_odom_kf[:3, 3] - poses[-1][:3, 3])) if path else 0.0)
        poses.append(T_odom_kf)

    def finalize(self) -> list[MatchRecord]:
        """Match every robot once more at the end of the run (whole graphs)."""
        records: list[MatchRecord] = []
        for r in list(self._agents):
            records += self.match_robot(r, submap=False)
        return records

    def match_robot(self, robot: str, *, submap: bool = True) -> list[MatchRecord]:
        """Match ``robot``'s recent submap and whole graph against every other robot's whole graph, and
        (loop closure) its recent submap against its own older graph."""
        records = []
        queries: list[tuple[str, GraphArrays]] = []
        n_kf = len(self._T_odom_kf[robot])
        if submap and n_kf > self.cfg.backend.submap_keyframes:
            kfs = np.arange(n_kf - self.cfg.backend.submap_keyframes, n_kf)
            queries.append(("submap", self._graphs[robot].submap(kfs)))
            if self.cfg.backend.loop_closure:
                loop = self._loop_query(robot, queries[0][1])
                if loop is not None:
                    records.append(self._match_pair(robot, robot, "loop", *loop))
        queries.append(("whole", self._graphs[robot].arrays()))
        for other in list(self._agents):
            if other == robot or len(self._graphs[other]) == 0:
                continue
            graph_a = self._graphs[other].arrays()
            desc_a = compute_descriptors(graph_a, self.cfg.descriptor)
            for query, graph_b in queries:
                records.append(self._match_pair(other, robot, query, graph_a, graph_b, desc_a))
        self._matches += records
        return records

    def loop_exclusion_m(self, robot: str) -> float:
        """Metres of path before its submap whose keyframes ``robot``'s loop query leaves out of its older graph:
        twice the robot's object range (the 95th percentile distance from a node to the keyframe that first
        saw it; the fleet's extraction depth until the graph has nodes)."""
        graph = self._graphs[robot].arrays()
        if len(graph) == 0:
            return 2.0 * float(self.cfg.extraction.filled().max_depth_m)
        anchors = self._graphs[robot].anchor_keyframes(graph.node_ids)
        origins = np.stack([self._T_odom_kf[robot][k][:3, 3] for k in anchors])
        return 2.0 * float(np.percentile(np.linalg.norm(graph.positions_xyz - origins, axis=1), 95))

    def _loop_query(self, robot: str, recent: GraphArrays) -> tuple[GraphArrays, GraphArrays, np.ndarray] | None:
        """``(older graph, recent nodes, descriptors of the older graph)`` of ``robot``'s loop-closure match,
        or None while the robot has not driven far enough for an older graph.

        Older graph: the nodes first seen from keyframes before the excluded stretch (the submap, the
        ``submap_keyframes`` before it, and every keyframe within ``loop_exclusion_m`` of path before it).
        Recent nodes: the submap's nodes first seen after that stretch began, so no node is in both.
        """
        n_kf, window = len(self._T_odom_kf[robot]), self.cfg.backend.submap_keyframes
        first = n_kf - window  # the submap's first keyframe
        path = np.asarray(self._path_m[robot])
        cutoff = min(first - window, int(np.searchsorted(path, path[first] - self.loop_exclusion_m(robot), "right")))
        if cutoff <= 0:
            return None
        graph = self._graphs[robot]
        whole = graph.arrays()
        old = whole.subset(graph.anchor_keyframes(whole.node_ids) < cutoff)
        new = recent.subset(graph.anchor_keyframes(recent.node_ids) >= cutoff)
        if len(old) < self.cfg.matching.min_inliers or len(new) < self.cfg.matching.min_inliers:
            return None
        return old, new, compute_descriptors(old, self.cfg.descriptor)

    def _match_pair(
        self, robot_a: str, robot_b: str, query: str, graph_a: GraphArrays, graph_b: GraphArrays, desc_a
    ) -> MatchRecord:
        t0 = time.perf_counter()
        up_a, up_b = self._up[robot_a], self._up[robot_b]
        if up_a is not None and up_b is not None:
            # both robots know where "up" is (their ground plane): a 4-DoF match in gravity-aligned frames
            R_a, R_b = rotation_to_z(up_a), rotation_to_z(up_b)
            cfg4 = self.cfg.matching.model_copy(update={"gravity_aligned": True, "up_axis": (0.0, 0.0, 1.0)})
            result = match_graphs(
                graph_a.transformed(se3.make_pose(R_a, np.zeros(3))),
                graph_b.transformed(se3.make_pose(R_b, np.zeros(3))),
                self.cfg.descriptor, cfg4, descriptors_a=desc_a,
            )  # fmt: skip
            if result.T_a_b is not None:
                result.T_a_b = se3.make_pose(R_a.T, np.zeros(3)) @ result.T_a_b @ se3.make_pose(R_b, np.zeros(3))
        else:
            result = match_graphs(graph_a, graph_b, self.cfg.descriptor, self.cfg.matching, descriptors_a=desc_a)
        self.timings_ms["match"].append((time.perf_counter() - t0) * 1e3)
        rec = MatchRecord(
            self._step, robot_a, robot_b, query, result.success, False, result.reason, None, None,
            result.T_a_b, result.inliers, result.candidates, len(graph_a), len(graph_b), dict(result.timings_ms),
        )  # fmt: skip
        if not result.success:
            return rec
        rows_a = _rows_of(graph_a, result.inliers[:, 0])
        rows_b = _rows_of(graph_b, result.inliers[:, 1])
        rec.inlier_positions_a = graph_a.positions_xyz[rows_a]
        rec.inlier_positions_b = graph_b.positions_xyz[rows_b]
        anchors_a = self._graphs[robot_a].anchor_keyframes(result.inliers[:, 0])
        anchors_b = self._graphs[robot_b].anchor_keyframes(result.inliers[:, 1])
        closures = [
            (kf_a, kf_b, se3.inverse(self._T_odom_kf[robot_a][kf_a]) @ T @ self._T_odom_kf[robot_b][kf_b], n, rows)
            for kf_a, kf_b, T, n, rows in local_closures(
                rec.inlier_positions_a,
                rec.inlier_positions_b,
                graph_a.label_ids[rows_a],
                anchors_a,
                anchors_b,
                result.T_a_b,
                segment_m=self.cfg.backend.local_closure_m,
                min_inliers=self.cfg.matching.min_inliers // 2 + 1,
                max_rmse_m=self.cfg.matching.max_rmse_m,
                up_a=up_a,
                up_b=up_b,
                rays_a=self._viewing_rays(robot_a, anchors_a, rec.inlier_positions_a),
                rays_b=self._viewing_rays(robot_b, anchors_b, rec.inlier_positions_b),
                offset=self._surface_offset,
            )
        ]
        self._num_matches += 1
        pg = self._pose_graph
        confirming = pg.min_closures_to_anchor > 1 and not (pg.is_anchored(robot_a) and pg.is_anchored(robot_b))
        for kf_a, kf_b, T_akf_bkf, n, rows in closures:
            key = (robot_a, kf_a, robot_b, kf_b)
            # a later match that finds the same keyframe pair again is independent evidence: while it
            # can still confirm an unanchored robot it goes in; afterwards it is a duplicate
            if key in self._closures and not confirming:
                rec.closures.append(
                    {
                        "keyframe_a": kf_a,
                        "keyframe_b": kf_b,
                        "inliers": n,
                        "accepted": False,
                        "reason": "duplicate of an earlier closure between the same keyframes",
                    }
                )
                continue
            t1 = time.perf_counter()
            decision = self._pose_graph.add_inter_robot_closure(
                robot_a, kf_a, robot_b, kf_b, T_akf_bkf, num_inliers=n, match_id=self._num_matches
            )
            self.timings_ms["backend"].append((time.perf_counter() - t1) * 1e3)
            if robot_a != robot_b:  # the objects behind it: what makes two matches independent evidence
                self._support[decision.closure_id] = {
                    robot_a: frozenset(result.inliers[rows, 0].tolist()),
                    robot_b: frozenset(result.inliers[rows, 1].tolist()),
                }
            rec.closures.append(
                {
                    "keyframe_a": kf_a,
                    "keyframe_b": kf_b,
                    "inliers": n,
                    "accepted": decision.accepted,
                    "reason": decision.reason,
                }
            )
            if decision.accepted:
                self._closures.add(key)
        accepted = [c for c in rec.closures if c["accepted"]]
        rec.accepted = bool(accepted)
        shown = accepted[0] if accepted else rec.closures[0]
        rec.kf_a, rec.kf_b, rec.reason = shown["keyframe_a"], shown["keyframe_b"], shown["reason"]
        if len(rec.closures) > 1:
            rec.reason = f"{len(accepted)} of {len(rec.closures)} local closures accepted; {rec.reason}"
        rec.duplicate = all(c["reason"].startswith("duplicate") for c in rec.closures if not c["accepted"]) and (
            not accepted
        )
        return rec

    def _viewing_rays(self, agent: str, anchors: np.ndarray, positions_xyz: np.ndarray) -> np.ndarray:
        """(M, 3) unit rays in ``agent``'s odometry frame from the camera of each node's anchor keyframe (the
        one that first saw it) towards the node at (M, 3) ``positions_xyz``."""
        poses = self._T_odom_kf[agent]
        cameras = np.stack([poses[k][:3, 3] for k in anchors]) if len(anchors) else np.zeros((0, 3))
        rays = positions_xyz - cameras
        return rays / np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-9)

    # --- snapshots --------------------------------------------------------------------------------

    def state(self) -> MapServerState:
        """Everything this server holds (``MapServerState``)."""
        return MapServerState(
            tuple(self._agents),
            {a: g.state() for a, g in self._graphs.items()},
            {a: self.keyframe_poses(a) for a in self._agents},
            {a: None if u is None else np.array(u, dtype=np.float64) for a, u in self._up.items()},
            dict(self._since_match), tuple(self._matches), tuple(sorted(self._closures)),
            self._step, self._num_matches, {k: list(v) for k, v in self.timings_ms.items()},
            self._pose_graph.state(),
            {cid: {a: frozenset(ids) for a, ids in sup.items()} for cid, sup in self._support.items()},
            self._surface_offset.state(),
        )  # fmt: skip

    @classmethod
    def from_state(cls, state: MapServerState, cfg: ShgmConfig) -> MapServer:
        """Rebuild a map server from ``state()`` (made with the same configuration ``cfg``).

        Raises:
            GraphError, BackendError: the state is inconsistent (graphs, keyframes, pose graph).
        """
        agents = list(state.agents)
        if not agents or len(set(agents)) != len(agents) or not set(agents) == set(state.graphs) == set(
                state.T_odom_kf) == set(state.up) == set(state.since_match):  # fmt: skip
            raise BackendError(f"map server state: agents {agents} do not match its graphs, keyframes and counters")
        server = cls(agents[:1], cfg)
        for a in agents[1:]:
            server.add_agent(a)
        for a in agents:
            graph = SemanticGraph.from_state(state.graphs[a])
            poses = np.asarray(state.T_odom_kf[a], dtype=np.float64).reshape(-1, 4, 4)
            if graph.keyframe_ids != list(range(len(poses))):
                raise BackendError(f"map server state: {a}'s graph has other keyframes than its {len(poses)} poses")
            server._graphs[a] = graph
            for T in poses:
                server._append_keyframe(a, T)
            up = state.up[a]
            if up is not None and (np.shape(up) != (3,) or not np.isfinite(up).all()):
                raise BackendError(f"map server state: {a}'s up vector is not a finite (3,) vector")
            server._up[a] = None if up is None else np.array(up, dtype=np.float64)
            server._since_match[a] = int(state.since_match[a])
        if any(c[0] not in state.graphs or c[2] not in state.graphs for c in state.closures):
            raise BackendError("map server state: a closure names an unknown agent")
        server._matches = list(state.matches)
        server._closures = {tuple(c) for c in state.closures}
        server._step, server._num_matches = int(state.step), int(state.num_matches)
        server.timings_ms = {"match": list(state.timings_ms.get("match", [])),
                             "backend": list(state.timings_ms.get("backend", []))}  # fmt: skip
        server._pose_graph.restore_state(state.pose_graph, {a: server.keyframe_poses(a) for a in agents})
        server._support = {
            int(cid): {a: frozenset(ids) for a, ids in sup.items()} for cid, sup in state.support.items()
        }
        try:
            server._surface_offset = SurfaceOffset.from_state(state.surface_offset)
        except ValueError as exc:
            raise BackendError(f"map server state: {exc}") from None
        return server

    # --- queries ----------------------------------------------------------------------------------

    @property
    def reference(self) -> str:
        """The robot whose odometry frame is the shared frame."""
        return self._agents[0]

    @property
    def agents(self) -> list[str]:
        """Every agent the server mirrors, in the order it learnt of them (the reference first)."""
        return list(self._agents)

    @property
    def matches(self) -> list[MatchRecord]:
        """Every match attempt so far, in order (the rows of ``matches.json``)."""
        return list(self._matches)

    def received(self, agent: str) -> int:
        """How many keyframes of ``agent`` the server holds (0 for an agent it does not know)."""
        return len(self._T_odom_kf.get(agent, ()))

    def is_placed(self, agent: str) -> bool:
        """True when ``agent``'s keyframes are in the shared frame."""
        return agent in self._graphs and self._pose_graph.is_anchored(agent)

    def placement(self, agent: str) -> AgentPlacement:
        """Whether ``agent`` is the reference, confirmed, provisional (placed from a single piece of
        evidence, ``backend.confirmation``) or not placed; unknown agents are not placed."""
        pg = self._pose_graph
        if self._placements[0] != pg.version:
            anchored = [a for a in self._agents if pg.is_anchored(a)]
            self._placements = (pg.version, placements(self._agents, self.reference, anchored, pg.closures(),
                                                       self._support))  # fmt: skip
        return self._placements[1].get(agent, AgentPlacement(Placement.UNPLACED))

    def T_shared_kf(self, agent: str) -> np.ndarray | None:
        """(K, 4, 4) fused keyframe poses of ``agent`` in the shared frame, or None if not placed (or not
        known to the server yet)."""
        if not self.is_placed(agent):
            return None
        return self._pose_graph.estimate()[agent]

    def T_shared_odom(self, agent: str) -> np.ndarray | None:
        """(4, 4) where ``agent``'s odometry frame lies in the shared frame now (at its latest keyframe),
        or None if not placed."""
        return self._pose_graph.T_shared_odom(agent) if self.is_placed(agent) else None

    def graph(self, agent: str) -> GraphArrays:
        """``agent``'s mirrored semantic graph, in its odometry frame."""
        return self._graphs[agent].arrays()

    def keyframe_poses(self, agent: str) -> np.ndarray:
        """(K, 4, 4) ``T_odom_kf`` of ``agent``'s keyframes as received."""
        poses = self._T_odom_kf.get(agent, [])
        return np.stack(poses) if poses else np.zeros((0, 4, 4))

    def to_g2o(self) -> str:
        """The pose graph in g2o text form."""
        return self._pose_graph.to_g2o()

    def mean_match_ms(self) -> float:
        """Mean wall time of one graph match so far (0 before the first)."""
        return float(np.mean(self.timings_ms["match"])) if self.timings_ms["match"] else 0.0


def _rows_of(graph: GraphArrays, node_ids: np.ndarray) -> np.ndarray:
    """Row indices of ``node_ids`` in ``graph``."""
    order = np.argsort(graph.node_ids)
    return order[np.searchsorted(graph.node_ids, node_ids, sorter=order)]
