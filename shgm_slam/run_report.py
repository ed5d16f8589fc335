"""What a ``run`` reports: each robot's outcome and its evaluation against ground truth, the run's summary, each
step's cost.

The records: ``RobotReport`` (one row of the summary table), ``RunSummary`` (what ``runner.run_slam`` returns and
writes as ``metrics.json``), ``FrameStats`` (what one step cost, for benchmarks) and ``StageTimings`` (the mean time
per call of each stage). Once the run is done ``evaluate`` makes the robots' reports (fused trajectories of the
placed segments, ``fused_poses``; ATEs against ground truth), and ``report_placement`` and ``report_degenerate``
add their warnings. Nothing here prints, logs or talks to the viewer: ``runner`` says the warnings.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shgm_slam.backend.keys import MAX_AGENTS
from shgm_slam.config import OdometryKind
from shgm_slam.environment import environment
from shgm_slam.fusion import fuse_segments
from shgm_slam.geometry import se3
from shgm_slam.metrics import ate, joint_ate
from shgm_slam.odometry.stillness import ImageChange, odometry_motion, stillness_warning
from shgm_slam.perception.ground_scale import USUAL_FACTOR, usual_factor
from shgm_slam.robot.frontend import RobotFrontend
from shgm_slam.server.map_server import MapServer
from shgm_slam.server.records import MatchRecord, PairMatches
from shgm_slam.types import Intrinsics


@dataclass
class RobotReport:
    """Per-robot outcome of a run (one row of the summary table)."""

    name: str
    frames: int
    frames_processed: int
    frames_skipped: int  # reached but not processed (unreadable, a worker lost; reasons in the run's 'skipped')
    keyframes: int
    nodes: int
    localized: bool
    path_length_m: float = float("nan")
    # ATEs (RMSE, metres). "shared": in the shared frame without alignment (needs shared ground truth);
    # odometry alone is placed at the robot's TRUE start pose there, the best it could do without matching.
    ate_odometry_m: float = float("nan")
    ate_fused_m: float = float("nan")
    ate_odometry_aligned_m: float = float("nan")  # SE(3)-aligned (shape only)
    ate_fused_aligned_m: float = float("nan")
    # after ONE SE(3) fit of every placed robot's fused poses together (``metrics.joint_ate``): the shared frame
    # without the first robot's own drift, i.e. how well the robots agree (needs shared ground truth)
    ate_fused_joint_m: float = float("nan")
    # odometry health: each detected divergence cuts the trajectory and starts a new segment whose pose
    # is unknown until graph matching places it; the odometry ATEs above treat each segment on its own
    # (placed at its true first pose / aligned on its own). ``localized``: every segment with keyframes
    # is placed; ``placed_fraction``: the share of the robot's segment frames that are in the shared frame.
    segments: int = 1
    segments_placed: int = 0
    placed_fraction: float = 0.0
    fused_poses: int = 0  # rows of <robot>_fused_tum.txt (``eval`` refuses a file that holds fewer or more)
    frames_not_reached: int = 0  # the run was interrupted before these frames
    odometry_failures: int = 0
    failure_reasons: list[str] = field(default_factory=list)
    frames_dropped: int = 0  # frames between a divergence's onset and the next segment's first frame
    segment_start_frames: list[int] = field(default_factory=list)  # first frame of each segment
    # degenerate data, reported, never hidden: skipped frames, no graph nodes, odometry that did not move
    # while the images did (then ``localized`` is False: the trajectory is known to be invalid)
    warnings: list[str] = field(default_factory=list)
    # placed from a single piece of evidence (``backend.confirmation``): no independent graph match confirms
    # a segment's place in the shared frame yet; it may be wrong (its fused trajectory is written, marked so)
    provisional: bool = False
    odometry: str = ""  # the odometry kind the robot ran (``--odometry auto`` resolved)
    odometry_reason: str = ""  # why (auto's reason, or "set in the configuration")
    # visual odometry: share of its measured frames whose turn came from a ground vehicle's planar motion
    # (``odometry/planar_motion.py``; a UAV's frames keep PnP's); None for other odometries
    planar_turn_share: float | None = None
    # its odometry's heading drift as its own loop closures measured it, degrees per 100 m, where more than the
    # pose graph's prior (``backend/drift.py``: its odometry factors then weigh that much less); None otherwise
    measured_drift_deg_per_100m: float | None = None
    road_step_share: float | None = None
    # visual odometry holding a camera's tilt to the ground in view (``odometry.visual_ground_attitude``, a UAV):
    # share of its tracking references turned towards level; None where that is off
    levelled_share: float | None = None
    # KISS-ICP: frames where its step slipped against the image motion and the step solved from image tracks was
    # kept (``odometry/flow_check.py``); None for other odometries
    image_steps: int | None = None
    # KISS-ICP: frames where its motion over the last second slid against the image motion and the motion solved
    # from image tracks was kept (``odometry/window_check.py``); None for other odometries
    image_windows: int | None = None
    # predicted depth scaled to the camera's height above the road (``perception/ground_scale.py``): the
    # median factor (None: no frame scaled) and the share of processed frames scaled (None: not on for this
    # robot - measured depth, or perception.camera_height_m null; 0.0: on, but no level road at a plausible
    # height was found, e.g. a UAV)
    depth_scale: float | None = None
    depth_scale_share: float | None = None
    # the depth's random error relative to the depth that the robot's KISS-ICP voxel and spacing filter were sized
    # to (``odometry.depth_noise_rel``: measured on its first frames, ``scene_scale``, unless set in the config)
    depth_noise_rel: float | None = None
    voxel_size_m: float | None = None  # its KISS-ICP voxel (derived or set)
    # the longest stretch of its placed path that rests on its own odometry: metres of path from a keyframe to the
    # nearest one a factor ties to the shared frame (a closure's end; the prior for the first robot), the most over
    # its placed segments (``MapServer.path_from_closures_m``); None when no segment is placed
    path_from_closures_m: float | None = None
    # why its front end was lost mid-run (its worker process died, or failed on an error: a fault of the program or
    # the machine, not of the data); its later frames were skipped. None: it ran to its end
    front_end_lost: str | None = None


@dataclass
class RunSummary:
    """What ``run_slam`` returns: per-robot reports, closures, timings and where the results are."""

    out_dir: Path
    robots: list[RobotReport]
    matches_tried: int
    closures_accepted: int
    closures_rejected: int
    timings_ms: dict[str, float]  # mean per call of each stage
    per_keyframe_ms: float  # front end + back end (no loading, no perception) per keyframe
    wall_s: float
    interrupted: bool = False
    skipped_reasons: list[str] = field(default_factory=list)
    pairs: list[PairMatches] = field(default_factory=list)  # how the matches between each two robots went
    last_looks: list[str] = field(default_factory=list)  # ``MapServer.last_looks``: what each last look found
    ate_joint_m: float = float("nan")  # all placed robots' fused poses under one joint SE(3) fit, RMSE, metres

    @property
    def front_ends_lost(self) -> list[str]:
        """Why each robot whose front end was lost mid-run lost it (``RobotReport.front_end_lost``)."""
        return [r.front_end_lost for r in self.robots if r.front_end_lost]

    def to_json_dict(self) -> dict:
        return {
            "robots": [vars(r) for r in self.robots],
            "matches_tried": self.matches_tried,
            "closures_accepted": self.closures_accepted,
            "closures_rejected": self.closures_rejected,
            "pairs": [p.to_json_dict() for p in self.pairs],
            "timings_ms": self.timings_ms,
            "per_keyframe_ms": self.per_keyframe_ms,
            "wall_s": self.wall_s,
            "interrupted": self.interrupted,
            "skipped": self.skipped_reasons[:50],
            "last_looks": self.last_looks,
            "ate_joint_m": self.ate_joint_m,
            "environment": environment(),
        }


@dataclass(frozen=True)
class FrameStats:
    """What one step of ``run_slam`` cost (for benchmarks): ``front_end_ms`` the robot's stages without
    loading and perception (``RobotFrontend.process``: cloud, odometry, extraction, graph); ``load_ms``
    loading the frame and perception; ``match_ms`` / ``backend_ms`` the server's graph matching and
    pose-graph work the step triggered; ``server_ms`` the whole server poll (those two, decoding,
    corrections, results files; ``write_ms`` and ``correction_ms`` of them rewriting the results folder and
    answering the robots); ``step_ms`` the whole step (all of these and the viewer), wall time;
    ``step_cpu_ms`` its CPU time (all threads of the process: what it costs, whatever else the machine
    runs). ``matches`` the attempts it triggered."""

    robot: str
    frame_index: int
    keyframe: bool
    front_end_ms: float
    load_ms: float
    match_ms: float
    backend_ms: float
    server_ms: float
    step_ms: float
    matches: tuple[MatchRecord, ...] = ()
    step_cpu_ms: float = 0.0
    write_ms: float = 0.0
    correction_ms: float = 0.0


class StageTimings:
    """Mean time per call of each stage over a run's steps (``RunSummary.timings_ms``)."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    def add(self, timings: dict[str, float]) -> None:
        for k, v in timings.items():
            self.sums[k] = self.sums.get(k, 0.0) + v
            self.counts[k] = self.counts.get(k, 0) + 1

    def means(self) -> dict[str, float]:
        return {k: self.sums[k] / self.counts[k] for k in self.sums}


