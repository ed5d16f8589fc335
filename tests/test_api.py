"""shgm_slam from Python (``shgm_slam.api``): the command line's results, frames held in memory, clear errors."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

import shgm_slam
from shgm_slam import ArraySequence, open_sequence
from shgm_slam.api import read_fused, run
from shgm_slam.config import Dof, ShgmConfig
from shgm_slam.errors import ConfigError, DataError, GraphError
from shgm_slam.geometry.se3 import transform_points
from shgm_slam.graph.semantic_graph import edges_within_radius
from shgm_slam.types import GraphArrays

REPO_ROOT = Path(__file__).resolve().parents[1]


def in_memory(folder: Path) -> ArraySequence:
    """Every frame of a sequence folder, loaded into arrays (as a user's own frames would come)."""
    seq = open_sequence(folder)
    frames = list(seq)
    return ArraySequence(
        np.stack([f.image_rgb for f in frames]), seq.intrinsics, seq.timestamps_s,
        depth_m=np.stack([f.depth_m for f in frames]), label_ids=np.stack([f.label_ids for f in frames]),
        T_world_cam=seq.gt_poses, name=folder.name,
    )  # fmt: skip


@pytest.fixture(scope="module")
def two_runs(tiny_scenario: Path, tmp_path_factory: pytest.TempPathFactory):
    """car1 and car2 of the tiny world run once from their folders and once from memory, with defaults."""
    tmp = tmp_path_factory.mktemp("api")
    names = ("car1", "car2")
    from_folders = run({n: open_sequence(tiny_scenario / n) for n in names}, tmp / "folders")
    from_memory = run({n: in_memory(tiny_scenario / n) for n in names}, tmp / "memory")
    return from_folders, from_memory


def test_frames_in_memory_give_the_run_that_their_folders_give(two_runs) -> None:
    folders, memory = two_runs
    assert [r.name for r in memory.robots] == ["car1", "car2"]
    for a, b in zip(folders.robots, memory.robots, strict=True):
        assert (a.frames_processed, a.keyframes, a.nodes, a.localized) == (b.frames_processed, b.keyframes, b.nodes,
                                                                           b.localized)  # fmt: skip
    assert (folders.matches_tried, folders.closures_accepted) == (memory.matches_tried, memory.closures_accepted)
    assert memory.robots[0].localized and memory.robots[0].ate_fused_m < 1.0  # the truth came along
    compared = 0
    for robot in ("car1", "car2"):
        for kind in ("fused_tum", "odometry_tum", "fused_kitti"):
            name = f"{robot}_{kind}.txt"
            if (folders.out_dir / name).exists() or (memory.out_dir / name).exists():
                assert (folders.out_dir / name).read_bytes() == (memory.out_dir / name).read_bytes(), name
                compared += 1
    assert compared >= 4  # both odometries and at least the reference's fused trajectory, byte for byte


def test_frames_in_memory_travel_to_worker_processes(two_runs, tiny_scenario: Path, tmp_path: Path) -> None:
    """``jobs=2``: the sequences are pickled into spawned workers; the results are those of one process."""
    _, memory = two_runs
    cfg = ShgmConfig()
    before = cfg.model_dump()
    summary = run({n: in_memory(tiny_scenario / n) for n in ("car1", "car2")}, tmp_path / "jobs", jobs=2, config=cfg)
    assert cfg.model_dump() == before  # the caller's configuration is left as it was (derived values go elsewhere)
    assert not summary.skipped_reasons
    for name in ("car1_odometry_tum.txt", "car2_odometry_tum.txt", "car1_fused_tum.txt"):
        assert (summary.out_dir / name).read_bytes() == (memory.out_dir / name).read_bytes(), name


def test_predicted_depth_in_memory_is_treated_as_a_networks(tiny_scenario: Path) -> None:
    """``DepthOrigin.PREDICTED``: as for a ``perceive`` folder, the visual odometry and depth scaled to the camera
    height; measured depth (the default): KISS-ICP, never rescaled."""
    from shgm_slam import DepthOrigin
    from shgm_slam.config import OdometryKind
    from shgm_slam.runner import prepare_frontends

    seq = in_memory(tiny_scenario / "car1")
    predicted = ArraySequence([f.image_rgb for f in seq], seq.intrinsics, seq.timestamps_s,
                              depth_m=[f.depth_m for f in seq], label_ids=[f.label_ids for f in seq],
                              depth_origin=DepthOrigin.PREDICTED)  # fmt: skip
    fronts = prepare_frontends({"car1": predicted, "car2": seq}, ShgmConfig())
    assert fronts["car1"].depth_predicted and fronts["car1"].ground_scale_on
    assert fronts["car1"].odometry_choice.kind is OdometryKind.VISUAL
    assert not fronts["car2"].depth_predicted and not fronts["car2"].ground_scale_on
    assert fronts["car2"].odometry_choice.kind is OdometryKind.KISS_ICP


def test_read_fused_gives_what_the_run_wrote(two_runs) -> None:
    _, memory = two_runs
    for report in memory.robots:
        fused = read_fused(memory.out_dir, report.name)
        if not report.localized:
            continue
        assert fused is not None and fused.robot == report.name
        n = report.fused_poses
        assert fused.T_shared_cam.shape == (n, 4, 4) and fused.timestamps_s.shape == (n,)
        assert fused.provisional == report.provisional
        np.testing.assert_allclose(fused.T_shared_cam[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))
    with pytest.raises(DataError, match="holds no robot 'uav'; its run had car1, car2"):
        read_fused(memory.out_dir, "uav")


def test_evaluate_agrees_with_the_run(two_runs, tiny_scenario: Path) -> None:
    """``evaluate`` (``shgm-slam eval``) on the run's folder, from its ground-truth files or from the sequences: the
    fused ATE the run reported for each placed robot."""
    from shgm_slam.api import evaluate

    _, memory = two_runs
    from_files = evaluate(memory.out_dir)
    from_sequences = evaluate(memory.out_dir, {n: open_sequence(tiny_scenario / n) for n in ("car1", "car2")})
    for result in (from_files, from_sequences):
        assert result.reference_robot == "car1"
        by_name = {r.name: r for r in result.robots}
        for report in memory.robots:
            assert by_name[report.name].localized == report.localized
            if report.localized:
                assert by_name[report.name].ate_fused_m == pytest.approx(report.ate_fused_m, abs=0.01)


def test_evaluate_opens_paths_and_refuses_what_is_no_sequence(two_runs, tiny_scenario: Path) -> None:
    """Ground truth named by path, as ``eval --gt`` takes it: a string was taken for a sequence of as many frames as
    it has characters ("its sequence has 29 frames but the run had ..."), a ``Path`` or a list of sequences ended
    in Python's TypeError or ValueError."""
    from shgm_slam.api import evaluate

    _, memory = two_runs
    opened = evaluate(memory.out_dir, {n: open_sequence(tiny_scenario / n) for n in ("car1", "car2")})
    by_path = evaluate(memory.out_dir, {"car1": str(tiny_scenario / "car1"), "car2": tiny_scenario / "car2"})
    assert by_path.gt_source == "sequences"
    for a, b in zip(opened.robots, by_path.robots, strict=True):
        assert a.name == b.name and a.evaluated_poses == b.evaluated_poses
        np.testing.assert_equal(a.ate_fused_m, b.ate_fused_m)
    with pytest.raises(DataError, match=r"sequences\['car1'\]: int is not a sequence; give the sequence"):
        evaluate(memory.out_dir, {"car1": 8})
    with pytest.raises(DataError, match=r"sequences must be a mapping .*not list"):
        evaluate(memory.out_dir, [open_sequence(tiny_scenario / "car1")])
    with pytest.raises(DataError, match="results folder None is no path"):
        evaluate(None)
    with pytest.raises(DataError, match=r"metrics\.json is a file, not a folder"):
        read_fused(memory.out_dir / "metrics.json", "car1")  # said "does not exist"


def test_a_refused_run_leaves_no_folder_behind(tiny_scenario: Path, tmp_path: Path) -> None:
    car1 = open_sequence(tiny_scenario / "car1")
    with pytest.raises(ConfigError, match="robot name '1car' is invalid"):
        run({"1car": car1}, tmp_path / "a")
    with pytest.raises(ConfigError, match="no robots given"):
        run({}, tmp_path / "b")
    with pytest.raises(DataError, match="robot 'car1': list is not a sequence"):
        run({"car1": [car1[0]]}, tmp_path / "c")
    with pytest.raises(ConfigError, match="viewer 'window': choose one of"):
        run({"car1": car1}, tmp_path / "d", viewer="window")
    with pytest.raises(ConfigError, match="jobs 0"):
        run({"car1": car1}, tmp_path / "e", jobs=0)
    with pytest.raises(ConfigError, match="does not exist"):
        run({"car1": car1}, tmp_path / "f", config=tmp_path / "missing.yaml")
    images_only = ArraySequence([f.image_rgb for f in car1], car1.intrinsics, car1.timestamps_s)
    with pytest.raises(DataError, match=r"robot 'car1': sequence in memory has no depth .* set perception.depth_model"):
        run({"car1": images_only}, tmp_path / "h")
    with pytest.raises(ConfigError, match="settings for robot\\(s\\) car9"):
        run({"car1": car1}, tmp_path / "g", config=ShgmConfig.model_validate({"robots": {"car9": {}}}))
    # a progress function of other arguments ran until after the first frame: a TypeError, the folder incomplete
    with pytest.raises(ConfigError, match=r"progress '<lambda>' cannot be called with \(frames done, frames total\)"):
        run({"car1": car1}, tmp_path / "i", progress=lambda fraction: None)
    with pytest.raises(ConfigError, match=r"progress must be a function of .*not str"):
        run({"car1": car1}, tmp_path / "j", progress="bar")
    with pytest.raises(ConfigError, match=r"robots must be a mapping \{name: sequence\}, not list"):  # "no robots"
        run([("car1", car1)], tmp_path / "k")
    # a configuration as a mapping of stages is validated as a YAML file is (it was refused as "not dict")
    with pytest.raises(ConfigError, match=r"config mapping: matching\.bogus: Extra inputs are not permitted"):
        run({"car1": car1}, tmp_path / "l", config={"matching": {"bogus": 1}})
    with pytest.raises(ConfigError, match=r"config mapping: matching\.top_kk: .*did you mean top_k\?"):  # as a file
        run({"car1": car1}, tmp_path / "l", config={"matching": {"top_kk": 3}})
    # numpy integers are whole numbers of jobs ("jobs np.int64(2): give a whole number" before), and a mapping is a
    # configuration: both taken, so the run is refused by the next check, its viewer
    with pytest.raises(ConfigError, match="viewer 'window'"):
        run({"car1": car1}, tmp_path / "m", config={"matching": {"top_k": 3}}, jobs=np.int64(2), viewer="window")
    with pytest.raises(ConfigError, match="jobs True"):
        run({"car1": car1}, tmp_path / "n", jobs=True)
    assert not any(tmp_path.iterdir())


@pytest.fixture(scope="module")
def sparse_pairs():
    from shgm_slam.bench.localization_sparse import SparseOptions, make_pairs
    from shgm_slam.sim.city import CityParams, build_city

    seed = 10  # a tuning seed of the sparse benchmark
    return make_pairs(build_city(CityParams(), seed=seed), seed, SparseOptions(seeds=(seed,), pairs_per_seed=3), 10.0)


def test_match_localizes_graph_files_as_the_command_line_does(sparse_pairs, tmp_path: Path) -> None:
    from shgm_slam.api import match
    from shgm_slam.io.graph_json import write_graph

    placed = 0
    for k, pair in enumerate(sparse_pairs):
        a, b = write_graph(tmp_path / f"a{k}.json", pair.graph_a), write_graph(tmp_path / f"b{k}.json", pair.graph_b)
        found = match(a, b)
        again = match(pair.graph_a, pair.graph_b)
        assert found.gravity_aligned and found.up_axis == again.up_axis  # map-like graphs lie flat along z
        assert found.nodes == (len(pair.graph_a), len(pair.graph_b))
        assert found.result.success == again.result.success
        if not pair.overlapping:
            assert not found.result.success, "a far-apart pair was accepted"
        elif found.result.success:
            placed += 1
            centroid = pair.graph_b.positions_xyz.mean(axis=0)
            truth = transform_points(pair.T_a_b, centroid)
            err = np.linalg.norm(transform_points(found.result.T_a_b, centroid) - truth)
            assert err < 2.0
    assert placed >= 2
    six = match(sparse_pairs[0].graph_a, sparse_pairs[0].graph_b, dof=Dof.SIX)
    assert not six.gravity_aligned and six.up_axis == found.up_axis  # any rotation; the chance model keeps the up


def test_the_package_exports_the_api_lazily() -> None:
    assert {"run", "match", "read_fused", "evaluate", "ArraySequence", "open_sequence", "ShgmConfig"} <= set(
        shgm_slam.__all__
    )
    assert shgm_slam.run is run
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        shgm_slam.nothing  # noqa: B018


def readme_python_example() -> str:
    """The README's *From Python* example (the python block after that heading)."""
    text = (REPO_ROOT / "README.md").read_text()
    section = text[text.index("### From Python"):]
    found = re.search(r"```python\n(.*?)```", section, re.S)
    assert found, "README: *From Python* has no python block"
    return found.group(1)


def test_the_readme_python_example_runs(tiny_scenario: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    """The example, run where ``make demo``'s world (``cache/airsim-like-seed0``) is the tiny world."""
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "airsim-like-seed0").symlink_to(tiny_scenario)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "readme_example"}
    exec(compile(readme_python_example(), "README.md", "exec"), namespace)
    summary = namespace["summary"]
    assert summary.out_dir == Path("results/from_python") and [r.name for r in summary.robots] == ["car1", "car2"]
    assert summary.robots[0].localized and "car1" in namespace["placed"]
    printed = capsys.readouterr().out
    assert all(f"{name}: " in printed for name in namespace["placed"])


