"""The library function behind ``shgm-slam run``: robots in, fused trajectories and a summary out.

``run_slam`` interleaves the robots in time, streams every stage to the viewer, writes the results
folder as it goes (and once more at the end, also after Ctrl-C), and evaluates against ground truth
when the sequences have it. What the viewer is sent is in ``run_view``; the reports, the summary and the
evaluation in ``run_report``.
"""

from __future__ import annotations

import contextlib
import logging
import re
import time
from collections.abc import Callable
from pathlib import Path

from shgm_slam.backend.keys import MAX_AGENTS, segments_per_robot
from shgm_slam.config import ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.data.base import sequence_root
from shgm_slam.data.interleave import interleave
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.interrupts import stops_deferred
from shgm_slam.io.export import ResultsWriter, check_outside_sequence
from shgm_slam.odometry.stillness import ImageChange
from shgm_slam.robot.build import make_frontend
from shgm_slam.robot.frontend import FrameResult, RobotFrontend
from shgm_slam.robot.node import RobotNode
from shgm_slam.robot.remote import FrontendLostError, ParallelFrontends
from shgm_slam.run_report import (
    FrameStats,
    RobotReport,
    RunSummary,
    StageTimings,
    evaluate,
    report_degenerate,
    report_placement,
)
from shgm_slam.run_view import RunView, last_healthy_position, log_frame, log_matches
from shgm_slam.scene_scale import effective_fields
from shgm_slam.server.map_server import MapServer
from shgm_slam.server.node import ServerNode
from shgm_slam.server.placement import PlacementWatch
from shgm_slam.server.records import pair_matches
from shgm_slam.shared_frame import SharedTruth
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.keys import validate_robot_name
from shgm_slam.types import Sequence
from shgm_slam.viz.rerun_logger import NullLogger, Viz

__all__ = [  # the pipeline's API
    "FleetRun",
    "FrameFn",
    "ProgressFn",
    "check_fleet",
    "check_out_outside_sequences",
    "effective_config",
    "fleet_backend",
    "make_frontend",
    "open_robots",
    "parse_robot_arg",
    "prepare_frontends",
    "replay_backend",
    "run_slam",
]

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


def check_out_outside_sequences(out: Path, robots: dict[str, Sequence]) -> None:
    """Refuse a results folder that is a robot's sequence folder or lies inside one (frames held in memory have
    no folder).

    Raises:
        ConfigError: ``out`` is (inside) the folder of a robot's sequence: the results would be written among the
            sequence's files (a ``graph_*.json`` or ``run.rrd`` in a sequence others read).
    """
    for name, sequence in robots.items():
        if (root := sequence_root(sequence)) is not None:
            check_outside_sequence(out, root, f"of robot {name!r} ")


def fleet_backend(cfg: ShgmConfig, fronts: dict[str, RobotFrontend], predicted: list[str] | None = None) -> ShgmConfig:
    """``cfg`` with the back end's depth-dependent values (still None) set from where the fleet's depth comes
    from (``BackendConfig.for_depth``: predicted when any robot's depth model predicts it). ``predicted``: the
    robots whose depth is predicted, when robots without a front end yet belong to the fleet (None: ``fronts``')."""
    if predicted is None:
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


ProgressFn = Callable[[int, int], None]
FrameFn = Callable[[FrameStats], None]


def prepare_frontends(robots: dict[str, Sequence], cfg: ShgmConfig) -> dict[str, RobotFrontend]:
    """Every robot's front end (``make_frontend``), after checking that ``cfg.robots`` names only these robots.

    This is everything that can refuse a run (config, models, the first frames); the CLI calls it before it
    creates the results folder, so a refused run leaves nothing behind that the next one would have to clear.
    Each robot may start ``segments_per_robot`` trajectory segments: together they fit the pose graph.

    Raises:
        ConfigError, DataError, ModelError: what ``make_frontend`` raises; overrides for unknown robots; more
            robots than the pose graph holds (``MAX_AGENTS``).
    """
    share = check_fleet(list(robots), cfg)
    return {r: make_frontend(r, seq, cfg, max_segments=share) for r, seq in robots.items()}


