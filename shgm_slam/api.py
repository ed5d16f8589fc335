"""shgm_slam from Python: the command line's jobs as functions, on sequence folders or on frames you hold.

``run`` is ``shgm-slam run`` (robots in, a results folder and its ``RunSummary`` out), ``match`` is
``shgm-slam match`` (two semantic graphs, gravity-aligned when both lie flat), ``read_fused`` reads a robot's
fused trajectory back from a results folder and ``evaluate`` is ``shgm-slam eval``. Robots are any
``types.Sequence``: a folder opened with ``open_sequence("path[:start-end]")``, or frames in memory
(``data.memory.ArraySequence``). Errors are ``errors.ShgmError`` subclasses with a message that says what to
fix (``ConfigError``, ``DataError``, ``ModelError``, ...); nothing here prints or exits.

The command line calls these same functions, so a script gets the results ``shgm-slam`` would give.
"""

from __future__ import annotations

import inspect
import operator
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from shgm_slam.config import Dof, ShgmConfig, config_from_mapping, load_config
from shgm_slam.errors import ConfigError, DataError, GraphError
from shgm_slam.types import GraphArrays, Sequence

if TYPE_CHECKING:  # the viewer, the pose graph and the models load only when a run needs them
    from shgm_slam.evaluation import EvaluationResult
    from shgm_slam.matching.result import MatchResult
    from shgm_slam.run_report import RunSummary
    from shgm_slam.viz.rerun_logger import RerunMode


@dataclass(frozen=True)
class GraphMatch:
    """What ``match`` found, and how it matched.

    Attributes:
        result: the matcher's result (``T_a_b`` maps B's frame into A's; None when not accepted, with ``reason``).
        gravity_aligned: matched as yaw + translation about ``up_axis`` (4-DoF), else with any rotation (6-DoF).
        up_axis: (3,) the vertical the match (and its chance model) used, in both graphs' frames.
        dof_note: why that freedom was chosen (``matching.gravity.choose_dof``).
        decisive: accepted, and alone as far beyond chance as the independent matches the running system needs
            to place a robot (``backend.min_closures_to_anchor``).
        nodes: the two graphs' node counts (A, B).
    """

    result: MatchResult
    gravity_aligned: bool
    up_axis: tuple[float, float, float]
    dof_note: str
    decisive: bool
    nodes: tuple[int, int]


@dataclass(frozen=True)
class FusedTrajectory:
    """A robot's trajectory in the shared frame (the first robot's first camera frame), as ``run`` wrote it.

    Attributes:
        robot: the robot's name.
        timestamps_s: (N,) seconds of its placed frames.
        T_shared_cam: (N, 4, 4) camera -> shared frame poses (KITTI camera axes: x right, y down, z forward).
        provisional: its place rests on one piece of evidence that no independent match confirmed yet.
    """

    robot: str
    timestamps_s: np.ndarray
    T_shared_cam: np.ndarray
    provisional: bool


def config_of(config: ShgmConfig | Mapping | Path | str | None) -> ShgmConfig:
    """``config`` as an ``ShgmConfig``: itself, validated from a mapping of stages (what the YAML file holds, e.g.
    ``{"matching": {"top_k": 3}}``), loaded from a YAML file, or the defaults (None).

    Raises:
        ConfigError: a file that is missing, a file or mapping that holds unknown or invalid fields; another type.
    """
    if isinstance(config, ShgmConfig):
        return config
    if config is None or isinstance(config, str | Path):
        return load_config(config)
    if isinstance(config, Mapping):
        return config_from_mapping(dict(config), "config mapping")  # as a YAML file's are refused (near misses)
    raise ConfigError(f"config must be an ShgmConfig, a mapping of stages, a YAML file's path or None, not "
                      f"{type(config).__name__}")  # fmt: skip


def checked_robots(robots: Mapping[str, Sequence]) -> dict[str, Sequence]:
    """``robots`` as a dict, checked: at least one, valid names, each a non-empty ``types.Sequence``.

    Raises:
        ConfigError: no robots, or an invalid name.
        DataError: a value that is not a sequence, or has no frames.
    """
    from shgm_slam.transport.keys import validate_robot_name

    if not isinstance(robots, Mapping):
        raise ConfigError(f"robots must be a mapping {{name: sequence}}, not {type(robots).__name__}; e.g. "
                          "{'car1': open_sequence('data/car1')} (dict(pairs) of (name, sequence) pairs)")  # fmt: skip
    if not robots:
        raise ConfigError("no robots given: pass {name: sequence}, e.g. {'car1': open_sequence('data/car1')}")
    for name, sequence in robots.items():
        validate_robot_name(name)
        if not isinstance(sequence, Sequence):
            raise DataError(
                f"robot {name!r}: {type(sequence).__name__} is not a sequence; open a folder with open_sequence() or "
                "hold frames in an ArraySequence"
            )
        if len(sequence) == 0:
            raise DataError(f"robot {name!r}: sequence {sequence.name} has zero frames")
    return dict(robots)


