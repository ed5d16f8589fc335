"""The library function behind ``shgm-slam run``: robots in, fused trajectories and a summary out.

``run_slam`` interleaves the robots in time, streams every stage to the viewer, writes the results
folder as it goes (and once more at the end, also after Ctrl-C), and evaluates against ground truth
when the sequences have it.
"""

from __future__ import annotations

import contextlib
import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shgm_slam.arrays import thinning_stride
from shgm_slam.backend.keys import MAX_AGENTS, segments_per_robot
from shgm_slam.config import OdometryKind, ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.data.base import parse_sequence_spec
from shgm_slam.data.interleave import interleave
from shgm_slam.environment import environment
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.fusion import fuse_segments
from shgm_slam.geometry import se3
from shgm_slam.interrupts import stops_deferred
from shgm_slam.io.export import ResultsWriter, check_outside_sequence
from shgm_slam.metrics import ate, joint_ate
from shgm_slam.odometry.stillness import ImageChange, odometry_motion, stillness_warning
from shgm_slam.robot.build import make_frontend
from shgm_slam.robot.frontend import FrameResult, RobotFrontend
from shgm_slam.robot.node import RobotNode
from shgm_slam.robot.remote import ParallelFrontends
from shgm_slam.run_view import RunView
from shgm_slam.scene_scale import effective_fields
from shgm_slam.server.map_server import MapServer
from shgm_slam.server.node import ServerNode
from shgm_slam.server.placement import PlacementWatch
from shgm_slam.server.records import MatchRecord, PairMatches, pair_matches
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.keys import validate_robot_name
from shgm_slam.types import Sequence
from shgm_slam.viz.rerun_logger import NullLogger, Viz

log = logging.getLogger(__name__)

_ROBOT_RE = re.compile(r"^(?P<name>[^=]*)=(?P<spec>.+)$")


def parse_robot_arg(text: str) -> tuple[str, str]:
    """Split ``NAME=PATH[:start-end]`` into ``(name, spec)``.

    Raises:
        ConfigError: the text is not of that form, or the name is not a valid robot name
            (``transport.keys.validate_robot_name``: 1-32 characters, a letter first; ``server`` is reserved).
    """
    m = _ROBOT_RE.match(text.strip())
    if not m:
        raise ConfigError(
            f"--robot {text!r}: expected NAME=PATH[:start-end], e.g. car1=data/seq08:0-1500 "
            "(names start with a letter; letters, digits, _ and - only)"
        )
    try:
        validate_robot_name(m["name"])
    except ConfigError as exc:
        raise ConfigError(f"--robot {text!r}: {exc}") from None
    return m["name"], m["spec"]


def open_robots(robot_args: list[str]) -> dict[str, Sequence]:
    """Open every ``NAME=PATH[:start-end]`` robot; clear errors for duplicates and empty sequences."""
    if not robot_args:
        raise ConfigError("no robots given: pass at least one --robot NAME=PATH[:start-end]")
    robots: dict[str, Sequence] = {}
    for arg in robot_args:
        name, spec = parse_robot_arg(arg)
        if name in robots:
            raise ConfigError(f"robot name {name!r} is given twice; every --robot needs its own name")
        seq = open_sequence(spec)
        if len(seq) == 0:
            raise DataError(f"robot {name!r}: sequence {spec} has zero frames (check the frame range)")
        robots[name] = seq
    return robots


def check_out_outside_sequences(out: Path, robot_args: list[str]) -> None:
    """Refuse a results folder that is a robot's sequence folder or lies inside one.

    Raises:
        ConfigError: ``out`` is (inside) the folder of a robot's ``NAME=PATH[:start-end]``: the results would
            be written among the sequence's files (a ``graph_*.json`` or ``run.rrd`` in a sequence others read).
    """
    for arg in robot_args:
        name, spec = parse_robot_arg(arg)
        check_outside_sequence(out, parse_sequence_spec(spec)[0], f"of robot {name!r} ")