def evaluate(
    fronts, server: MapServer, robots, processed, gt_shared_frame: bool, reached: dict[str, int] | None = None
) -> tuple[list[RobotReport], float]:
    """Each robot's report, and the RMSE of all placed robots' fused poses under one joint SE(3) fit (NaN
    without shared ground truth). ``reached``: frames per robot whose turn came (default: all of them)."""
    names = list(robots)
    gt0 = robots[names[0]].gt_poses
    reports = []
    joint: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # report row -> (M, 4, 4) ground truth, fused
    for r, front in fronts.items():
        seq = robots[r]
        fused = fused_poses(front, server)
        placed = {k for k, _ in placed_segments(front, server)}
        with_kf = [s for s in front.segments if s.num_keyframes]
        in_seg = front.frame_segment >= 0
        came = len(seq) if reached is None else reached[r]
        rep = RobotReport(
            r, len(seq), processed[r], came - processed[r], front.num_keyframes,
            sum(s.num_nodes for s in front.segments), bool(with_kf) and all(s.index in placed for s in with_kf),
        )  # fmt: skip
        rep.frames_not_reached = len(seq) - came
        rep.fused_poses = 0 if fused is None else int(np.isfinite(fused.reshape(len(fused), -1)).all(axis=1).sum())
        if front.odometry_choice is not None:
            rep.odometry, rep.odometry_reason = front.odometry_choice.kind.value, front.odometry_choice.reason
        if rep.odometry == OdometryKind.VISUAL.value and front.measured_frames:
            rep.planar_turn_share = front.planar_turns / front.measured_frames
            rep.road_step_share = front.road_steps / front.measured_frames
            if front.cfg.odometry.visual_ground_attitude and front.references:
                rep.levelled_share = front.levelled_references / front.references
        if rep.odometry == OdometryKind.KISS_ICP.value:
            rep.image_steps = front.image_steps
            rep.image_windows = front.image_windows
        rep.depth_noise_rel, rep.voxel_size_m = front.cfg.odometry.depth_noise_rel, front.cfg.odometry.voxel_size_m
        if front.ground_scale_on:
            rep.depth_scale_share = len(front.depth_scales) / max(processed[r], 1)
            rep.depth_scale = float(np.median(front.depth_scales)) if front.depth_scales else None
        rep.path_from_closures_m = server.longest_path_from_closures_m([s.agent for s in with_kf])
        drifts = [d for s in with_kf if (d := server.measured_drift(s.agent)) is not None]
        rep.measured_drift_deg_per_100m = float(np.degrees(max(drifts)) * 100.0) if drifts else None
        rep.segment_start_frames = [int(s.first_frame) for s in front.segments if s.first_frame >= 0]
        rep.segments = len(rep.segment_start_frames)
        rep.segments_placed = len(placed)
        rep.placed_fraction = float(np.isin(front.frame_segment, list(placed)).sum() / max(in_seg.sum(), 1))
        rep.odometry_failures = len(front.failures)
        rep.failure_reasons = [f.describe() for f in front.failures]
        rep.frames_dropped = int((~in_seg).sum()) - (len(seq) - processed[r])
        gt = seq.gt_poses
        ok = np.isfinite(front.T_odom_cam.reshape(len(seq), -1)).all(axis=1)
        if gt is not None and ok.sum() >= 3:
            rep.path_length_m = float(np.linalg.norm(np.diff(gt[ok][:, :3, 3], axis=0), axis=1).sum())
            shared = gt_shared_frame and gt0 is not None
            gt_ref = se3.inverse(gt0[0]) @ gt if shared else gt
            sq_aligned, sq_start = [], []
            for seg in front.segments:  # each segment on its own: their relative poses are unknown
                rows = ok & (front.frame_segment == seg.index)
                if not rows.any():
                    continue
                odo = front.T_odom_cam[rows]
                if rows.sum() >= 3:
                    sq_aligned.append(ate(gt[rows], odo, align="se3")["rmse"] ** 2 * rows.sum())
                placed_at_start = gt_ref[rows][0] @ se3.inverse(odo[0]) @ odo
                sq_start.append(np.sum((placed_at_start[:, :3, 3] - gt_ref[rows][:, :3, 3]) ** 2))
            rep.ate_odometry_aligned_m = float(np.sqrt(sum(sq_aligned) / ok.sum()))
            if shared:
                rep.ate_odometry_m = float(np.sqrt(sum(sq_start) / ok.sum()))
            if fused is not None:
                okf = ok & np.isfinite(fused.reshape(len(seq), -1)).all(axis=1)
                rep.ate_fused_aligned_m = ate(gt[okf], fused[okf], align="se3")["rmse"]
                if shared:
                    rep.ate_fused_m = ate(gt_ref[okf], fused[okf], align="none")["rmse"]
                    joint[len(reports)] = (gt_ref[okf], fused[okf])
        reports.append(rep)
    if not joint:
        return reports, float("nan")
    per_robot, together = joint_ate([g for g, _ in joint.values()], [f for _, f in joint.values()])
    for row, stats in zip(joint, per_robot, strict=True):
        reports[row].ate_fused_joint_m = stats.rmse
    return reports, together.rmse