def viewer_mode(viewer: RerunMode | str | None, viewer_url: str | None = None) -> RerunMode:
    """``viewer`` as a ``RerunMode`` (None: ``OFF``); for ``CONNECT``, ``viewer_url`` (default: this machine's
    viewer) checked before any work.

    Raises:
        ConfigError: an unknown mode, or a malformed URL.
    """
    from shgm_slam.viz.rerun_logger import DEFAULT_CONNECT_URL, RerunMode, viewer_address

    try:
        mode = RerunMode.OFF if viewer is None else RerunMode(viewer)
    except ValueError:
        raise ConfigError(f"viewer {viewer!r}: choose one of {', '.join(m.value for m in RerunMode)}") from None
    if mode is RerunMode.CONNECT:
        viewer_address(viewer_url or DEFAULT_CONNECT_URL)
    return mode


def worker_count(jobs: object) -> int:
    """``jobs`` as an int (a numpy integer too), refused (ConfigError) unless a whole number of at least 1."""
    try:
        count = operator.index(jobs)  # type: ignore[arg-type]
    except TypeError:
        count = 0
    if isinstance(jobs, bool) or count < 1:
        raise ConfigError(f"jobs {jobs!r}: give a whole number of worker processes, at least 1")
    return count


def check_progress(progress: object) -> None:
    """Refuse (ConfigError) a ``progress`` that is not None nor callable with (frames done, frames total): it was
    first called after the first frame, and the run ended there with a TypeError and an incomplete results folder.
    """
    if progress is None:
        return
    if not callable(progress):
        raise ConfigError(f"progress must be a function of (frames done, frames total), not {type(progress).__name__}")
    try:
        signature = inspect.signature(progress)
    except (TypeError, ValueError):  # a builtin without a signature: taken as it is
        return
    try:
        signature.bind(0, 0)
    except TypeError as exc:
        raise ConfigError(f"progress {getattr(progress, '__name__', progress)!r} cannot be called with (frames done, "
                          f"frames total): {exc}; give a function of two arguments") from None  # fmt: skip