def fleet_backend(cfg: ShgmConfig, fronts: dict[str, RobotFrontend]) -> ShgmConfig:
    """``cfg`` with the back end's depth-dependent values (still None) set from where the fleet's depth comes
    from (``BackendConfig.for_depth``: predicted when any robot's depth model predicts it)."""
    predicted = [r for r, f in fronts.items() if f.depth_predicted]
    backend = cfg.backend.for_depth(predicted_depth=bool(predicted))
    if predicted and backend != cfg.backend:
        log.info("odometry on predicted depth (%s): pose-graph odometry sigmas grow %.3f rad and %.0f %% per "
                 "metre", ", ".join(predicted), backend.odometry_drift_rot_rad_per_m,
                 100 * backend.odometry_drift_trans_per_m)  # fmt: skip
    return cfg.model_copy(update={"backend": backend})


def effective_config(cfg: ShgmConfig, robot_cfgs: dict[str, ShgmConfig]) -> ShgmConfig:
    """``cfg`` with each robot's data-derived values (``resolve_robot_config``) written into its
    ``robots`` overrides: loading it reproduces every front end's settings."""
    return cfg.with_robot_values({name: effective_fields(rcfg) for name, rcfg in robot_cfgs.items()})


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


ProgressFn = Callable[[int, int], None]


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


FrameFn = Callable[[FrameStats], None]


class _Timings:
    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    def add(self, timings: dict[str, float]) -> None:
        for k, v in timings.items():
            self.sums[k] = self.sums.get(k, 0.0) + v
            self.counts[k] = self.counts.get(k, 0) + 1

    def means(self) -> dict[str, float]:
        return {k: self.sums[k] / self.counts[k] for k in self.sums}


def prepare_frontends(robots: dict[str, Sequence], cfg: ShgmConfig) -> dict[str, RobotFrontend]:
    """Every robot's front end (``make_frontend``), after checking that ``cfg.robots`` names only these robots.

    This is everything that can refuse a run (config, models, the first frames); the CLI calls it before it
    creates the results folder, so a refused run leaves nothing behind that the next one would have to clear.
    Each robot may start ``segments_per_robot`` trajectory segments: together they fit the pose graph.

    Raises:
        ConfigError, DataError, ModelError: what ``make_frontend`` raises; overrides for unknown robots; more
            robots than the pose graph holds (``MAX_AGENTS``).
    """
    names = list(robots)
    if len(names) > MAX_AGENTS:
        raise ConfigError(
            f"{len(names)} robots: the pose graph holds at most {MAX_AGENTS} agents (robots and their trajectory "
            f"segments after odometry failures); run at most {MAX_AGENTS} robots"
        )
    unknown = sorted(set(cfg.robots) - set(names))
    if unknown:
        raise ConfigError(
            f"the config has settings for robot(s) {', '.join(unknown)} that are not in this run "
            f"({', '.join(names)}); fix the names under 'robots:'"
        )
    # each robot's share of the pose graph's agents: a robot whose odometry keeps failing stops at its share
    # (a logged skip of its later frames) instead of ending the whole run when the agents run out
    share = segments_per_robot(len(names))
    return {r: make_frontend(r, seq, cfg, max_segments=share) for r, seq in robots.items()}