def _street_graph(n: int = 40) -> GraphArrays:
    rng = np.random.default_rng(2)
    p = rng.uniform(0, 60, (n, 3)) * [1.0, 0.05, 1.0]
    return GraphArrays(np.arange(n, dtype=np.int64), rng.choice([2, 5, 7, 13], n).astype(np.int64), p,
                       np.full(n, 100.0), edges_within_radius(p, 20.0))  # fmt: skip


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda g: {"positions_xyz": np.where(np.arange(40)[:, None] == 3, np.nan, g.positions_xyz)},
         r"non-finite node positions \(row 3\)"),  # was numpy's LinAlgError from the vertical's eigenvectors
        (lambda g: {"positions_xyz": np.full_like(g.positions_xyz, np.inf)}, "non-finite node positions"),
        (lambda g: {"node_ids": np.zeros(40, np.int64)}, "node ids repeat"),  # was matched, inliers ambiguous
        (lambda g: {"label_ids": g.label_ids + 0.5}, "label ids must be integers"),  # was truncated silently
        (lambda g: {"edges": np.array([[-3, 2]])}, "references row -3"),  # named row 2
        (lambda g: {"edges": np.array([1, 2, 3])}, r"\(E, 2\) array"),  # was numpy's reshape error
        (lambda g: {"sizes": g.sizes.tolist()}, "must be numpy arrays"),  # was AttributeError
        (lambda g: {"positions_xyz": g.positions_xyz.astype(object)}, "positions_xyz must be numbers, got object"),
        # ^ was np.isfinite's TypeError; v was numpy's "Eigenvalues did not converge" (LinAlgError)
        (lambda g: {"positions_xyz": g.positions_xyz * 1e200}, "graph B: a node lies .* m from the origin, beyond"),
        (lambda g: {"positions_xyz": g.positions_xyz / 111000 + [48.1, 11.5, 0]},  # degrees
         "graph B: its 40 nodes span only .*latitude and longitude"),  # was "no consistent hypothesis"
    ],
)  # fmt: skip
def test_match_refuses_graph_arrays_that_hold_no_graph(change, message) -> None:
    good = _street_graph()
    bad = dataclasses.replace(good, **change(good))
    with pytest.raises(GraphError, match=message):
        shgm_slam.match(good, bad)
    with pytest.raises(GraphError, match=message.replace("graph B", "graph A")):
        shgm_slam.match(bad, good)
    assert shgm_slam.match(good, good).result.success  # the good graph itself matches


