"""The map server: mirrors every agent's graph from messages, matches agents, fuses them in iSAM2."""

from __future__ import annotations

import logging
import time

import numpy as np

from shgm_slam.backend.confirmation import (
    AgentPlacement,
    Placement,
    Support,
    describe,
    describe_waiting,
    placements,
)
from shgm_slam.backend.pose_graph import make_pose_graph
from shgm_slam.backend.records import ClosureStatus
from shgm_slam.config import ShgmConfig
from shgm_slam.descriptors import NodeDescriptors
from shgm_slam.descriptors.incremental import IncrementalDescriptors
from shgm_slam.errors import BackendError, ConfigError
from shgm_slam.geometry import se3
from shgm_slam.geometry.ground import rotation_to_z
from shgm_slam.graph.semantic_graph import SemanticGraph
from shgm_slam.labels import FLAT_GROUND_LABELS
from shgm_slam.matching import MatchResult, match_graphs
from shgm_slam.messages import KeyframeMessage
from shgm_slam.server.closures import SurfaceOffset, local_closures
from shgm_slam.server.evidence import MARGINAL_OBJECT, match_evidence, match_objects, sharing, support_objects
from shgm_slam.server.last_look import (
    LAST_LOOK_QUERY,
    last_look_lines,
    smallest_matches,
    still_accepted,
)
from shgm_slam.server.places import free_path_m, loop_near, rows_near
from shgm_slam.server.queries import (
    BACKFILL_QUERY,
    CONFIRMING_MATCHES,
    RECENT_WINDOW_SUBMAPS,
    WINDOW_QUERY,
    loop_cutoff,
    loop_exclusion_m,
    recent_window,
    unclosed_window,
)
from shgm_slam.server.records import MatchRecord
from shgm_slam.server.state import MapServerState
from shgm_slam.server.viewpoints import (
    camera_height_m,
    closure_information,
    elevation_gap_rad,
    up_is_level,
    up_spread_rad,
    viewing_rays,
    views_differ,
)
from shgm_slam.types import GraphArrays

__all__ = [
    "BACKFILL_QUERY",
    "CONFIRMING_MATCHES",
    "HEIGHT_NODES",
    "LAST_LOOK_QUERY",
    "MARGINAL_OBJECT",
    "RECENT_WINDOW_SUBMAPS",
    "WINDOW_QUERY",
    "MapServer",
    "MapServerState",
]

log = logging.getLogger(__name__)


HEIGHT_NODES = 512
"""Newest flat-ground nodes a robot's camera height is measured over (``camera_height_m``): enough for a
stable median, and a cost that does not grow with the graph."""