def run_slam(
    robots: dict[str, Sequence],
    cfg: ShgmConfig,
    out_dir: Path,
    *,
    viz: Viz | None = None,
    progress: ProgressFn | None = None,
    gt_shared_frame: bool = True,
    write_every_keyframes: int = 25,
    on_frame: FrameFn | None = None,
    journal: bool = False,
    fronts: dict[str, RobotFrontend] | None = None,
    jobs: int = 1,
) -> RunSummary:
    """Run the whole multi-robot system and write the results folder.

    A run that ends with an error after writing into ``out_dir`` leaves ``incomplete.txt`` there (why; the other
    files are its last checkpoint), so that folder is not taken for results (``eval`` refuses it).

    Args:
        robots: robot name -> sequence (order matters: the first robot defines the shared frame).
        cfg: the fleet configuration; ``config.yaml`` gets it with every robot's derived values
            (``effective_config``).
        out_dir: results folder (created).
        viz: viewer (``NullLogger`` when None).
        progress: called with (frames done, frames total).
        gt_shared_frame: the sequences' ground truths share one world frame (true for our simulator and
            for frame ranges of one KITTI sequence), so fused ATE is measured in the shared frame.
        write_every_keyframes: rewrite the results folder this often (survives crashes and Ctrl-C).
        on_frame: called after every processed frame with what it cost (``FrameStats``).
        journal: keep the map server's message journal (``journal.bin``) in ``out_dir``: every keyframe
            the robots sent, in order, so the back end can be run again on it (``replay_backend``).
        fronts: the robots' front ends from ``prepare_frontends`` (None: opened here, before anything is written).
        jobs: run the robots' front ends in this many worker processes (``robot.remote``; 1: all in this
            process; at most one per robot): the same results, sooner on several cores. ``fronts`` then
            only validate the run and give each robot's resolved configuration (their models are freed); the
            workers build their own.
    """
    viz = viz or NullLogger()
    if fronts is None:
        fronts = prepare_frontends(robots, cfg)
    schedule = list(interleave(robots))
    with contextlib.ExitStack() as workers:
        if jobs > 1 and len(robots) > 1:
            fronts = workers.enter_context(ParallelFrontends(
                fronts, cfg, schedule, jobs, viewer_points=viz.max_cloud_points))
        try:
            return _run(robots, cfg, out_dir, fronts, schedule, viz, progress, gt_shared_frame, write_every_keyframes,
                        on_frame, journal)  # fmt: skip
        except Exception as exc:  # re-raised: what was written so far must not pass for the run's results
            if Path(out_dir).is_dir():
                ResultsWriter(out_dir).mark_failed(exc)
            raise
        except KeyboardInterrupt:  # a second stop while the results were written (the first one is kept)
            if Path(out_dir).is_dir():
                with contextlib.suppress(DataError):
                    ResultsWriter(out_dir).mark_incomplete("stopped again while its results were being written")
                log.warning("stopped while writing the results: %s holds a checkpoint, marked by incomplete.txt",
                            out_dir)  # fmt: skip
            raise