def placed_segments(front: RobotFrontend, server: MapServer) -> list[tuple[int, np.ndarray]]:
    """(segment index, (K, 4, 4) T_shared_kf) of every segment of ``front`` placed in the shared frame."""
    out = []
    for seg in front.segments:
        T_shared_kf = server.T_shared_kf(seg.agent) if seg.num_keyframes else None
        if T_shared_kf is not None:
            out.append((seg.index, T_shared_kf))
    return out


def fused_poses(front: RobotFrontend, server: MapServer) -> np.ndarray | None:
    """(N, 4, 4) fused poses: the frames of every placed segment in the shared frame, NaN elsewhere;
    None when no segment is placed."""
    segs = [s for s in front.segments if s.num_keyframes]
    return fuse_segments(
        front.T_odom_cam, front.frame_segment,
        {s.index: np.asarray(s.kf_frames, dtype=np.int64) for s in segs},
        {s.index: np.stack(s.kf_poses) for s in segs},
        dict(placed_segments(front, server)),
    )  # fmt: skip


def report_placement(reports: list[RobotReport], fronts: dict[str, RobotFrontend], server: MapServer) -> None:
    """Flag each robot with a segment placed from a single piece of evidence, and say why a segment with
    accepted closures is not placed (too few independent matches): a warning each."""
    for rep in reports:
        for seg in fronts[rep.name].segments:
            rep.provisional |= server.placement(seg.agent).provisional
            if (note := server.placement_note(seg.agent)) is not None:
                rep.warnings.append(note)