class MapServer:
    """Mirrors every robot's graph from messages, matches robots periodically, fuses them in iSAM2.

    Every ``match_every_keyframes`` keyframes of a robot r, r's recent submap and r's whole graph are
    matched against every other robot's whole graph (robots here are agents: a robot's trajectory
    segments after odometry failures are agents of their own, added at run time); accepted matches become inter-robot
    relative-pose factors between keyframes. Shared frame = the first robot's odometry frame.

    Candidate places first (cost flat with distance): once two placed robots' closures rest on at least
    ``CONFIRMING_MATCHES`` independent matches, r's submap is matched only against the other's nodes
    anchored near it (``places``: within the two robots' object ranges plus the drift tolerance of the
    fused estimate), and, while r is there, r's recent window (``RECENT_WINDOW_SUBMAPS``: its newest
    keyframes' nodes) against the other's nodes near it (query ``"window"``) instead of the whole graphs;
    while r is nowhere near the other's map neither is matched. Each round also tries one of r's older windows
    that no closure ties yet, in turn (query ``"backfill"``): what r drove before it was placed.
    ``finalize`` matches whole graphs once more, and an agent whose accepted matches with a placed partner
    all found the same objects once more without them (``_independent_match``). Descriptors come from a
    per-agent cache updated around each change (``IncrementalDescriptors``).

    Loop closure (``backend.loop_closure``): r's recent submap is also matched against r's *own* older
    graph (query ``"loop"``), with the same matching, verification and closure cutting; accepted
    closures join two keyframes of r in the pose graph. The older graph leaves out the stretch r just
    drove (``loop_exclusion_m``): objects seen from the submap lie within r's object range of it, so
    only nodes first seen from keyframes more than two object ranges of path (and at least a submap's
    worth of keyframes) before the submap can be shared with it through a revisit, never through the
    pass that is still in view. Of the older graph only the nodes anchored near the submap are matched
    (``places``): within two object ranges plus the drift tolerance, counted along r's odometry between
    the two keyframes (exactly what the pose graph's odometry check of a loop closure allows) or, once r
    is placed, from each to its nearest keyframe tied by a closure, whichever is shorter.
    """

    def __init__(self, robot_names: list[str], cfg: ShgmConfig) -> None:
        if not robot_names:
            raise ConfigError("the map server needs at least the reference robot (whose frame is the shared frame)")
        self.cfg = cfg
        self._agents = list(robot_names)
        self._pose_graph = make_pose_graph(self._agents, cfg.backend)
        self._graphs = {r: SemanticGraph(cfg.graph.merge_radius_m, cfg.graph.connectivity_m) for r in robot_names}
        # descriptors of each agent's whole graph and of its older graph (loop queries), kept up to date
        self._descriptors = {r: IncrementalDescriptors(cfg.descriptor) for r in robot_names}
        self._old_descriptors = {r: IncrementalDescriptors(cfg.descriptor) for r in robot_names}
        # the one home of keyframe poses on the server: each agent's keyframes in its odometry frame
        self._T_odom_kf: dict[str, list[np.ndarray]] = {r: [] for r in robot_names}
        self._path_m: dict[str, list[float]] = {r: [] for r in robot_names}  # odometry path length per keyframe
        self._up_sum = {r: np.zeros(3) for r in robot_names}  # sum of each agent's keyframe normals (odometry frame)
        self._matches: list[MatchRecord] = []
        self._since_match = dict.fromkeys(robot_names, 0)
        self._closures: set[tuple[str, int, str, int]] = set()
        self._step = 0
        self._num_matches = 0  # successful graph matches so far (each closure's evidence id)
        self._surface_offset = SurfaceOffset()  # how far solid objects' centres lie behind what cameras see
        self._support: dict[int, Support] = {}  # closure id -> the matched objects (node ids) behind it
        self._placements: tuple[int, dict[str, AgentPlacement]] = (-1, {})  # (pose-graph version, cache)
        self._confirmed_anchors: set[tuple[str, int]] = set()  # (agent, anchoring closure id) once confirmed
        self._object_ranges: dict[str, tuple[SemanticGraph, int, float]] = {}  # agent -> (graph, its version, m)
        self.timings_ms: dict[str, list[float]] = {"match": [], "backend": []}

    def add_agent(self, agent: str) -> None:
        """Start mirroring a new agent (a robot's later trajectory segment): its own graph, unanchored
        in the pose graph, matched like any robot against every other agent, its robot's too."""
        self._pose_graph.add_robot(agent)
        self._agents.append(agent)
        self._graphs[agent] = SemanticGraph(self.cfg.graph.merge_radius_m, self.cfg.graph.connectivity_m)
        self._descriptors[agent] = IncrementalDescriptors(self.cfg.descriptor)
        self._old_descriptors[agent] = IncrementalDescriptors(self.cfg.descriptor)
        self._T_odom_kf[agent] = []
        self._path_m[agent] = []
        self._up_sum[agent] = np.zeros(3)
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
            self._up_sum[msg.robot] += msg.up_odom
        self._pose_graph.add_keyframe(msg.robot, msg.kf_index, msg.T_odom_kf, msg.up_odom)
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
        """Match every robot once more at the end of the run (whole graphs; an agent still resting on one piece
        of evidence also without the objects behind it, ``_independent_match``), then solve the pose graph to
        convergence (``MultiRobotPoseGraph.converge``: the final estimate does not depend on the order
        in which robots' messages arrived, only on what was accepted)."""
        records: list[MatchRecord] = []
        for r in list(self._agents):
            records += self.match_robot(r, submap=False)
        for r in list(self._agents):
            records += self._independent_match(r)  # one piece of evidence so far: look for a second
        t0 = time.perf_counter()
        iterations = self._pose_graph.converge()
        self.timings_ms["backend"].append((time.perf_counter() - t0) * 1e3)
        log.info("pose graph solved to convergence in %d iterations (%.0f ms)", iterations,
                 self.timings_ms["backend"][-1])  # fmt: skip
        return records

    def match_robot(self, robot: str, *, submap: bool = True) -> list[MatchRecord]:
        """Match ``robot``'s recent submap (``submap``) and whole graph against every other robot's graph,
        and (loop closure) its recent submap against its own older graph; candidate places first (class
        docstring). Without ``submap`` only whole graphs are matched, every pair."""
        records = []
        n_kf = len(self._T_odom_kf[robot])
        recent: tuple[np.ndarray, GraphArrays] | None = None
        if submap and n_kf > self.cfg.backend.submap_keyframes:
            kfs = np.arange(n_kf - self.cfg.backend.submap_keyframes, n_kf)
            recent = (kfs, self._graphs[robot].submap(kfs))
            if self.cfg.backend.loop_closure:
                loop = self._loop_query(robot, *recent)
                if loop is not None:
                    records.append(self._match_pair(robot, robot, "loop", *loop))
        whole = self._graphs[robot].arrays()
        for other in list(self._agents):
            if other == robot or len(self._graphs[other]) == 0:
                continue
            graph_a = self._graphs[other].arrays()
            desc_a = self._descriptors[other].update(graph_a)
            if not submap or not self._confirmed(other, robot):  # global: where robot is in other's map is open
                if recent is not None:
                    records.append(self._match_pair(other, robot, "submap", graph_a, recent[1], desc_a))
                records.append(self._match_pair(other, robot, "whole", graph_a, whole, desc_a))
                continue
            if recent is None:
                continue
            rows = self._rows_near(other, robot, recent[0])
            if rows.size >= self.cfg.matching.min_inliers:  # else robot is not near other's map now
                near = graph_a.subset(rows)
                records.append(self._match_pair(other, robot, "submap", near, recent[1], desc_a.subset(rows)))
                records += self._match_window(other, robot, self._recent_window(robot), WINDOW_QUERY, graph_a, desc_a,
                                              whole)  # fmt: skip
            older = self._unclosed_window(robot)
            if older is not None:
                records += self._match_window(other, robot, older, BACKFILL_QUERY, graph_a, desc_a, whole)
        return self._keep(records)

    def _recent_window(self, robot: str) -> np.ndarray:
        """``robot``'s newest ``RECENT_WINDOW_SUBMAPS`` submaps of keyframes (indices, ``queries.recent_window``)."""
        return recent_window(len(self._T_odom_kf[robot]), self.cfg.backend.submap_keyframes)

    def _unclosed_window(self, robot: str) -> np.ndarray | None:
        """One older window of ``robot``'s keyframes (indices) that no closure ties yet, or None
        (``queries.unclosed_window``)."""
        b = self.cfg.backend
        return unclosed_window(len(self._T_odom_kf[robot]), b.submap_keyframes, b.match_every_keyframes,
                               self._pose_graph.closure_keyframes(robot))  # fmt: skip

    def _match_window(
        self, other: str, robot: str, kfs: np.ndarray, query: str, graph_a: GraphArrays, desc_a: NodeDescriptors,
        whole: GraphArrays,
    ) -> list[MatchRecord]:  # fmt: skip
        """Placed ``robot``'s nodes observed from keyframes ``kfs`` against placed ``other``'s nodes near them in
        the fused estimate (``_rows_near``): one match record, or none when either side has too few nodes.
        ``graph_a``, ``desc_a``: ``other``'s graph and descriptors; ``whole``: ``robot``'s graph."""
        rows_a = self._rows_near(other, robot, kfs)
        rows_b = self._graphs[robot].observed_rows(kfs)
        if min(rows_a.size, rows_b.size) < self.cfg.matching.min_inliers:
            return []
        desc_b = self._descriptors[robot].update(whole).subset(rows_b)
        return [self._match_pair(other, robot, query, graph_a.subset(rows_a), whole.subset(rows_b),
                                 desc_a.subset(rows_a), desc_b)]  # fmt: skip

    def _independent_match(self, agent: str) -> list[MatchRecord]:
        """The last look for a second, independent match of an agent whose accepted closures with a placed
        partner all rest on one piece of evidence (not placed: waiting; or placed provisionally, with
        ``backend.min_closures_to_anchor: 1``): the two whole graphs matched again without the objects
        behind the smallest of its accepted matches with that partner (query ``"independent"``), once per
        partner. What it finds rests on other objects, so it counts as independent evidence when it agrees
        and is outvoted or rejected when it does not; where it lies on the same two straight stretches as the
        earlier matches (``backend/stretches.py``) it is not a second piece either. Which matches a run tried
        depends on when keyframes arrived (in a distributed run, also on the order of messages): the last look
        makes the end result depend on what the two graphs hold. Returns its match records (none when nothing
        is waiting). (The partner used to look too, its graph as the query, which counted as its own evidence
        while a straight stretch pair was per querying robot; it no longer is, so that look is no other piece.)
        """
        if agent not in self._graphs or self.placement(agent).placement in (Placement.REFERENCE,
                                                                            Placement.CONFIRMED):  # fmt: skip
            return []
        pg = self._pose_graph
        smallest = smallest_matches(agent, pg.closures(), self._support)  # partner -> what the look leaves out
        records = []
        for partner, ids in smallest.items():
            if (self.placement(agent).placement is Placement.CONFIRMED or not self.is_placed(partner)
                    or pg.evidence_between(agent, partner) >= CONFIRMING_MATCHES):  # fmt: skip
                continue
            graph_a, graph_b = self._graphs[partner].arrays(), self._graphs[agent].arrays()
            rows_a = np.flatnonzero(~np.isin(graph_a.node_ids, list(ids[partner])))
            rows_b = np.flatnonzero(~np.isin(graph_b.node_ids, list(ids[agent])))
            if min(rows_a.size, rows_b.size) < self.cfg.matching.min_inliers:
                continue
            desc_a = self._descriptors[partner].update(graph_a).subset(rows_a)
            desc_b = self._descriptors[agent].update(graph_b).subset(rows_b)
            records.append(self._match_pair(partner, agent, LAST_LOOK_QUERY, graph_a.subset(rows_a),
                                            graph_b.subset(rows_b), desc_a, desc_b))  # fmt: skip
        return self._keep(records)

    def _keep(self, records: list[MatchRecord]) -> list[MatchRecord]:
        """Record match attempts (``matches``) and, when one was accepted, which agents are confirmed now."""
        self._matches += records
        if any(r.accepted for r in records):  # only an accepted closure can confirm an agent
            self._note_confirmed_anchors()
        return records

    def last_looks(self) -> list[str]:
        """One line per last look (``_independent_match``) so far, for the run's summary, ``metrics.json`` and
        ``server.json``: whose, with whom, and what came of it (confirmed, provisional, outvoted, or why
        the match was rejected; ``last_look.last_look_lines``)."""
        return last_look_lines(self._matches, lambda agent: self.placement(agent).placement, self._still_accepted)

    def _still_accepted(self, record: MatchRecord) -> bool:
        """True when a closure that ``record`` added is in its pair's consistent set now."""
        return still_accepted(record, self._pose_graph.closures())

    def _confirmed(self, a: str, b: str) -> bool:
        """Both placed and their accepted closures rest on ``CONFIRMING_MATCHES`` independent matches."""
        return (
            self.is_placed(a) and self.is_placed(b)
            and self._pose_graph.evidence_between(a, b) >= CONFIRMING_MATCHES
        )  # fmt: skip

    def object_range_m(self, agent: str) -> float | None:
        """How far ``agent``'s objects lie from the keyframes that first saw them: the 95th percentile
        of node-to-anchor distances (metres); None while its graph is empty."""
        graph = self._graphs[agent]
        if len(graph) == 0:
            return None
        cached = self._object_ranges.get(agent)
        if cached is not None and cached[0] is graph and cached[1] == graph.version:
            return cached[2]  # a match asks several times per keyframe; each answer costs the whole graph
        origins = np.stack(self._T_odom_kf[agent])[graph.anchors(), :3, 3]
        reach = float(np.percentile(np.linalg.norm(graph.arrays().positions_xyz - origins, axis=1), 95))
        self._object_ranges[agent] = (graph, graph.version, reach)
        return reach

    def camera_height_m(self, agent: str) -> float | None:
        """How high above the ground ``agent``'s camera looks from (``viewpoints.camera_height_m``: over its
        newest ``HEIGHT_NODES`` flat-ground nodes, from the keyframes that first saw them), metres; None while
        unknown. Bounded cost whatever the graph's size."""
        graph = self._graphs[agent]
        if len(graph) == 0:
            return None
        arrays = graph.arrays()
        flat = np.flatnonzero(np.isin(arrays.label_ids, FLAT_GROUND_LABELS))[-HEIGHT_NODES:]
        poses = self._T_odom_kf[agent]
        cameras = np.array([poses[k][:3, 3] for k in graph.anchors()[flat]]).reshape(-1, 3)
        return camera_height_m(cameras, arrays.positions_xyz[flat], arrays.label_ids[flat], self.up_odom(agent))

    def evidence_free_labels(self, a: str, b: str) -> tuple[int, ...]:
        """Labels that give no evidence when matching ``a`` against ``b``: the viewpoint-dependent ones when
        the two look from very different heights (a car and a UAV), none otherwise."""
        m = self.cfg.matching
        differ = views_differ(self.camera_height_m(a), self.camera_height_m(b), m.view_height_ratio)
        return tuple(m.viewpoint_dependent_labels) if differ else ()

    def loop_exclusion_m(self, robot: str) -> float:
        """Metres of path before its submap whose keyframes ``robot``'s loop query leaves out of its older graph:
        twice the robot's object range (``object_range_m``; the fleet's extraction depth until the graph has
        nodes)."""
        reach = self.object_range_m(robot)
        return loop_exclusion_m(reach, self.cfg.extraction.filled().max_depth_m)

    def path_from_closures_m(self, agent: str) -> float | None:
        """The longest stretch of placed ``agent``'s path that rests on its own odometry alone: the most metres of
        path from one of its keyframes to the nearest keyframe a factor ties to the shared frame (an accepted
        closure's end, or the prior of the shared frame's robot); None while it is not placed. Far from those
        keyframes its fused poses carry its odometry's drift (what this reports, honestly, for a user to weigh)."""
        if not self.is_placed(agent) or not self._path_m.get(agent):
            return None
        free = self._free_path_m(agent)
        return float(free.max()) if free.size and np.isfinite(free).all() else None

    def longest_path_from_closures_m(self, agents: list[str]) -> float | None:
        """``path_from_closures_m``, the most over ``agents`` (a robot's trajectory segments), to 0.1 m; None when
        none of them is placed."""
        free = [m for a in agents if (m := self.path_from_closures_m(a)) is not None]
        return round(max(free), 1) if free else None

    def _free_path_m(self, agent: str) -> np.ndarray:
        """(K,) metres from each keyframe of placed ``agent`` to its nearest keyframe tied by a closure."""
        return free_path_m(np.asarray(self._path_m[agent]), self._pose_graph.closure_keyframes(agent))

    def _rows_near(self, a: str, b: str, kfs_b: np.ndarray) -> np.ndarray:
        """Rows of placed ``a``'s graph anchored near placed ``b``'s keyframes ``kfs_b`` in the fused
        estimate (``places``): within both object ranges plus the drift tolerance."""
        estimate = self._pose_graph.estimate()
        free_b, free_a = self._free_path_m(b)[kfs_b], self._free_path_m(a)
        reach = (self.object_range_m(a) or 0.0) + (self.object_range_m(b) or 0.0)
        return rows_near(self._graphs[a].anchors(), estimate[a][:, :3, 3], free_a, estimate[b][kfs_b, :3, 3], free_b,
                         reach, self._pose_graph.thresholds)  # fmt: skip

    def _loop_query(
        self, robot: str, kfs: np.ndarray, recent: GraphArrays
    ) -> tuple[GraphArrays, GraphArrays, NodeDescriptors] | None:
        """``(older nodes near the submap, recent nodes, their descriptors)`` of ``robot``'s loop-closure
        match, or None while the robot has not driven far enough for an older graph.

        Older graph: the nodes first seen from keyframes before the excluded stretch (the submap, the
        ``submap_keyframes`` before it, and every keyframe within ``loop_exclusion_m`` of path before it);
        its descriptors count paths within it. Of it, the nodes anchored near the submap (class docstring).
        Recent nodes: the submap's nodes first seen after that stretch began, so no node is in both.
        """
        path = np.asarray(self._path_m[robot])
        cutoff = loop_cutoff(path, self.cfg.backend.submap_keyframes, self.loop_exclusion_m(robot))
        if cutoff <= 0:
            return None
        graph = self._graphs[robot]
        anchors = graph.anchors()
        if self.is_placed(robot):
            free = self._free_path_m(robot)
            xyz = self._pose_graph.estimate()[robot][:, :3, 3]
        else:
            free, xyz = None, np.stack(self._T_odom_kf[robot])[:, :3, 3]
        near = loop_near(xyz, path, free, kfs, cutoff, self.loop_exclusion_m(robot), self._pose_graph.thresholds)
        older = np.flatnonzero(anchors < cutoff)  # a prefix of the rows: nodes are created in keyframe order
        rows = np.flatnonzero(near[anchors])
        new = recent.subset(graph.anchor_keyframes(recent.node_ids) >= cutoff)
        if rows.size < self.cfg.matching.min_inliers or len(new) < self.cfg.matching.min_inliers:
            return None
        old_graph = graph.arrays().subset(older)
        desc = self._old_descriptors[robot].update(old_graph).subset(np.searchsorted(older, rows))
        return old_graph.subset(np.searchsorted(older, rows)), new, desc

    def _match_pair(
        self, robot_a: str, robot_b: str, query: str, graph_a: GraphArrays, graph_b: GraphArrays, desc_a,
        desc_b: NodeDescriptors | None = None,
    ) -> MatchRecord:
        t0 = time.perf_counter()
        up_a, up_b = self.up_odom(robot_a), self.up_odom(robot_b)
        free = self.evidence_free_labels(robot_a, robot_b)
        if up_a is not None and up_b is not None:
            # both robots know where "up" is (their ground plane): match in frames whose z is up, so that the
            # chance model shifts hypotheses along the ground (``chance.shift_vectors``); 4-DoF when
            # both ups are level enough for it, else 6-DoF, which absorbs a submap's own tilt
            R_a, R_b = rotation_to_z(up_a), rotation_to_z(up_b)
            level = self.gravity_aligned(robot_a) and self.gravity_aligned(robot_b)
            cfg_z = self.cfg.matching.model_copy(update={"gravity_aligned": level, "up_axis": (0.0, 0.0, 1.0)})
            result = match_graphs(
                graph_a.transformed(se3.make_pose(R_a, np.zeros(3))),
                graph_b.transformed(se3.make_pose(R_b, np.zeros(3))),
                self.cfg.descriptor, cfg_z, descriptors_a=desc_a, descriptors_b=desc_b, evidence_free_labels=free,
            )  # fmt: skip
            to_a, from_b = se3.make_pose(R_a.T, np.zeros(3)), se3.make_pose(R_b, np.zeros(3))
            if result.T_a_b is not None:
                result.T_a_b = to_a @ result.T_a_b @ from_b
            if result.T_a_b_hypothesis is not None:
                result.T_a_b_hypothesis = to_a @ result.T_a_b_hypothesis @ from_b
        else:
            result = match_graphs(graph_a, graph_b, self.cfg.descriptor, self.cfg.matching, descriptors_a=desc_a,
                                  descriptors_b=desc_b, evidence_free_labels=free)  # fmt: skip
        self.timings_ms["match"].append((time.perf_counter() - t0) * 1e3)
        rec = MatchRecord(
            self._step, robot_a, robot_b, query, result.success, False, result.reason, None, None,
            result.T_a_b, result.inliers, result.candidates, len(graph_a), len(graph_b), dict(result.timings_ms),
            evidence=match_evidence(result, len(self._T_odom_kf[robot_b]) - 1),
        )  # fmt: skip
        if not result.success:
            return rec
        rows_a = _rows_of(graph_a, result.inliers[:, 0])
        rows_b = _rows_of(graph_b, result.inliers[:, 1])
        rec.inlier_positions_a = graph_a.positions_xyz[rows_a]
        rec.inlier_positions_b = graph_b.positions_xyz[rows_b]
        anchors_a = self._graphs[robot_a].anchor_keyframes(result.inliers[:, 0])
        anchors_b = self._graphs[robot_b].anchor_keyframes(result.inliers[:, 1])
        rays_a = self._viewing_rays(robot_a, anchors_a, rec.inlier_positions_a)
        rays_b = self._viewing_rays(robot_b, anchors_b, rec.inlier_positions_b)
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
                rays_a=rays_a,
                rays_b=rays_b,
                offset=self._surface_offset,
            )
        ]
        self._num_matches += 1
        pg = self._pose_graph
        confirming = pg.min_closures_to_anchor > 1 and (
            not (pg.is_anchored(robot_a) and pg.is_anchored(robot_b))
            or self.placement(robot_a).provisional or self.placement(robot_b).provisional
        )  # fmt: skip
        marginal = robot_a != robot_b and self._marginal(robot_a, robot_b, result)
        decisive = robot_a != robot_b and not marginal and self._decisive(robot_a, robot_b, result)
        # the objects behind every closure of this match, what makes two matches independent evidence: all of
        # the match's partners, not the closure's own. The closures are cut from one verified alignment, so a
        # closure is not evidence apart from the rest of its match: a re-match of a grown graph whose new
        # stretch's closure rests on new objects rests on the old ones too (KITTI 02, a fleet of 8: a street
        # alias re-found by every whole-graph match entered as two pieces through such closures, 566 m off)
        support = {robot_a: frozenset(result.inliers[:, 0].tolist()),
                   robot_b: frozenset(result.inliers[:, 1].tolist())}  # fmt: skip
        objects = match_objects(robot_a, robot_b, support, marginal)
        for kf_a, kf_b, T_akf_bkf, n, rows in closures:
            key = (robot_a, kf_a, robot_b, kf_b)
            # a later match that finds the same keyframe pair again is independent evidence: while it
            # can still confirm an unanchored or provisional robot (one placed by a decisive match) it goes
            # in; afterwards it is a duplicate
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
            b_cfg = self.cfg.backend
            information = closure_information(
                b_cfg.closure_sigma_rot_rad, b_cfg.closure_sigma_trans_m,
                elevation_gap_rad(rays_a[rows], rays_b[rows], up_a, up_b), b_cfg.closure_sigma_per_elevation,
            )  # fmt: skip
            t1 = time.perf_counter()
            decision = self._pose_graph.add_inter_robot_closure(
                robot_a, kf_a, robot_b, kf_b, T_akf_bkf, num_inliers=n, information=information,
                match_id=self._num_matches, support=objects, decisive=decisive, update=False,
            )  # fmt: skip
            self.timings_ms["backend"].append((time.perf_counter() - t1) * 1e3)
            if robot_a != robot_b:
                self._support[decision.closure_id] = support
            rec.closures.append(
                {
                    "keyframe_a": kf_a,
                    "keyframe_b": kf_b,
                    "inliers": n,
                    "accepted": decision.accepted,
                    "reason": decision.reason,
                    "stretches": _listed(self._pose_graph.stretch_pair(decision.closure_id)),
                }
            )
            if decision.accepted:
                self._closures.add(key)
        t1 = time.perf_counter()
        self._pose_graph.update()  # one iSAM2 update for all closures of this match
        self.timings_ms["backend"].append((time.perf_counter() - t1) * 1e3)
        rec.conclude()
        return rec

    def _marginal(self, robot_a: str, robot_b: str, result: MatchResult) -> bool:
        """Whether an accepted match between two robots is marginal once the pair's repeated queries are counted.

        Each match's threshold bounds the false-alarm rate of *one* search. The same two robots are matched again
        and again as they drive (every keyframe's submap query, each robot's own, last looks), so along a street
        that looks like another one an alias gets that many chances. A match counts as a piece of its own only
        when its log likelihood ratio clears the threshold by the log of the matches tried between the pair so
        far (``alpha / n`` of the rate to the n-th); the marginal ones of a pair count as one piece together (they
        share a pseudo-object). With rendered depth it changed no placement measured. It is not enough for every alias:
        with a frame-invariant matcher (not in this version) a parallel street in the fleet of 8 in KITTI 09
        aliased in 11 matches of one pair, 0.6-3.2 nats above their thresholds, and the 22nd match of the pair
        still counted, by 0.05 nats; a spending whose sum stays within the rate (``2 ln n + ln(pi^2 / 6)``)
        kept it out but also left robots that meet after many tries waiting (docs/benchmarks.md).
        """
        return result.is_marginal(self._tried(robot_a, robot_b))

    def _decisive(self, robot_a: str, robot_b: str, result: MatchResult) -> bool:
        """Whether an accepted match between two robots carries, alone, the evidence of the independent
        matches a robot needs to enter the shared frame (``backend.decisive_match``).

        A match counts as a piece of its own when its log likelihood ratio clears its threshold plus the log of
        the matches the pair has tried (``_marginal``); ``backend.min_closures_to_anchor`` such pieces on other
        objects place a robot. A match whose ratio alone is that many times the bar, ``needed * (threshold +
        log tried)``, is as unlikely under chance as the pieces together: it places the robot by itself, and the
        place stays provisional until an independent match confirms it. Matches on a short shared stretch
        (a street crossed once) otherwise leave a robot waiting however strong they are: on KITTI splits four
        robots waited on matches 17-53 nats above their thresholds, while accepted aliases measured so far lay
        at most 7.3 nats above theirs (docs/benchmarks.md). No constant is tuned: the bar is the one two pieces
        clear.
        """
        if not self.cfg.backend.decisive_match:
            return False
        return result.is_decisive(self._pose_graph.min_closures_to_anchor, self._tried(robot_a, robot_b))

    def _tried(self, robot_a: str, robot_b: str) -> int:
        """Matches tried between two robots so far (either direction), the one being decided included."""
        return 1 + sum(1 for m in self._matches if {m.robot_a, m.robot_b} == {robot_a, robot_b})

    def _viewing_rays(self, agent: str, anchors: np.ndarray, positions_xyz: np.ndarray) -> np.ndarray:
        """(M, 3) unit rays in ``agent``'s odometry frame from the camera of each node's anchor keyframe (the
        one that first saw it) towards the node at (M, 3) ``positions_xyz``."""
        poses = self._T_odom_kf[agent]
        cameras = np.stack([poses[k][:3, 3] for k in anchors]) if len(anchors) else np.zeros((0, 3))
        return viewing_rays(cameras, positions_xyz)

    # --- snapshots --------------------------------------------------------------------------------

    def state(self) -> MapServerState:
        """Everything this server holds (``MapServerState``)."""
        return MapServerState(
            tuple(self._agents),
            {a: g.state() for a, g in self._graphs.items()},
            {a: self.keyframe_poses(a) for a in self._agents},
            {a: np.array(u, dtype=np.float64) for a, u in self._up_sum.items()},
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
                raise BackendError(f"map server state: {a}'s sum of ground normals is not a finite (3,) vector")
            server._up_sum[a] = np.zeros(3) if up is None else np.array(up, dtype=np.float64)
            server._since_match[a] = int(state.since_match[a])
        if any(c[0] not in state.graphs or c[2] not in state.graphs for c in state.closures):
            raise BackendError("map server state: a closure names an unknown agent")
        server._matches = list(state.matches)
        server._closures = {tuple(c) for c in state.closures}
        server._step, server._num_matches = int(state.step), int(state.num_matches)
        server.timings_ms = {"match": list(state.timings_ms.get("match", [])),
                             "backend": list(state.timings_ms.get("backend", []))}  # fmt: skip
        server._support = {
            int(cid): {a: frozenset(ids) for a, ids in sup.items()} for cid, sup in state.support.items()
        }
        objects = {cid: support_objects(sup) for cid, sup in server._support.items()}
        server._pose_graph.restore_state(state.pose_graph, {a: server.keyframe_poses(a) for a in agents}, objects)
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

    def up_spread_rad(self, agent: str) -> float | None:
        """Angular spread (radians) of ``agent``'s keyframe ground normals in its odometry frame
        (``viewpoints.up_spread_rad``), or None while it has none."""
        return up_spread_rad(self._up_sum[agent], self._pose_graph.ground_normal_count(agent))

    def gravity_aligned(self, agent: str) -> bool:
        """Whether ``agent``'s mean "up" is good enough to match it in a gravity-aligned frame
        (``viewpoints.up_is_level``): known, and its spread over the keyframes, at the distance of its
        objects (``object_range_m``), within the verification radius."""
        return self.up_odom(agent) is not None and up_is_level(
            self.up_spread_rad(agent), self.object_range_m(agent), self.cfg.matching.verification_radius_m
        )

    def up_odom(self, agent: str) -> np.ndarray | None:
        """(3,) ``agent``'s mean ground normal (unit, up) over its keyframes in its odometry frame, or None
        while none of its keyframes has fitted the ground."""
        total = self._up_sum[agent]
        norm = float(np.linalg.norm(total))
        return total / norm if norm > 0 else None

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
            decided = placements(self._agents, self.reference, anchored, pg.closures(), self._support,
                                 pg.stretches(), pg.agreeing_partners)  # fmt: skip
            self._placements = (pg.version, decided)
        return self._placements[1].get(agent, AgentPlacement(Placement.UNPLACED))

    def placement_note(self, agent: str) -> str | None:
        """The line a user gets about ``agent``'s placement when it is not plainly placed: provisional
        (``describe``) or waiting for evidence (``waiting_note``); None otherwise."""
        p = self.placement(agent)
        if not p.provisional:
            return self.waiting_note(agent)
        tied = sharing(self._pose_graph.shared_support(agent, p.partner)) if p.partner and p.matches > 1 else ()
        return describe(agent, p, tied)

    def waiting_note(self, agent: str) -> str | None:
        """Why unplaced ``agent`` is not in the shared frame although some of its inter-robot closures were
        accepted (too few independent matches, ``describe_waiting``), or None (placed, or nothing accepted)."""
        if agent not in self._graphs or self.is_placed(agent):
            return None
        pg = self._pose_graph
        matches: dict[str, set] = {}  # placed partner -> the graph matches its accepted closures came from
        for c in pg.closures():
            if c.status is ClosureStatus.ACCEPTED and c.robot_a != c.robot_b and agent in (c.robot_a, c.robot_b):
                other = c.robot_b if c.robot_a == agent else c.robot_a
                if self.is_placed(other):
                    matches.setdefault(other, set()).add(c.evidence)
        if not matches:
            return None
        partner = max(matches, key=lambda o: (pg.evidence_between(agent, o), len(matches[o]), o))
        others = tuple(sorted(set(matches) - {partner}))
        return describe_waiting(agent, partner, max(1, pg.evidence_between(agent, partner)),
                                pg.min_closures_to_anchor, len(matches[partner]), others,
                                sharing(pg.shared_support(agent, partner)))  # fmt: skip

    def measured_drift(self, agent: str) -> float | None:
        """Odometry rotation drift (rad per metre) ``agent``'s own loop closures measured beyond the prior
        (``MultiRobotPoseGraph.measured_drift``); None while the prior holds or the agent is unknown."""
        return self._pose_graph.measured_drift(agent) if agent in self._graphs else None

    def T_shared_kf(self, agent: str) -> np.ndarray | None:
        """(K, 4, 4) fused keyframe poses of ``agent`` in the shared frame, or None if not placed (or not
        known to the server yet)."""
        if not self.is_placed(agent):
            return None
        return self._pose_graph.estimate()[agent]

    def T_shared_kf_at(self, agent: str, kf_indices: np.ndarray) -> np.ndarray | None:
        """(M, 4, 4) fused poses of keyframes ``kf_indices`` of ``agent`` in the shared frame, or None if
        not placed (a few keyframes without reading the whole estimate)."""
        return self._pose_graph.T_shared_kfs(agent, kf_indices) if self.is_placed(agent) else None

    @property
    def corrections(self) -> int:
        """Counter of the pose-graph changes that can move old keyframes (``MultiRobotPoseGraph.corrections``)."""
        return self._pose_graph.corrections

    def graph_anchors(self, agent: str) -> np.ndarray:
        """(N,) keyframe each node of ``agent``'s mirrored graph (row order of ``graph``) is anchored to."""
        return self._graphs[agent].anchors()

    def T_shared_odom(self, agent: str) -> np.ndarray | None:
        """(4, 4) where ``agent``'s odometry frame lies in the shared frame now (at its latest keyframe),
        or None if not placed."""
        return self._pose_graph.T_shared_odom(agent) if self.is_placed(agent) else None

    def graph(self, agent: str) -> GraphArrays:
        """``agent``'s mirrored semantic graph, in its odometry frame."""
        return self._graphs[agent].arrays()

    def shared_graph(self, agent: str) -> GraphArrays | None:
        """``agent``'s semantic graph in the shared frame, or None while it is not placed: each node moved with
        the keyframe it is anchored to (``graph_anchors``; that keyframe's fused pose times its odometry pose's
        inverse), so the loop and inter-robot closures that bent the trajectory bend the map alike. The fused map
        is every placed agent's shared graph together."""
        graph = self.graph(agent)
        positions = self.shared_positions(agent, self.graph_anchors(agent), graph.positions_xyz)
        if positions is None:
            return None
        return GraphArrays(graph.node_ids, graph.label_ids, positions, graph.sizes, graph.edges)

    def shared_positions(self, agent: str, anchors: np.ndarray, positions_xyz: np.ndarray) -> np.ndarray | None:
        """(N, 3) points of ``agent`` in the shared frame, or None while it is not placed: ``positions_xyz`` (N, 3),
        metres in its odometry frame, each moved with the correction of the keyframe it is anchored to (``anchors``
        (N,) keyframe indices; that keyframe's fused pose times its odometry pose's inverse), as ``shared_graph``
        moves the graph's nodes. Reads only the anchored keyframes' poses: the viewer calls it per chunk and
        keyframe, so its cost must not grow with the keyframes held."""
        positions_xyz = np.asarray(positions_xyz, dtype=np.float64).reshape(-1, 3)
        if not self.is_placed(agent):
            return None
        if not len(positions_xyz):
            return positions_xyz
        kfs, inverse = np.unique(np.asarray(anchors, dtype=np.int64), return_inverse=True)
        T_shared_kf = self.T_shared_kf_at(agent, kfs)  # (BackendError for keyframes it does not hold)
        poses = self._T_odom_kf[agent]
        T_odom_kf = np.stack([poses[k] for k in kfs.tolist()])  # (not ``keyframe_poses``: it stacks all K)
        correction = T_shared_kf @ se3.inverse(T_odom_kf)  # odometry frame -> shared, per keyframe
        at = correction[inverse]
        return np.einsum("nij,nj->ni", at[:, :3, :3], positions_xyz) + at[:, :3, 3]

    def keyframe_poses(self, agent: str) -> np.ndarray:
        """(K, 4, 4) ``T_odom_kf`` of ``agent``'s keyframes as received."""
        poses = self._T_odom_kf.get(agent, [])
        return np.stack(poses) if poses else np.zeros((0, 4, 4))

    def to_g2o(self) -> str:
        """The pose graph in g2o text form."""
        return self._pose_graph.to_g2o()

    def _note_confirmed_anchors(self) -> None:
        """Remember, for every agent confirmed now, the closure it is anchored through (``anchorings``).
        Called once a keyframe's matches are all done (``match_robot``): the state a robot, the log and the
        viewer can see, not the passing state between two matches of one keyframe."""
        for agent in self._agents:
            if self.placement(agent).placement is Placement.CONFIRMED:
                closure_id = self._pose_graph.anchor_closure(agent)
                if closure_id is not None:
                    self._confirmed_anchors.add((agent, closure_id))

    def anchorings(self) -> list[dict]:
        """Each time an agent entered the shared frame, in order: the agent, the closure that placed it
        (``MultiRobotPoseGraph.anchorings``; ``T_a_b`` maps keyframe ``kf_b``'s camera frame of ``robot_b``
        into keyframe ``kf_a``'s of ``robot_a``), whether that closure was withdrawn later and whether the
        agent's place was ever confirmed while it stood on that closure (checked after each keyframe's
        matches; not kept in snapshots), as JSON-friendly values for ``server.json``."""
        return [
            {"agent": agent, "closure_id": c.closure_id, "robot_a": c.robot_a, "kf_a": c.kf_a,
             "robot_b": c.robot_b, "kf_b": c.kf_b, "T_a_b": np.round(c.T_a_b, 9).tolist(),
             "withdrawn": c.status is not ClosureStatus.ACCEPTED,
             "confirmed": (agent, c.closure_id) in self._confirmed_anchors}
            for agent, c in self._pose_graph.anchorings()
        ]  # fmt: skip

    def mean_match_ms(self) -> float:
        """Mean wall time of one graph match so far (0 before the first)."""
        return float(np.mean(self.timings_ms["match"])) if self.timings_ms["match"] else 0.0


def _listed(pair: tuple[int, int] | None) -> list[int] | None:
    """A closure's stretch pair as ``matches.json`` writes it (a list, or null)."""
    return None if pair is None else list(pair)


def _rows_of(graph: GraphArrays, node_ids: np.ndarray) -> np.ndarray:
    """Row indices of ``node_ids`` in ``graph``."""
    order = np.argsort(graph.node_ids)
    return order[np.searchsorted(graph.node_ids, node_ids, sorter=order)]