def _run(robots, cfg, out_dir, fronts, schedule, viz, progress, gt_shared_frame, write_every_keyframes, on_frame,
         journal) -> RunSummary:  # fmt: skip
    names = list(robots)
    writer = ResultsWriter(out_dir)
    writer.write_ground_truth(robots, gt_shared_frame)  # <robot>_gt_tum.txt, for evo and `shgm-slam eval`
    cfg = fleet_backend(cfg, fronts)
    # the same nodes as the distributed deployment, on the in-process bus (every message is encoded)
    bus = InProcessBus()
    server_node = ServerNode(
        cfg, InProcessTransport(bus), out_dir, reference=names[0], expect=len(names), journal=journal,
        write_every_keyframes=write_every_keyframes, stale_after_s=float("inf"),  # one process: never silent
        order_keyframes=False,  # interleave() steps the robots in the server's keyframe order already
    )  # fmt: skip
    nodes = {r: RobotNode(f, InProcessTransport(bus)) for r, f in fronts.items()}
    for node in nodes.values():
        node.hello()
    server_node.poll()
    server = server_node.map
    viz.setup({r: seq.intrinsics for r, seq in robots.items()})
    view = RunView(viz)
    writer.write_text("config.yaml", effective_config(cfg, {r: f.cfg for r, f in fronts.items()}).to_yaml())
    total = sum(len(s) for s in robots.values())
    timings = _Timings()
    skipped: list[str] = []
    processed = dict.fromkeys(names, 0)
    reached = dict.fromkeys(names, 0)  # frames whose turn came (the rest: not reached, the run interrupted)
    image_change = {r: ImageChange() for r in names}
    compute_ms = 0.0
    t_start = time.perf_counter()
    done = 0
    interrupted = False
    kf_total = 0
    watch = PlacementWatch()
    try:
        for robot, index in schedule:
            with stops_deferred():  # a stop lands between frames, never inside the server's or a robot's step
                done += 1
                reached[robot] += 1
                t_step, cpu_step = time.perf_counter(), time.process_time()
                try:
                    res = nodes[robot].step(index)
                except DataError as exc:
                    skipped.append(f"{robot} frame {index}: {exc}")
                    if not getattr(exc, "repeat", False):  # a lost worker costs every later frame: said once
                        viz.log_text(f"{robot}: skipped frame {index}: {exc}", "WARN")
                    if progress:
                        progress(done, total)
                    continue
                processed[robot] += 1
                if not fronts[robot].stopped:  # a stopped robot's dropped frames say nothing about its odometry
                    image_change[robot].add(res.frame.image_rgb)
                if res.failure is not None:
                    then = "its later frames are dropped" if fronts[robot].stopped else (
                        f"new trajectory segment {res.agent}")  # fmt: skip
                    viz.log_odometry_failure(
                        robot, f"{robot}: odometry diverged, {res.failure.describe()}; {then}",
                        _last_healthy_position(fronts[robot], server),
                    )  # fmt: skip
                t0 = time.perf_counter()
                n_match, n_backend = len(server.timings_ms["match"]), len(server.timings_ms["backend"])
                n_write, n_corr = len(server_node.timings_ms["write"]), len(server_node.timings_ms["correction"])
                records = server_node.poll()
                res.timings_ms["server"] = (time.perf_counter() - t0) * 1e3
                nodes[robot].poll()
                timings.add(res.timings_ms)
                step_compute = sum(v for k, v in res.timings_ms.items() if k != "load" and not k.startswith("perc"))
                compute_ms += step_compute
                _log_frame(viz, view, server, fronts[robot], res, records)
                if records:
                    _log_placements(viz, watch, server)
                kf_total += res.message is not None
                if on_frame is not None:
                    match_ms = sum(server.timings_ms["match"][n_match:])
                    backend_ms = sum(server.timings_ms["backend"][n_backend:])
                    on_frame(FrameStats(
                        robot, index, res.message is not None, step_compute - res.timings_ms["server"],
                        sum(res.timings_ms.values()) - step_compute, match_ms, backend_ms, res.timings_ms["server"],
                        (time.perf_counter() - t_step) * 1e3, tuple(records), (time.process_time() - cpu_step) * 1e3,
                        sum(server_node.timings_ms["write"][n_write:]),
                        sum(server_node.timings_ms["correction"][n_corr:]),
                    ))  # fmt: skip
                if progress:
                    progress(done, total)
    except KeyboardInterrupt:
        interrupted = True
    if interrupted:  # no final matching: write what there is
        server_node.expect = None
    for node in nodes.values():
        node.done()
    records = []
    try:
        with stops_deferred():  # every robot done: the server matches whole graphs and writes the results
            records = server_node.poll()
    except KeyboardInterrupt:  # stopped during the final matching: it ended, and the run says it was stopped
        interrupted = True
    if not server_node.finished:
        server_node.finish(match=not interrupted)
    _log_matches(viz, server, records)
    _log_placements(viz, watch, server)
    if viz.enabled:
        view.finish(server, fronts.values())  # the viewer ends on the final estimate, not the last keyframe's
    for node in nodes.values():
        node.poll()
    reports, ate_joint_m = _evaluate(fronts, server, robots, processed, gt_shared_frame, reached)
    _report_placement(reports, fronts, server)
    _report_degenerate(reports, fronts, image_change, viz)
    accepted = sum(m.accepted for m in server.matches)
    summary = RunSummary(
        out_dir=Path(out_dir),
        robots=reports,
        matches_tried=len(server.matches),
        closures_accepted=accepted,
        closures_rejected=sum(m.success and not m.accepted and not m.duplicate for m in server.matches),
        pairs=pair_matches(server.matches),
        timings_ms={
            **timings.means(),
            "match": server.mean_match_ms(),
        },
        per_keyframe_ms=compute_ms / max(kf_total, 1),
        wall_s=time.perf_counter() - t_start,
        interrupted=interrupted,
        skipped_reasons=skipped,
        last_looks=server.last_looks(),
        ate_joint_m=ate_joint_m,
    )
    for line in filter(None, (p.never_met() for p in summary.pairs)):
        viz.log_text(line, "WARN")  # the viewer's log panel says why two robots never met
    writer.write_json("metrics.json", summary.to_json_dict())
    viz.close()
    return summary