MIN_CAMERA_PIXELS = 320 * 96 // 4
"""Cameras with fewer pixels than this get a warning: the defaults were chosen on 320x96 and larger images; at 80x24
and 64x48 the demo world's robots ran but none but the first was placed, with nothing naming the camera."""
MIN_CAMERA_HFOV_DEG = 20.0
"""Cameras whose horizontal field of view is narrower than this get a warning: at 10 degrees the demo world's cars
saw too few objects to build a graph (the defaults were chosen at 60-90 degrees)."""


def camera_warning(intrinsics: Intrinsics) -> str | None:
    """A warning when ``intrinsics`` describe a camera far smaller or narrower than the defaults were chosen on
    (``MIN_CAMERA_PIXELS``, ``MIN_CAMERA_HFOV_DEG``), else None."""
    hfov_deg = float(np.degrees(2.0 * np.arctan2(intrinsics.width / 2.0, intrinsics.fx)))
    small = intrinsics.width * intrinsics.height < MIN_CAMERA_PIXELS
    if not small and hfov_deg >= MIN_CAMERA_HFOV_DEG:
        return None
    what = f"{intrinsics.width}x{intrinsics.height} pixels" if small else f"a {hfov_deg:.0f}-degree field of view"
    return (f"camera of {what}: the defaults were chosen on 320x96 or larger images of 60-90 degrees; expect few "
            "graph objects and weak odometry, so a robot that is not placed may owe it to the camera")