def run(
    robots: Mapping[str, Sequence],
    out: Path | str | None = None,
    *,
    config: ShgmConfig | Mapping | Path | str | None = None,
    viewer: RerunMode | None = None,
    viewer_url: str | None = None,
    gt_shared_frame: bool = True,
    overwrite: bool = False,
    jobs: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> RunSummary:
    """Run the multi-robot system (``shgm-slam run``) and write the results folder.

    Everything that can refuse the run (names, configuration, models, the first frames, an ``out`` inside a
    robot's sequence folder) is checked before ``out`` is created; ``out`` is then locked for the run (a second
    run on it is refused) and refused when it holds an earlier run's results unless ``overwrite``.

    Args:
        robots: robot name -> sequence, in order (the first robot's first camera frame is the shared frame).
        out: results folder (created); None: ``results/<YYYYmmdd_HHMMSS>`` and ``results/latest``.
        config: an ``ShgmConfig``, a mapping of stages as a YAML file holds them, a YAML file, or None for the
            defaults.
        viewer: where the Rerun recording goes (``viz.RerunMode``): None or ``OFF`` nowhere, ``SAVE``
            ``out/run.rrd``, ``SPAWN`` a new viewer, ``CONNECT`` a running one at ``viewer_url`` (default: on
            this machine).
        viewer_url: the viewer's gRPC URL for ``"connect"``.
        gt_shared_frame: the sequences' ground truths share one world frame (frame ranges of one sequence, the
            simulator's robots): fused ATE is then measured in the shared frame.
        overwrite: reuse an ``out`` that holds an earlier run's results (they are removed first).
        jobs: worker processes for the robots' front ends (1: all in this process; a script that uses more needs
            the ``if __name__ == "__main__":`` guard: workers are spawned).
        progress: called with (frames done, frames total) after every frame, or None.

    Returns:
        The run's ``run_report.RunSummary`` (per-robot reports, matches, timings, ``out_dir``).

    Raises:
        ConfigError, DataError, ModelError: what refuses the run (the message says what to fix).
        KeyboardInterrupt: stopped; ``out`` then holds every result up to the stop (``summary.interrupted`` is
            set instead when the stop came between frames).
    """
    from shgm_slam.io.export import claimed_results_dir
    from shgm_slam.runner import check_out_outside_sequences, prepare_frontends, run_slam
    from shgm_slam.viz.rerun_logger import make_viz

    robots = checked_robots(robots)
    cfg = config_of(config)
    jobs = worker_count(jobs)
    check_progress(progress)
    mode = viewer_mode(viewer, viewer_url)
    if out is not None:
        check_out_outside_sequences(Path(out), robots)
    fronts = prepare_frontends(robots, cfg)
    with claimed_results_dir(None if out is None else Path(out), overwrite=overwrite) as out_dir:
        viz = make_viz(mode, robots=list(robots), save_path=out_dir / "run.rrd", connect_url=viewer_url,
                       max_cloud_points=8000)  # fmt: skip
        return run_slam(robots, cfg, out_dir, viz=viz, progress=progress, gt_shared_frame=gt_shared_frame,
                        fronts=fronts, jobs=jobs)  # fmt: skip


def dof_of(dof: Dof | str | int) -> Dof:
    """``dof`` as a ``Dof``: itself, its value ("auto", "4", "6") or the number 4 or 6.

    Raises:
        ConfigError: anything else (Python's ValueError before).
    """
    if isinstance(dof, Dof):
        return dof
    try:
        return Dof(str(dof).strip().lower())
    except ValueError:
        raise ConfigError(f"dof {dof!r}: choose Dof.AUTO ('auto'), Dof.FOUR (4: yaw about the vertical) or Dof.SIX "
                          "(6: any rotation)") from None  # fmt: skip


def graph_of(graph: object, name: str, connectivity_m: float) -> GraphArrays:
    """``graph`` (``GraphArrays`` or a graph file's path) as checked ``GraphArrays`` (``matching.matcher.check_graph``).

    Raises:
        GraphError: another type (a decoded document: ``io.graph_json.graph_from_dict`` reads it), an unreadable
            file, arrays that hold no graph.
    """
    from shgm_slam.io.graph_json import FORMAT_TAG, read_graph
    from shgm_slam.matching.matcher import check_graph

    if isinstance(graph, str | os.PathLike):
        return read_graph(graph, connectivity_m=connectivity_m)
    if not isinstance(graph, GraphArrays):
        raise GraphError(f"graph {name}: give GraphArrays or a {FORMAT_TAG} file's path, not {type(graph).__name__} "
                         "(a decoded document: shgm_slam.io.graph_json.graph_from_dict(doc))")  # fmt: skip
    check_graph(graph, name)
    return graph


def match(
    graph_a: GraphArrays | Path | str,
    graph_b: GraphArrays | Path | str,
    *,
    config: ShgmConfig | Mapping | Path | str | None = None,
    dof: Dof | str | int = Dof.AUTO,
) -> GraphMatch:
    """Localize graph B in graph A (``shgm-slam match``): ``T_a_b`` maps B's coordinates into A's frame.

    Args:
        graph_a, graph_b: ``GraphArrays`` or ``shgm-graph/1`` JSON files (``io.graph_json``).
        config: an ``ShgmConfig`` (its descriptor, matching and graph stages), a mapping of stages, a YAML file,
            or None.
        dof: ``Dof.AUTO`` matches gravity-aligned about the vertical both graphs lie flat along (maps, ground
            robots), else as the configuration says; ``Dof.FOUR`` / ``Dof.SIX`` (or 4 / 6) force it.

    Raises:
        GraphError: an unreadable or malformed graph file, ``GraphArrays`` that do not hold a graph
            (``matching.matcher.check_graph``, ``graph_of``), another type. ConfigError: a bad configuration or
            ``dof``.
    """
    from shgm_slam.matching import match_graphs
    from shgm_slam.matching.gravity import choose_dof

    cfg = config_of(config)
    freedom = dof_of(dof)
    a = graph_of(graph_a, "A", cfg.graph.connectivity_m)  # (checked before the vertical is read from the positions)
    b = graph_of(graph_b, "B", cfg.graph.connectivity_m)
    matching_cfg, dof_note = choose_dof(freedom, a.positions_xyz, b.positions_xyz, cfg.matching)
    result = match_graphs(a, b, cfg.descriptor, matching_cfg)
    return GraphMatch(result, bool(matching_cfg.gravity_aligned), tuple(matching_cfg.up_axis), dof_note,
                      result.is_decisive(cfg.backend.min_closures_to_anchor), (len(a), len(b)))  # fmt: skip


def read_fused(results_dir: Path | str, robot: str) -> FusedTrajectory | None:
    """The fused trajectory ``run`` wrote for ``robot`` (``<robot>_fused_tum.txt``); None when it was not placed.

    Raises:
        DataError: ``results_dir`` is not a results folder or holds no finished run's results (its run ended with
            an error, was killed or is still running: a checkpoint, ``evaluation.check_results_finished``),
            ``robot`` was not in its run, or the file was edited after the run (its row count is not the one the
            run recorded).
    """
    from shgm_slam.evaluation import check_fused_rows, check_results_finished, is_provisional, run_robot_order
    from shgm_slam.io.trajectories import read_tum

    root = results_path(results_dir)
    if root.is_file():
        raise DataError(f"results folder {root} is a file, not a folder; point at the folder run() wrote")
    if not root.is_dir():
        raise DataError(f"results folder {root} does not exist; point at the folder run() wrote")
    check_results_finished(root)
    names = run_robot_order(root)
    if robot not in names:
        raise DataError(f"{root} holds no robot {robot!r}; its run had {', '.join(names)}")
    path = root / f"{robot}_fused_tum.txt"
    if not path.is_file():
        check_fused_rows(root, robot, 0)  # the run wrote one that is gone: an error, not "not placed"
        return None
    times, poses = read_tum(path)
    check_fused_rows(root, robot, len(times))
    return FusedTrajectory(robot, times, poses, is_provisional(path))


def evaluate(
    results_dir: Path | str, sequences: Mapping[str, Sequence] | None = None, *, gt_shared_frame: bool = True
) -> EvaluationResult:
    """Fused ATE of every robot of a results folder against ground truth (``shgm-slam eval``): in the shared
    frame, per robot aligned, and all robots under one joint fit (``evaluation.evaluate_results``).

    Args:
        results_dir: the folder ``run`` wrote.
        sequences: robot -> the sequence it ran on (or its ``path[:start-end]``, opened with ``open_sequence``),
            for its ground truth; None: the ``<robot>_gt_tum.txt`` files the run wrote.
        gt_shared_frame: the sequences' ground truths share one world frame.

    Raises:
        DataError: not a finished run's results folder; ``sequences`` that are no mapping of sequences, or whose
            ground truth differs from what the run wrote (``evaluation.evaluate_results``).
    """
    from shgm_slam.evaluation import evaluate_results

    return evaluate_results(results_path(results_dir), ground_truth_sequences(sequences),
                            gt_shared_frame=gt_shared_frame)  # fmt: skip


def results_path(results_dir: object) -> Path:
    """``results_dir`` as a Path; DataError for what is no path (``Path(None)``'s TypeError before)."""
    if not isinstance(results_dir, str | os.PathLike):
        raise DataError(f"results folder {results_dir!r} is no path; give the folder run() wrote (summary.out_dir)")
    return Path(results_dir)


def ground_truth_sequences(sequences: Mapping[str, Sequence | Path | str] | None) -> dict[str, Sequence] | None:
    """``evaluate``'s ``sequences`` as a dict of sequences: paths (``path[:start-end]``) opened, the rest checked.
    A path given as a string was taken for a sequence of as many frames as it has characters ("its sequence has 29
    frames but the run had 60"), a ``Path`` or a list ended in Python's TypeError or ValueError.

    Raises:
        DataError: no mapping (nor pairs), a value that is neither a sequence nor a path, a path that opens no sequence
            (a file, such as the sequence's poses.txt, given for its folder; the robot named).
    """
    from shgm_slam.data.base import open_sequence

    if sequences is None:
        return None
    try:
        pairs = dict(sequences)  # (a list of (robot, sequence) pairs too)
    except (TypeError, ValueError):
        raise DataError(f"sequences must be a mapping {{robot: sequence or path}}, not {type(sequences).__name__}; "
                        "e.g. {'car1': open_sequence('data/car1')}") from None  # fmt: skip
    opened: dict[str, Sequence] = {}
    for name, sequence in pairs.items():
        if isinstance(sequence, str | os.PathLike):
            try:
                sequence = open_sequence(sequence)
            except DataError as exc:  # (which robot's: the message names only the path)
                raise DataError(f"sequences[{name!r}]: {exc}") from None
        elif not isinstance(sequence, Sequence):
            raise DataError(f"sequences[{name!r}]: {type(sequence).__name__} is not a sequence; give the sequence "
                            "the robot ran on (open_sequence(), an ArraySequence) or its path[:start-end]")  # fmt: skip
        opened[name] = sequence
    return opened