def replay_backend(recorded: Path, cfg: ShgmConfig, out_dir: Path, robots: list[str]) -> ServerNode:
    """Run the map server again on the keyframes a run recorded, with ``cfg``'s matching and back end.

    The front ends (perception, odometry, graphs) are not run: their messages come from
    ``recorded/journal.bin`` (``run_slam(..., journal=True)``), in the order the original run sent them,
    so a change of matching, verification or pose graph is measured on identical input in seconds.

    Args:
        recorded: results folder of the original run (holds ``journal.bin``).
        cfg: the configuration (only its matching and back-end stages matter here).
        out_dir: new results folder (fused and odometry trajectories, graphs, matches, pose graph).
        robots: the run's robot names, the reference (shared frame) first.

    Returns:
        The finished server node (its ``map`` answers what was placed and how).

    Raises:
        DataError: ``recorded`` holds no journal, or the journal's robots never all finished.
    """
    source = Path(recorded) / "journal.bin"
    if not source.is_file():
        raise DataError(f"{recorded} holds no journal.bin: record the run with a journal first")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "journal.bin").write_bytes(source.read_bytes())
    node = ServerNode(
        cfg, InProcessTransport(InProcessBus()), out_dir, reference=robots[0], expect=len(robots), journal=True,
        write_every_keyframes=0, stale_after_s=float("inf"),
    )  # fmt: skip
    node.poll()
    if not node.finished:
        raise DataError(f"the journal in {recorded} does not hold every robot's last keyframe ({', '.join(robots)})")
    return node


def _report_degenerate(
    reports: list[RobotReport], fronts: dict[str, RobotFrontend], image_change: dict[str, ImageChange], viz: Viz
) -> None:
    """Add each robot's degenerate-data warnings to its report, the log and the viewer's log panel."""
    for rep in reports:
        front = fronts[rep.name]
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
        if rep.frames_processed and rep.nodes == 0:
            rep.warnings.append(
                "no graph nodes: no object passed extraction, so it cannot be matched (check the labels, "
                "extraction.labels, the depth range and the blob size)"
            )
        if rep.frames_processed:
            still = stillness_warning(*odometry_motion(front.T_odom_cam, front.frame_segment), image_change[rep.name])
            if still is not None:
                rep.warnings.append(still)
                rep.localized = False  # a trajectory known to be invalid is never "fused"
        for text in rep.warnings:
            log.warning("%s: %s", rep.name, text)
            viz.log_text(f"{rep.name}: {text}", "WARN")


def _report_placement(reports: list[RobotReport], fronts: dict[str, RobotFrontend], server: MapServer) -> None:
    """Flag each robot with a segment placed from a single piece of evidence, and say why a segment with
    accepted closures is not placed (too few independent matches): a warning each."""
    for rep in reports:
        for seg in fronts[rep.name].segments:
            rep.provisional |= server.placement(seg.agent).provisional
            if (note := server.placement_note(seg.agent)) is not None:
                rep.warnings.append(note)


def _log_placements(viz: Viz, watch: PlacementWatch, server: MapServer) -> None:
    """Agents that joined the shared frame provisionally, were confirmed or lost their place: log and viewer."""
    for level, text in watch.changes(server):
        (log.warning if level == "WARN" else log.info)("%s", text)
        viz.log_text(text, level)


def _last_healthy_position(front: RobotFrontend, server: MapServer) -> np.ndarray | None:
    """(3,) shared-frame position of the last frame of the segment that just failed, if that is placed."""
    seg = front.segments[-1] if front.stopped else front.segments[-2]
    frames = np.flatnonzero(front.frame_segment == seg.index)
    if not len(frames) or server.T_shared_kf(seg.agent) is None:
        return None
    return (server.T_shared_odom(seg.agent) @ front.T_odom_cam[frames[-1]])[:3, 3]