def check_fleet(names: list[str], cfg: ShgmConfig, unknown_fix: str = "fix the names under 'robots:'") -> int:
    """Refuse a fleet the pose graph cannot hold or a config with settings for robots not in it (``unknown_fix``:
    what the message tells the user to do); returns each robot's share of the pose graph's agents
    (``segments_per_robot``: the trajectory segments it may start).

    Raises:
        ConfigError: more robots than ``MAX_AGENTS``; two names that differ only in case (their files, such as
            ``<robot>_fused_tum.txt``, are one file on a case-insensitive file system: macOS, Windows);
            ``cfg.robots`` names a robot not in ``names``.
    """
    seen: dict[str, str] = {}
    for name in names:
        other = seen.setdefault(name.casefold(), name)
        if other != name:
            raise ConfigError(f"robots {other!r} and {name!r} differ only in case: their result files (such as "
                              f"{name}_fused_tum.txt) would be one file on a case-insensitive file system (macOS, "
                              "Windows); give them names that differ in more than case")  # fmt: skip
    if len(names) > MAX_AGENTS:
        raise ConfigError(
            f"{len(names)} robots: the pose graph holds at most {MAX_AGENTS} agents (robots and their trajectory "
            f"segments after odometry failures); run at most {MAX_AGENTS} robots"
        )
    unknown = sorted(set(cfg.robots) - set(names))
    if unknown:
        raise ConfigError(
            f"the config has settings for robot(s) {', '.join(unknown)} that are not in this run "
            f"({', '.join(names)}); {unknown_fix}"
        )
    # each robot's share of the pose graph's agents: a robot whose odometry keeps failing stops at its share
    # (a logged skip of its later frames) instead of ending the whole run when the agents run out
    return segments_per_robot(len(names))


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
        fleet: FleetRun | None = None
        try:
            fleet = FleetRun(robots, cfg, out_dir, fronts, viz=viz, gt_shared_frame=gt_shared_frame,
                             write_every_keyframes=write_every_keyframes, journal=journal)  # fmt: skip
            interrupted = False
            try:
                for robot, index in schedule:
                    with stops_deferred():  # a stop lands between frames, never inside the server's or a robot's step
                        fleet.step(robot, index, on_frame)
                        if progress:
                            progress(fleet.done, len(schedule))
            except KeyboardInterrupt:
                interrupted = True
            return fleet.finish(interrupted=interrupted)
        except Exception as exc:  # re-raised: what was written so far must not pass for the run's results
            if Path(out_dir).is_dir():
                ResultsWriter(out_dir).mark_failed(exc)
            raise
        except KeyboardInterrupt:  # a stop while the run started, or while the results were written (a second one,
            # or the first after the final matching): what is there is a checkpoint, not the results
            when = "while the run was starting" if fleet is None else "while its results were being written"
            if Path(out_dir).is_dir():
                with contextlib.suppress(DataError):
                    ResultsWriter(out_dir).mark_incomplete(f"stopped {when}")
                log.warning("stopped %s: %s holds a checkpoint, marked by incomplete.txt", when, out_dir)
            raise