def test_match_takes_dof_as_a_number_and_refuses_what_is_no_graph() -> None:
    """``dof=4`` / ``6`` (the command line's ``--dof 4``) and a configuration as a mapping are taken; an unknown dof
    and a graph that is neither ``GraphArrays`` nor a path are refused naming what to give (Python's ValueError
    and pathlib's TypeError before)."""
    good = _street_graph()
    assert shgm_slam.match(good, good, dof=4).gravity_aligned
    assert not shgm_slam.match(good, good, dof=np.int64(6)).gravity_aligned
    assert shgm_slam.match(good, good, dof="AUTO", config={"matching": {"top_k": 3}}).result.success
    with pytest.raises(ConfigError, match=r"dof 5: choose Dof\.AUTO"):
        shgm_slam.match(good, good, dof=5)
    with pytest.raises(GraphError, match="graph A: give GraphArrays or a shgm-graph/1 file's path, not dict"):
        shgm_slam.match({"format": "shgm-graph/1", "classes": [], "nodes": []}, good)
    with pytest.raises(GraphError, match=r"graph B: give GraphArrays .*not NoneType"):
        shgm_slam.match(good, None)


def test_map_files_without_heights_match(tmp_path) -> None:
    """Two map layers of [x, y] positions (no heights; refused before) are read at height 0 and matched about
    their common vertical."""
    import json

    g = _street_graph()
    for name, shift in (("a", (0.0, 0.0)), ("b", (-7.0, 4.0))):
        nodes = [{"id": int(i), "label": int(lab), "position": [float(x + shift[0]), float(z + shift[1])]}
                 for i, lab, (x, _, z) in zip(g.node_ids, g.label_ids, g.positions_xyz, strict=True)]  # fmt: skip
        doc = {"format": "shgm-graph/1", "classes": list(shgm_slam.labels.CITYSCAPES_CLASSES), "nodes": nodes}
        (tmp_path / f"{name}.json").write_text(json.dumps(doc))
    m = shgm_slam.match(tmp_path / "a.json", tmp_path / "b.json")
    assert m.result.success and m.gravity_aligned
    np.testing.assert_allclose(m.result.T_a_b[:3, 3], [7.0, -4.0, 0.0], atol=1e-6)