def _placed_segments(front: RobotFrontend, server: MapServer) -> list[tuple[int, np.ndarray]]:
    """(segment index, (K, 4, 4) T_shared_kf) of every segment of ``front`` placed in the shared frame."""
    out = []
    for seg in front.segments:
        T_shared_kf = server.T_shared_kf(seg.agent) if seg.num_keyframes else None
        if T_shared_kf is not None:
            out.append((seg.index, T_shared_kf))
    return out


def _fused(front: RobotFrontend, server: MapServer) -> np.ndarray | None:
    """(N, 4, 4) fused poses: the frames of every placed segment in the shared frame, NaN elsewhere;
    None when no segment is placed."""
    segs = [s for s in front.segments if s.num_keyframes]
    return fuse_segments(
        front.T_odom_cam, front.frame_segment,
        {s.index: np.asarray(s.kf_frames, dtype=np.int64) for s in segs},
        {s.index: np.stack(s.kf_poses) for s in segs},
        dict(_placed_segments(front, server)),
    )  # fmt: skip


def _evaluate(
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
        fused = _fused(front, server)
        placed = {k for k, _ in _placed_segments(front, server)}
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
        if rep.odometry == OdometryKind.KISS_ICP.value:
            rep.image_steps = front.image_steps
            rep.image_windows = front.image_windows
        rep.depth_noise_rel, rep.voxel_size_m = front.cfg.odometry.depth_noise_rel, front.cfg.odometry.voxel_size_m
        if front.ground_scale_on:
            rep.depth_scale_share = len(front.depth_scales) / max(processed[r], 1)
            rep.depth_scale = float(np.median(front.depth_scales)) if front.depth_scales else None
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


def _log_frame(
    viz: Viz, view: RunView, server: MapServer, front: RobotFrontend, res: FrameResult, records
) -> None:
    r, agent = res.robot, res.agent or res.robot
    if not viz.enabled:  # nothing shown: skip the poses, clouds, trajectories and graphs only the viewer needs
        _log_matches(viz, server, records)
        return
    viz.set_time(r, res.frame.index, res.frame.timestamp_s)
    if not np.isfinite(res.T_odom_cam).all():  # between a divergence and the next measured frame
        _log_matches(viz, server, records)
        return
    T_shared_odom = server.T_shared_odom(agent)
    T_view = res.T_odom_cam if T_shared_odom is None else T_shared_odom @ res.T_odom_cam
    # the heavy parts (depth image, point cloud) only at keyframes: keeps recordings ~100 KB per frame
    key = res.message is not None
    pts = labels = None
    if key:  # thinned as the viewer would before it is moved into the shared frame
        step = thinning_stride(len(res.points_cam), viz.max_cloud_points)
        pts = se3.transform_points(T_view, res.points_cam[::step])
        labels = None if res.point_labels is None else res.point_labels[::step]
    viz.log_frame(r, T_view, res.frame.image_rgb, res.depth_m if key else None, res.label_ids, pts, labels)
    viz.log_timings(r, res.timings_ms)
    if res.message is not None:
        view.keyframe(server, front, res)  # only the trajectory stretches and graph parts that changed
    _log_matches(viz, server, records)


def _log_matches(viz: Viz, server: MapServer, records) -> None:
    for m in records:
        if not m.success:
            continue
        if server.is_placed(m.robot_a) and server.is_placed(m.robot_b):
            pa = se3.transform_points(server.T_shared_odom(m.robot_a), m.inlier_positions_a)
            pb = se3.transform_points(server.T_shared_odom(m.robot_b), m.inlier_positions_b)
            viz.log_matches(m.robot_a, m.robot_b, pa, pb, m.accepted, len(m.inliers))
        level = "INFO" if m.accepted or m.duplicate else "WARN"
        verdict = "accepted" if m.accepted else "already known" if m.duplicate else "rejected"
        viz.log_text(f"{m.robot_a}<->{m.robot_b} ({m.query}): {len(m.inliers)} inliers, {verdict}: {m.reason}", level)