class FleetRun:
    """One run of the whole system, frame by frame: the robots' nodes and the map server on the in-process bus,
    the viewer and the results folder. ``run_slam`` steps it through a recorded schedule; ``live.LiveRun`` through
    frames as they arrive (the robots' sequences then grow between steps, and a robot without a front end yet
    joins later: ``add_robot``).

    Args:
        robots: robot name -> sequence, every robot of the fleet (order matters: the first robot defines the shared
            frame; it must have a front end from the start).
        cfg: the fleet configuration.
        out_dir: results folder (written into at once: ground truth, ``config.yaml``).
        fronts: the front ends of the robots that run from the start (``prepare_frontends``, or
            ``ParallelFrontends``' mirrors).
        viz: viewer (``NullLogger`` when None).
        gt_shared_frame, write_every_keyframes, journal: as for ``run_slam``.
        predicted: the robots whose depth is predicted (``fleet_backend``; None: those of ``fronts``).
    """

    def __init__(
        self,
        robots: dict[str, Sequence],
        cfg: ShgmConfig,
        out_dir: Path,
        fronts: dict[str, RobotFrontend],
        *,
        viz: Viz | None = None,
        gt_shared_frame: bool = True,
        write_every_keyframes: int = 25,
        journal: bool = False,
        predicted: list[str] | None = None,
    ) -> None:
        names = list(robots)
        fronts = dict(fronts)
        self.robots, self.fronts, self.out_dir, self.gt_shared_frame = robots, fronts, Path(out_dir), gt_shared_frame
        self.viz = viz = viz or NullLogger()
        self.writer = ResultsWriter(out_dir)
        self.writer.write_ground_truth(self.joined, gt_shared_frame)  # <robot>_gt_tum.txt, for evo and `shgm-slam eval`
        self._gt_written = {r: len(seq) for r, seq in self.joined.items()}  # frames each ground-truth file holds
        self.cfg = cfg = fleet_backend(cfg, fronts, predicted)
        # the same nodes as the distributed deployment, on the in-process bus (every message is encoded)
        bus = InProcessBus()
        self.server_node = ServerNode(
            cfg, InProcessTransport(bus), out_dir, reference=names[0], expect=len(names), journal=journal,
            write_every_keyframes=write_every_keyframes, stale_after_s=float("inf"),  # one process: never silent
            order_keyframes=False,  # the frames come in the server's keyframe order already (``interleave``)
        )  # fmt: skip
        self._bus = bus
        self.nodes = {r: RobotNode(f, InProcessTransport(bus)) for r, f in fronts.items()}
        for node in self.nodes.values():
            node.hello()
        self.server_node.poll()
        self.server = self.server_node.map
        viz.setup({r: seq.intrinsics for r, seq in robots.items()})
        self.view = RunView(viz, SharedTruth(self.robots, gt_shared_frame))
        self._write_config()
        self.timings = StageTimings()
        self.skipped: list[str] = []
        self.lost: dict[str, str] = {}  # robot -> why its front end was lost (``FrontendLostError``)
        self.processed = dict.fromkeys(names, 0)
        self.reached = dict.fromkeys(names, 0)  # frames whose turn came (the rest: not reached, the run interrupted)
        self.image_change = {r: ImageChange() for r in names}
        self.compute_ms = 0.0
        self.t_start = time.perf_counter()
        self.done = 0  # frames whose turn came, over all robots
        self.kf_total = 0
        self.watch = PlacementWatch()
        self.finished = False

    @property
    def joined(self) -> dict[str, Sequence]:
        """The sequences of the robots that run (those with a front end), in the fleet's order."""
        return {r: seq for r, seq in self.robots.items() if r in self.fronts}

    def add_robot(self, robot: str, front: RobotFrontend, sequence: Sequence | None = None) -> None:
        """A robot that had no front end yet joins the running system (its node says hello to the map server;
        ``config.yaml`` gets its settings): one of the fleet's robots, or, with its ``sequence``, a robot the
        fleet did not have (it joins the fleet after the robots it had; the viewer gets its camera).

        Raises:
            ConfigError: ``robot`` runs already, is not in the fleet and no ``sequence`` is given, or is in the
                fleet and a ``sequence`` is given.
        """
        if robot in self.fronts or (robot in self.robots) == (sequence is not None):
            raise ConfigError(f"robot {robot!r} cannot join: it runs already, or it is not in this run and has "
                              "no sequence (or is in it and was given another)")  # fmt: skip
        if sequence is not None:
            self.robots = {**self.robots, robot: sequence}
            self.view.truth = SharedTruth(self.robots, self.gt_shared_frame)
            self.processed[robot] = self.reached[robot] = 0
            self.image_change[robot] = ImageChange()
            self.viz.setup({robot: sequence.intrinsics})
        fronts = {**self.fronts, robot: front}
        self.fronts = {r: fronts[r] for r in self.robots if r in fronts}  # in the fleet's order (reports, files)
        self.nodes[robot] = node = RobotNode(front, InProcessTransport(self._bus))
        node.hello()
        self.server_node.poll()
        self._write_config()

    def _write_config(self) -> None:
        """``config.yaml``: the fleet configuration with every running robot's derived values."""
        fronts = {r: f.cfg for r, f in self.fronts.items()}
        self.writer.write_text("config.yaml", effective_config(self.cfg, fronts).to_yaml())

    def step(self, robot: str, index: int, on_frame: FrameFn | None = None) -> FrameResult | None:
        """Run frame ``index`` of ``robot`` through its node and the map server, log it and count it.

        Returns:
            The front end's result, or None when the frame was skipped (unreadable: logged and counted).
        """
        fronts, server, server_node, viz = self.fronts, self.server, self.server_node, self.viz
        self.done += 1
        self.reached[robot] += 1
        t_step, cpu_step = time.perf_counter(), time.process_time()
        try:
            res = self.nodes[robot].step(index)
        except DataError as exc:
            self.skipped.append(f"{robot} frame {index}: {exc}")
            if isinstance(exc, FrontendLostError) and not exc.repeat:
                self.lost[robot] = f"at frame {index}: {exc}"
            if not getattr(exc, "repeat", False):  # a lost worker costs every later frame: said once
                viz.log_text(f"{robot}: skipped frame {index}: {exc}", "WARN")
            return None
        self.processed[robot] += 1
        if not fronts[robot].stopped:  # a stopped robot's dropped frames say nothing about its odometry
            self.image_change[robot].add(res.frame.image_rgb)
        if res.failure is not None:
            then = "its later frames are dropped" if fronts[robot].stopped else f"new trajectory segment {res.agent}"
            viz.log_odometry_failure(
                robot, f"{robot}: odometry diverged, {res.failure.describe()}; {then}",
                last_healthy_position(fronts[robot], server),
            )  # fmt: skip
        t0 = time.perf_counter()
        n_match, n_backend = len(server.timings_ms["match"]), len(server.timings_ms["backend"])
        n_write, n_corr = len(server_node.timings_ms["write"]), len(server_node.timings_ms["correction"])
        records = server_node.poll()
        res.timings_ms["server"] = (time.perf_counter() - t0) * 1e3
        self.nodes[robot].poll()
        self.timings.add(res.timings_ms)
        step_compute = sum(v for k, v in res.timings_ms.items() if k != "load" and not k.startswith("perc"))
        self.compute_ms += step_compute
        log_frame(viz, self.view, server, fronts[robot], res, records)
        if records:
            _log_placements(viz, self.watch, server)
        self.kf_total += res.message is not None
        if on_frame is not None:
            match_ms = sum(server.timings_ms["match"][n_match:])
            backend_ms = sum(server.timings_ms["backend"][n_backend:])
            on_frame(FrameStats(
                robot, index, res.message is not None, step_compute - res.timings_ms["server"],
                sum(res.timings_ms.values()) - step_compute, match_ms, backend_ms, res.timings_ms["server"],
                (time.perf_counter() - t_step) * 1e3, tuple(records), (time.process_time() - cpu_step) * 1e3,
                sum(server_node.timings_ms["write"][n_write:]), sum(server_node.timings_ms["correction"][n_corr:]),
            ))  # fmt: skip
        return res

    def finish(self, *, interrupted: bool = False) -> RunSummary:
        """Every robot done: the final matching (none when ``interrupted``), the results folder, the evaluation
        against ground truth where the sequences have it, and the summary (also in ``metrics.json``)."""
        fronts, server, server_node, viz = self.fronts, self.server, self.server_node, self.viz
        self.finished = True
        if interrupted:  # no final matching: write what there is
            server_node.expect = None
        for node in self.nodes.values():
            node.done()
        records = []
        try:
            with stops_deferred():  # every robot done: the server matches whole graphs and writes the results
                records = server_node.poll()
        except KeyboardInterrupt:  # stopped during the final matching: it ended, and the run says it was stopped
            interrupted = True
        if not server_node.finished:
            server_node.finish(match=not interrupted)
        log_matches(viz, server, records)
        _log_placements(viz, self.watch, server)
        if viz.enabled:
            self.view.finish(server, fronts.values())  # the viewer ends on the final estimate, not the last keyframe's
        for node in self.nodes.values():
            node.poll()
        joined = self.joined  # (robots that never joined: no report)
        if {r: len(seq) for r, seq in joined.items()} != self._gt_written:  # frames came one by one
            self.writer.write_ground_truth(joined, self.gt_shared_frame)
        reports, ate_joint_m = evaluate(fronts, server, joined, self.processed, self.gt_shared_frame, self.reached)
        report_placement(reports, fronts, server)
        report_degenerate(reports, fronts, self.image_change)
        for rep in reports:
            rep.front_end_lost = self.lost.get(rep.name)
        _say_warnings(reports, viz)
        accepted = sum(m.accepted for m in server.matches)
        summary = RunSummary(
            out_dir=self.out_dir,
            robots=reports,
            matches_tried=len(server.matches),
            closures_accepted=accepted,
            closures_rejected=sum(m.success and not m.accepted and not m.duplicate for m in server.matches),
            pairs=pair_matches(server.matches),
            timings_ms={
                **self.timings.means(),
                "match": server.mean_match_ms(),
            },
            per_keyframe_ms=self.compute_ms / max(self.kf_total, 1),
            wall_s=time.perf_counter() - self.t_start,
            interrupted=interrupted,
            skipped_reasons=self.skipped,
            last_looks=server.last_looks(),
            ate_joint_m=ate_joint_m,
        )
        for line in filter(None, (p.never_met() for p in summary.pairs)):
            viz.log_text(line, "WARN")  # the viewer's log panel says why two robots never met
        self.writer.write_json("metrics.json", summary.to_json_dict())
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


def _log_placements(viz: Viz, watch: PlacementWatch, server: MapServer) -> None:
    """Agents that joined the shared frame provisionally, were confirmed or lost their place: log and viewer."""
    for level, text in watch.changes(server):
        (log.warning if level == "WARN" else log.info)("%s", text)
        viz.log_text(text, level)


def _say_warnings(reports: list[RobotReport], viz: Viz) -> None:
    """Each robot's warnings (``run_report.report_placement`` / ``report_degenerate``) in the log and the viewer's
    log panel."""
    for rep in reports:
        for text in rep.warnings:
            log.warning("%s: %s", rep.name, text)
            viz.log_text(f"{rep.name}: {text}", "WARN")
