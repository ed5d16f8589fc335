"""Orchestration only: per-robot front ends, the map server, and the interleaved multi-robot run.

Data flow (ARCHITECTURE.md): frames -> perception (files or ONNX) -> pseudo-LiDAR -> odometry ->
keyframes -> semantic graph (front end, per robot) --KeyframeMessage--> map server: mirrored graphs,
periodic cross-robot matching, GTSAM pose graph. A robot only emits small ``KeyframeMessage`` objects
(keyframe pose + new/updated graph nodes); that boundary is where robots become separate processes.
"""

from __future__ import annotations

import heapq
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from shgm_slam.backend.pose_graph import make_pose_graph
from shgm_slam.config import ShgmConfig
from shgm_slam.descriptors import compute_descriptors
from shgm_slam.geometry import se3
from shgm_slam.graph.extraction import extract_objects
from shgm_slam.graph.semantic_graph import GraphUpdate, SemanticGraph
from shgm_slam.labels import Label
from shgm_slam.matching import match_graphs
from shgm_slam.matching.pose import spread_m
from shgm_slam.odometry.clouds import depth_to_cloud
from shgm_slam.odometry.health import HealthLimits, OdometryFailure, OdometryHealthMonitor
from shgm_slam.odometry.sources import OdometryEstimate, OdometrySource
from shgm_slam.perception import PerceptionSource
from shgm_slam.types import Frame, GraphArrays, Sequence

log = logging.getLogger(__name__)


GROUND_LABELS = (Label.ROAD, Label.SIDEWALK, Label.TERRAIN)
COMPACT_LABELS = (
    Label.POLE,
    Label.TRAFFIC_LIGHT,
    Label.TRAFFIC_SIGN,
    Label.VEGETATION,
    Label.CAR,
    Label.TRUCK,
    Label.BUS,
)
"""Classes whose object centroid does not depend on the viewpoint (unlike buildings or road patches)."""