def report_degenerate(
    reports: list[RobotReport], fronts: dict[str, RobotFrontend], image_change: dict[str, ImageChange]
) -> None:
    """Add each robot's degenerate-data warnings to its report (``runner`` says every warning in the log and the
    viewer's log panel)."""
    for rep in reports:
        front = fronts[rep.name]
        camera = camera_warning(front.sequence.intrinsics)
        if camera is not None:
            rep.warnings.append(camera)
        if rep.frames_skipped:
            rep.warnings.append(f"{rep.frames_skipped} of {rep.frames} frames skipped (reasons in 'skipped')")
        if rep.frames_not_reached:
            rep.warnings.append(
                f"interrupted: {rep.frames_not_reached} of its {rep.frames} frames were not run (from frame "
                f"{rep.frames - rep.frames_not_reached} of the range on)"
            )
        if front.stopped:
            rep.warnings.append(
                f"stopped at frame {front.failures[-1].onset_frame}: its odometry diverged {len(front.failures)} "
                f"times, and {front.max_segments} trajectory segments is each robot's share of the pose graph's "
                f"{MAX_AGENTS} agents in a run of {len(reports)} robots; its later frames are dropped (reasons in "
                "'failure_reasons'; check its depth, timestamps and odometry)"
            )
        if rep.depth_scale is not None and not usual_factor(rep.depth_scale):
            rep.warnings.append(
                f"predicted depth scaled by x{rep.depth_scale:.2f} (median) to put the road "
                f"{front.cfg.perception.camera_height_m:g} m below the camera, outside the usual "
                f"x{USUAL_FACTOR[0]:g}-{USUAL_FACTOR[1]:g}: the depth model's metric scale is far off on these images "
                "(a model trained on other scenes varies from frame to frame too), or the camera is not mounted at "
                "that height (set perception.camera_height_m)"
            )
        if rep.frames_processed and rep.nodes == 0:
            rep.warnings.append(
                "no graph nodes: no object passed extraction, so it cannot be matched (check the labels, "
                "extraction.labels, the depth range and the blob size)"
            )
        if rep.frames_processed:
            still = stillness_warning(*odometry_motion(front.T_odom_cam, front.frame_segment), image_change[rep.name],
                                      given=rep.odometry == OdometryKind.GIVEN.value)  # fmt: skip
            if still is not None:
                rep.warnings.append(still)
                rep.localized = False  # a trajectory known to be invalid is never "fused"