def ground_normal(
    points_cam: np.ndarray, label_ids: np.ndarray | None, *, max_range_m: float = 100.0
) -> np.ndarray | None:
    """Unit normal of the ground plane, pointing up (towards the camera), in the camera frame.

    Fitted to the road, sidewalk and terrain points of one pseudo-LiDAR cloud (least squares plane);
    None when there are too few ground points or they are not planar (RMS distance > 0.3 m).
    """
    if label_ids is None:
        return None
    ground = np.isin(label_ids, GROUND_LABELS) & (np.linalg.norm(points_cam, axis=1) < max_range_m)
    pts = points_cam[ground]
    if len(pts) < 200:
        return None
    centre = pts.mean(axis=0)
    _, sv, vt = np.linalg.svd(pts[:: max(1, len(pts) // 5000)] - centre, full_matrices=False)
    normal = vt[2]
    if sv[2] / np.sqrt(len(pts[:: max(1, len(pts) // 5000)])) > 0.3 or sv[1] < 1e-6:
        return None
    return normal if normal @ (-centre) > 0 else -normal


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking the unit vector ``up`` onto +z (the gravity-aligned frame's vertical)."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    s, c = np.linalg.norm(axis), float(up @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else se3.rot_x(np.pi)
    return se3.so3_exp(axis / s * np.arctan2(s, c))


# --------------------------------------------------------------------------------------------------
# Front end (one per robot)
# --------------------------------------------------------------------------------------------------


class KeyframeSelector:
    """A new keyframe every ``distance_m`` metres or ``angle_deg`` degrees of motion (the first frame too)."""

    def __init__(self, distance_m: float, angle_deg: float) -> None:
        self.distance_m = distance_m
        self.angle_rad = np.radians(angle_deg)
        self._T_odom_last: np.ndarray | None = None

    def is_keyframe(self, T_odom_cam: np.ndarray) -> bool:
        """True when ``T_odom_cam`` (4, 4) moved far enough from the last keyframe (and records it)."""
        if self._T_odom_last is not None:
            d = se3.inverse(self._T_odom_last) @ T_odom_cam
            if np.linalg.norm(d[:3, 3]) < self.distance_m and se3.rotation_angle(d) < self.angle_rad:
                return False
        self._T_odom_last = np.array(T_odom_cam, dtype=np.float64)
        return True


@dataclass(frozen=True)
class KeyframeMessage:
    """What a robot sends to the map server for each keyframe (small: a pose and graph node states).

    ``T_odom_kf`` is the keyframe's camera pose in the robot's odometry frame (its first camera frame).
    ``robot`` is the sending agent: the robot, or one of its later trajectory segments (``segment_agent``).
    """

    robot: str
    kf_index: int
    frame_index: int
    timestamp_s: float
    T_odom_kf: np.ndarray
    graph_update: GraphUpdate
    up_odom: np.ndarray | None = None  # (3,) unit "up" (ground normal) in the odometry frame, if known


SEGMENT_SEPARATOR = "#"
"""Agent names of trajectory segments: ``car1`` (the first), ``car1#1``, ``car1#2`` ... (robot names
cannot contain it, see ``runner.parse_robot_arg``)."""


SEGMENT_GRACE_S = 1.0
"""After a re-initialisation, predicted poses are not checked against the image motion for this long."""


def segment_agent(robot: str, segment: int) -> str:
    """The map server's agent name of ``robot``'s trajectory segment ``segment`` (0: the robot's name)."""
    return robot if segment == 0 else f"{robot}{SEGMENT_SEPARATOR}{segment}"


def agent_robot(agent: str) -> tuple[str, int]:
    """Inverse of ``segment_agent``: (robot, segment index)."""
    robot, _, seg = agent.partition(SEGMENT_SEPARATOR)
    return robot, int(seg) if seg else 0


@dataclass
class TrajectorySegment:
    """A stretch of one robot's frames with one healthy odometry: its own odometry frame (the camera of
    ``first_frame``), keyframes and semantic graph. The map server treats it as an agent of its own;
    its pose relative to the robot's other segments is unknown until graph matching places it."""

    index: int
    agent: str
    first_frame: int
    graph: SemanticGraph
    keyframes: KeyframeSelector
    kf_frames: list[int] = field(default_factory=list)
    kf_poses: list[np.ndarray] = field(default_factory=list)
    up_sum: np.ndarray = field(default_factory=lambda: np.zeros(3))  # keyframe ground normals, odometry frame
    end_failure: OdometryFailure | None = None  # the divergence that ended it (None: healthy to the end)

    @property
    def num_keyframes(self) -> int:
        return len(self.kf_frames)


@dataclass
class FrameResult:
    """Everything one front-end step produced (for the orchestrator, the viewer and the summary).

    ``agent`` is the trajectory segment the frame belongs to (``segment_agent``); ``failure`` the
    odometry divergence this frame revealed (then the frame starts a new segment), else None.
    ``T_odom_cam`` is NaN for frames that belong to no segment (after a divergence, before the
    odometry measures again).
    """

    robot: str
    frame: Frame
    T_odom_cam: np.ndarray
    depth_m: np.ndarray | None
    label_ids: np.ndarray | None
    points_cam: np.ndarray
    point_labels: np.ndarray | None
    odometry_ok: bool
    message: KeyframeMessage | None
    timings_ms: dict[str, float]
    agent: str = ""
    failure: OdometryFailure | None = None


class RobotFrontend:
    """One robot's front end: perception -> pseudo-LiDAR -> odometry -> keyframes -> semantic graph.

    Each trajectory segment's graph lives in its own odometry frame; nodes are anchored to keyframes.
    With ``cfg.odometry.health_check`` every pose is checked (``odometry.health``); on a divergence the
    segment is cut at its onset (frames from the onset on get NaN poses and segment -1), the odometry
    is re-initialised, and the next measured frame starts a new segment with a fresh graph, sent to
    the map server as a new agent (``segment_agent``).
    """

    def __init__(
        self,
        name: str,
        sequence: Sequence,
        cfg: ShgmConfig,
        perception: PerceptionSource,
        odometry: OdometrySource,
    ) -> None:
        self.name = name
        self.sequence = sequence
        self.cfg = cfg
        self.perception = perception
        self.odometry = odometry
        self.health = (
            OdometryHealthMonitor(HealthLimits.from_config(cfg.odometry)) if cfg.odometry.health_check else None
        )
        n = len(sequence)
        self.T_odom_cam = np.full((n, 4, 4), np.nan)  # each frame in its own segment's odometry frame
        self.frame_kf = np.full(n, -1, dtype=np.int64)  # last keyframe (of its segment) at or before each frame
        self.frame_segment = np.full(n, -1, dtype=np.int64)  # segment of each frame (-1: none)
        self.segments: list[TrajectorySegment] = []
        self.failures: list[OdometryFailure] = []
        self._new_segment(0)

    # --- segments ------------------------------------------------------------------------------

    @property
    def segment(self) -> TrajectorySegment:
        """The current trajectory segment."""
        return self.segments[-1]

    @property
    def graph(self) -> SemanticGraph:
        """The current segment's semantic graph."""
        return self.segment.graph

    @property
    def num_keyframes(self) -> int:
        """Keyframes over all segments."""
        return sum(s.num_keyframes for s in self.segments)

    def _new_segment(self, first_frame: int) -> None:
        k = len(self.segments)
        self.segments.append(
            TrajectorySegment(
                k, segment_agent(self.name, k), first_frame,
                SemanticGraph(self.cfg.graph.merge_radius_m, self.cfg.graph.connectivity_m),
                KeyframeSelector(self.cfg.keyframes.distance_m, self.cfg.keyframes.angle_deg),
            )
        )  # fmt: skip

    def _fail(self, failure: OdometryFailure) -> None:
        """Cut the current segment at the failure's onset and re-initialise the odometry."""
        log.warning("%s: odometry diverged (%s); restarting as a new trajectory segment", self.name, failure.describe())
        self.failures.append(failure)
        seg = self.segment
        seg.end_failure = failure
        cut = np.arange(self.T_odom_cam.shape[0]) >= failure.onset_frame
        cut &= self.frame_segment == seg.index
        self.T_odom_cam[cut] = np.nan
        self.frame_segment[cut] = -1
        self.frame_kf[cut] = -1
        self.odometry.reset()
        self.health.reset()
        # a new segment starts at the next measured frame (the one after a re-initialisation)
        self._new_segment(-1)

    # --- one frame -------------------------------------------------------------------------------

    def process(self, index: int) -> FrameResult:
        """Run frame ``index`` through the front end.

        Raises:
            DataError: the frame cannot be loaded or has no usable depth (the caller logs and skips it).
        """
        t0 = time.perf_counter()
        frame = self.sequence[index]
        t_load = time.perf_counter()
        perceived = self.perception.process(frame)
        t_perc = time.perf_counter()
        o = self.cfg.odometry
        points_cam, point_labels = depth_to_cloud(
            perceived.depth_m,
            frame.intrinsics,
            stride=o.cloud_stride,
            min_range_m=o.min_range_m,
            max_range_m=o.max_range_m,
            label_ids=perceived.label_ids,
        )
        t_cloud = time.perf_counter()
        est = self.odometry.update(frame, points_cam, perceived.depth_m, perceived.label_ids)
        failure = None
        if self.health is not None:
            failure = self._check(index, frame.timestamp_s, est)
            if failure is not None:
                self._fail(failure)
                est = self.odometry.update(frame, points_cam, perceived.depth_m, perceived.label_ids)
                self.health.check(index, frame.timestamp_s, est.T_odom_cam, measured=est.ok)
        seg = self.segment
        if seg.first_frame < 0:  # after a re-initialisation: wait for a measured pose
            if est.ok:
                seg.first_frame = index
                if failure is None:  # (a frame that just failed was checked again above)
                    self.health.check(index, frame.timestamp_s, est.T_odom_cam)
            else:
                self.odometry.reset()
                self.health.reset()
        T_odom_cam = est.T_odom_cam if seg.first_frame >= 0 else np.full((4, 4), np.nan)
        t_odo = time.perf_counter()
        message = None
        timings = {
            "load": (t_load - t0) * 1e3,
            **{f"perception_{k}": v for k, v in perceived.timings_ms.items()},
            "cloud": (t_cloud - t_perc) * 1e3,
            "odometry": (t_odo - t_cloud) * 1e3,
        }
        if seg.first_frame >= 0:
            self.T_odom_cam[index] = T_odom_cam
            self.frame_segment[index] = seg.index
            # keyframes only from measured poses: a prediction may be cut away by a later failure
            if est.ok and seg.keyframes.is_keyframe(T_odom_cam) and perceived.label_ids is not None:
                message = self._keyframe(seg, index, frame, perceived, T_odom_cam, points_cam, point_labels, timings)
            self.frame_kf[index] = seg.num_keyframes - 1
        return FrameResult(
            self.name, frame, T_odom_cam, perceived.depth_m, perceived.label_ids, points_cam, point_labels,
            est.ok, message, timings, seg.agent, failure,
        )  # fmt: skip

    def _check(self, index: int, timestamp_s: float, est: OdometryEstimate) -> OdometryFailure | None:
        seg = self.segment
        if seg.first_frame < 0:
            return None
        disagreement = est.rotation_disagreement_deg
        if not est.ok and timestamp_s - self.sequence.timestamps_s[seg.first_frame] < SEGMENT_GRACE_S:
            # a fresh segment's prediction has no motion to continue yet: a turn it misses is not a
            # divergence (coasting still ends it after ``max_coast_s``); without this a sharp turn right
            # after a re-initialisation cuts one new segment per frame
            disagreement = None
        return self.health.check(
            index, timestamp_s, est.T_odom_cam, measured=est.ok,
            registration_threshold_m=est.threshold_m, rotation_disagreement_deg=disagreement,
        )  # fmt: skip

    def _keyframe(self, seg, index, frame, perceived, T_odom_cam, points_cam, point_labels, timings) -> KeyframeMessage:
        t0 = time.perf_counter()
        ex = self.cfg.extraction
        objects = extract_objects(
            perceived.depth_m,
            perceived.label_ids,
            frame.intrinsics,
            T_odom_cam,
            labels=ex.labels,
            max_depth_m=ex.max_depth_m,
            min_depth_m=ex.min_depth_m,
            depth_step_m=ex.depth_step_m,
            min_blob_fraction=ex.min_blob_fraction,
        )
        t_ex = time.perf_counter()
        kf = seg.num_keyframes
        update = seg.graph.add_keyframe(kf, T_odom_cam, objects)
        t_graph = time.perf_counter()
        seg.kf_frames.append(index)
        seg.kf_poses.append(T_odom_cam.copy())
        n_cam = ground_normal(points_cam, point_labels)
        if n_cam is not None:
            seg.up_sum += T_odom_cam[:3, :3] @ n_cam
        up = seg.up_sum / np.linalg.norm(seg.up_sum) if seg.up_sum.any() else None
        timings["extraction"] = (t_ex - t0) * 1e3
        timings["graph"] = (t_graph - t_ex) * 1e3
        return KeyframeMessage(seg.agent, kf, index, frame.timestamp_s, T_odom_cam.copy(), update, up)


# --------------------------------------------------------------------------------------------------
# Map server (shared back end)
# --------------------------------------------------------------------------------------------------


@dataclass
class MatchRecord:
    """One inter-robot match attempt and what the back end decided (a row of ``matches.json``)."""

    step: int
    robot_a: str
    robot_b: str
    query: str  # "submap" | "whole": which part of robot_b's graph was matched against robot_a's graph
    success: bool
    accepted: bool
    reason: str
    kf_a: int | None
    kf_b: int | None
    T_a_b: np.ndarray | None
    inliers: np.ndarray
    candidates: int
    nodes_a: int
    nodes_b: int
    timings_ms: dict[str, float]
    inlier_positions_a: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    inlier_positions_b: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    closures: list[dict] = field(default_factory=list)
    duplicate: bool = False  # every closure it gave was already in the pose graph (neither new nor rejected)

    def to_json_dict(self) -> dict:
        return {
            "step": self.step,
            "robot_a": self.robot_a,
            "robot_b": self.robot_b,
            "query": self.query,
            "success": self.success,
            "accepted": self.accepted,
            "reason": self.reason,
            "keyframe_a": self.kf_a,
            "keyframe_b": self.kf_b,
            "T_a_b": None if self.T_a_b is None else np.round(self.T_a_b, 9).tolist(),
            "inliers": self.inliers.tolist(),
            "candidates": self.candidates,
            "nodes_a": self.nodes_a,
            "nodes_b": self.nodes_b,
            "timings_ms": {k: round(v, 3) for k, v in self.timings_ms.items()},
            "closures": self.closures,
        }


class MapServer:
    """Mirrors every robot's graph from messages, matches robots periodically, fuses them in iSAM2.

    Every ``match_every_keyframes`` keyframes of a robot r, r's recent submap and r's whole graph are
    matched against every other robot's whole graph (robots here are agents: a robot's trajectory
    segments after odometry failures are agents of their own, added at run time); accepted matches become inter-robot
    relative-pose factors between keyframes. Shared frame = the first robot's odometry frame.
    """

    def __init__(self, robot_names: list[str], cfg: ShgmConfig) -> None:
        self.robot_names = list(robot_names)
        self.cfg = cfg
        self.pose_graph = make_pose_graph(self.robot_names, cfg.backend)
        self.graphs = {r: SemanticGraph(cfg.graph.merge_radius_m, cfg.graph.connectivity_m) for r in robot_names}
        self.kf_poses: dict[str, list[np.ndarray]] = {r: [] for r in robot_names}
        self.up: dict[str, np.ndarray | None] = dict.fromkeys(robot_names)
        self.matches: list[MatchRecord] = []
        self._since_match = dict.fromkeys(robot_names, 0)
        self._closures: set[tuple[str, int, str, int]] = set()
        self._step = 0
        self._num_matches = 0  # successful graph matches so far (each closure's evidence id)
        self.timings_ms: dict[str, list[float]] = {"match": [], "backend": []}

    def add_agent(self, agent: str) -> None:
        """Start mirroring a new agent (a robot's later trajectory segment): its own graph, unanchored
        in the pose graph, matched like any robot against every other agent, its robot's too."""
        self.pose_graph.add_robot(agent)
        self.robot_names.append(agent)
        self.graphs[agent] = SemanticGraph(self.cfg.graph.merge_radius_m, self.cfg.graph.connectivity_m)
        self.kf_poses[agent] = []
        self.up[agent] = None
        self._since_match[agent] = 0

    def receive(self, msg: KeyframeMessage) -> list[MatchRecord]:
        """Ingest one keyframe message (a new agent is added on its first); returns the match attempts it
        triggered (possibly none)."""
        t0 = time.perf_counter()
        self._step += 1
        if msg.robot not in self.graphs:
            self.add_agent(msg.robot)
        self.kf_poses[msg.robot].append(msg.T_odom_kf)
        if msg.up_odom is not None:
            self.up[msg.robot] = msg.up_odom
        self.pose_graph.add_keyframe(msg.robot, msg.kf_index, msg.T_odom_kf)
        self.graphs[msg.robot].apply_update(msg.graph_update, self.kf_poses[msg.robot])
        self.timings_ms["backend"].append((time.perf_counter() - t0) * 1e3)
        self._since_match[msg.robot] += 1
        if self._since_match[msg.robot] < self.cfg.backend.match_every_keyframes:
            return []
        self._since_match[msg.robot] = 0
        return self.match_robot(msg.robot)

    def finalize(self) -> list[MatchRecord]:
        """Match every robot once more at the end of the run (whole graphs)."""
        records: list[MatchRecord] = []
        for r in self.robot_names:
            records += self.match_robot(r, submap=False)
        return records

    def match_robot(self, robot: str, *, submap: bool = True) -> list[MatchRecord]:
        """Match ``robot``'s recent submap and whole graph against every other robot's whole graph."""
        records = []
        queries: list[tuple[str, GraphArrays]] = []
        n_kf = len(self.kf_poses[robot])
        if submap and n_kf > self.cfg.backend.submap_keyframes:
            kfs = np.arange(n_kf - self.cfg.backend.submap_keyframes, n_kf)
            queries.append(("submap", self.graphs[robot].submap(kfs)))
        queries.append(("whole", self.graphs[robot].arrays()))
        for other in self.robot_names:
            if other == robot or len(self.graphs[other]) == 0:
                continue
            graph_a = self.graphs[other].arrays()
            desc_a = compute_descriptors(graph_a, self.cfg.descriptor)
            for query, graph_b in queries:
                records.append(self._match_pair(other, robot, query, graph_a, graph_b, desc_a))
        self.matches += records
        return records

    def _match_pair(
        self, robot_a: str, robot_b: str, query: str, graph_a: GraphArrays, graph_b: GraphArrays, desc_a
    ) -> MatchRecord:
        t0 = time.perf_counter()
        up_a, up_b = self.up[robot_a], self.up[robot_b]
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
        closures = self._local_closures(
            robot_a,
            robot_b,
            result.inliers,
            rec.inlier_positions_a,
            rec.inlier_positions_b,
            result.T_a_b,
            graph_a.label_ids[rows_a],
        )
        self._num_matches += 1
        pg = self.pose_graph
        confirming = pg.min_closures_to_anchor > 1 and not (pg.is_anchored(robot_a) and pg.is_anchored(robot_b))
        for kf_a, kf_b, T_akf_bkf, n in closures:
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
            decision = self.pose_graph.add_inter_robot_closure(
                robot_a, kf_a, robot_b, kf_b, T_akf_bkf, num_inliers=n, match_id=self._num_matches
            )
            self.timings_ms["backend"].append((time.perf_counter() - t1) * 1e3)
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

    def _local_closures(
        self,
        robot_a: str,
        robot_b: str,
        inliers: np.ndarray,
        pos_a: np.ndarray,
        pos_b: np.ndarray,
        T_a_b: np.ndarray,
        labels: np.ndarray,
    ) -> list[tuple[int, int, np.ndarray, int]]:
        """Turn one graph match into keyframe-to-keyframe closures ``(kf_a, kf_b, T_akf_bkf, inliers)``.

        A whole-graph transform averages over both robots' drift; it is exact only near the inliers.
        So the inliers are cut into segments of ``local_closure_m`` along robot a's graph, and every
        segment with enough well-spread inliers gives its own locally refitted closure between the
        keyframes anchoring its central inlier. Without such segments, one closure at the centre.
        """
        seg_m = self.cfg.backend.local_closure_m
        min_n = self.cfg.matching.min_inliers // 2 + 1
        anchors_a = self.graphs[robot_a].anchor_keyframes(inliers[:, 0])
        anchors_b = self.graphs[robot_b].anchor_keyframes(inliers[:, 1])
        order = np.argsort(anchors_a, kind="stable")
        groups: list[np.ndarray] = []
        start = 0
        for i in range(1, len(order) + 1):
            if i == len(order) or np.linalg.norm(pos_a[order[i]] - pos_a[order[start]]) > seg_m:
                groups.append(order[start:i])
                start = i
        out = []
        for g in groups:
            if len(g) < min_n or spread_m(pos_a[g]) < 0.25 * seg_m:
                continue
            T_local = self._refit(robot_a, robot_b, pos_a[g], pos_b[g], labels[g])
            resid = np.linalg.norm(se3.transform_points(T_local, pos_b[g]) - pos_a[g], axis=1)
            if np.sqrt(np.mean(resid**2)) > self.cfg.matching.max_rmse_m:
                continue
            c = g[int(np.argmin(np.linalg.norm(pos_a[g] - pos_a[g].mean(axis=0), axis=1)))]
            out.append((int(anchors_a[c]), int(anchors_b[c]), T_local, len(g)))
        if not out:
            c = int(np.argmin(np.linalg.norm(pos_a - pos_a.mean(axis=0), axis=1)))
            out.append((int(anchors_a[c]), int(anchors_b[c]), T_a_b, len(inliers)))
        return [
            (kf_a, kf_b, se3.inverse(self.kf_poses[robot_a][kf_a]) @ T @ self.kf_poses[robot_b][kf_b], n)
            for kf_a, kf_b, T, n in out
        ]

    def _refit(
        self, robot_a: str, robot_b: str, pos_a: np.ndarray, pos_b: np.ndarray, labels: np.ndarray
    ) -> np.ndarray:
        """Eq. 2 refit ``T_a_b`` of one segment's inliers.

        Compact objects (poles, lights, signs, trees, vehicles) have centroids that do not depend on the
        viewpoint, unlike buildings or road patches seen from different sides, so they alone are used
        when there are at least 4. With both robots' "up" known the fit is 4-DoF (yaw + translation).
        """
        compact = np.isin(labels, COMPACT_LABELS)
        if compact.sum() >= 4:
            pos_a, pos_b = pos_a[compact], pos_b[compact]
        up_a, up_b = self.up[robot_a], self.up[robot_b]
        if up_a is None or up_b is None:
            return se3.kabsch(pos_b, pos_a)
        R_a, R_b = rotation_to_z(up_a), rotation_to_z(up_b)
        T_g = se3.kabsch_yaw(pos_b @ R_b.T, pos_a @ R_a.T)
        return se3.make_pose(R_a.T, np.zeros(3)) @ T_g @ se3.make_pose(R_b, np.zeros(3))

    def T_shared_kf(self, robot: str) -> np.ndarray | None:
        """(K, 4, 4) fused keyframe poses of ``robot`` (an agent) in the shared frame, or None if not
        localized (or not known to the server yet)."""
        if robot not in self.graphs or not self.pose_graph.is_anchored(robot):
            return None
        return self.pose_graph.estimate()[robot]


def _rows_of(graph: GraphArrays, node_ids: np.ndarray) -> np.ndarray:
    """Row indices of ``node_ids`` in ``graph``."""
    order = np.argsort(graph.node_ids)
    return order[np.searchsorted(graph.node_ids, node_ids, sorter=order)]


def fuse_frames(
    T_odom_cam: np.ndarray, frame_kf: np.ndarray, T_odom_kf: np.ndarray, T_shared_kf: np.ndarray
) -> np.ndarray:
    """Per-frame fused poses: each frame rides on its last keyframe's correction.

    Args:
        T_odom_cam: (N, 4, 4) odometry poses of all frames (NaN rows for skipped frames).
        frame_kf: (N,) index of the last keyframe at or before each frame (-1 before the first).
        T_odom_kf: (K, 4, 4) keyframe poses in the odometry frame.
        T_shared_kf: (K, 4, 4) optimized keyframe poses in the shared frame.

    Returns:
        (N, 4, 4) ``T_shared_cam``; NaN where the frame was skipped or precedes the first keyframe.
    """
    out = np.full_like(T_odom_cam, np.nan)
    ok = frame_kf >= 0
    k = frame_kf[ok]
    correction = T_shared_kf[k] @ se3.inverse(T_odom_kf[k])
    out[ok] = correction @ T_odom_cam[ok]
    return out


# --------------------------------------------------------------------------------------------------
# Interleaving robots in time
# --------------------------------------------------------------------------------------------------


def interleave(sequences: dict[str, Sequence]) -> Iterator[tuple[str, int]]:
    """Yield ``(robot, frame_index)`` in order of time since each robot's first frame."""
    heap = []
    for r_i, (name, seq) in enumerate(sequences.items()):
        if len(seq):
            t = np.asarray(seq.timestamps_s, dtype=np.float64)
            heap.append((0.0, r_i, name, 0, t))
    heapq.heapify(heap)
    while heap:
        _, r_i, name, i, t = heapq.heappop(heap)
        yield name, i
        if i + 1 < len(t):
            heapq.heappush(heap, (float(t[i + 1] - t[0]), r_i, name, i + 1, t))
