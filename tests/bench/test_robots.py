"""bench robots: fleet costs summed over every robot's steps, the stretches, the report, bad fleet sizes."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.bench.robots import (
    PLACED_RIGHT_M,
    STRETCHES,
    FleetCost,
    overlapping,
    overlaps_m,
    placement,
    robots_markdown,
    run_robots_benchmark,
    stretch_specs,
)
from shgm_slam.errors import ConfigError
from shgm_slam.run_report import FrameStats
from shgm_slam.runner import parse_robot_arg
from shgm_slam.server.records import MatchRecord


def _match(nodes_a: int, nodes_b: int) -> MatchRecord:
    return MatchRecord(1, "a", "b", "submap", False, False, "", None, None, None, np.zeros((0, 2)), 0, nodes_a,
                       nodes_b, {})  # fmt: skip


def _stats(robot: str, frame: int, keyframe: bool, ms: float, matches: int = 0) -> FrameStats:
    return FrameStats(robot, frame, keyframe, ms, 1.0, ms / 2, ms / 4, ms, 3 * ms,
                      tuple(_match(100, 20) for _ in range(matches)), 2 * ms)  # fmt: skip


def test_fleet_cost_sums_every_robot_and_divides_by_keyframes():
    cost = FleetCost()
    for robot in ("r1", "r2"):
        for f in range(10):
            cost(_stats(robot, f, f % 2 == 0, 10.0, matches=1 if f == 0 else 0))
    row = cost.row(2, driven_s=5.0)
    assert row["frames"] == 20 and row["keyframes"] == 10
    assert row["front_end_ms_per_kf"] == pytest.approx(10.0 * 20 / 10)
    assert row["match_ms_per_kf"] == pytest.approx(5.0 * 20 / 10)
    assert row["server_other_ms_per_kf"] == pytest.approx((10.0 - 5.0 - 2.5) * 20 / 10)
    assert row["total_ms_per_kf"] == pytest.approx((30.0 - 1.0) * 20 / 10)
    assert row["matches_per_kf"] == pytest.approx(2 / 10)
    assert row["ms_per_match"] == pytest.approx(5.0 * 20 / 2)
    assert row["nodes_per_match"] == pytest.approx(120.0)
    assert row["cpu_s_per_driven_s"] == pytest.approx(20 * 20.0 / 1e3 / 5.0)


def test_an_empty_fleet_cost_has_no_division_by_zero():
    row = FleetCost().row(1, driven_s=0.0)
    assert row["total_ms_per_kf"] == 0.0 and row["ms_per_match"] == 0.0 and np.isnan(row["cpu_s_per_driven_s"])


def test_stretches_are_equal_contiguous_half_open_ranges(tmp_path: Path):
    specs = stretch_specs(tmp_path, 4541)
    assert len(specs) == STRETCHES
    ranges = []
    for i, spec in enumerate(specs):
        name, path = parse_robot_arg(spec)
        assert name == f"r{i + 1}" and path.startswith(str(tmp_path))
        a, b = (int(x) for x in path.rsplit(":", 1)[1].split("-"))
        ranges.append((a, b))
    assert ranges[0][0] == 0 and all(b == a2 for (_, b), (a2, _) in pairwise(ranges))
    assert {b - a for a, b in ranges} == {4541 // STRETCHES}
    with pytest.raises(ConfigError, match="too few"):
        stretch_specs(tmp_path, STRETCHES - 1)


@pytest.mark.parametrize("fleets", [(), (0,), (STRETCHES + 1,)])
def test_fleet_sizes_outside_the_stretches_are_refused_before_any_work(tmp_path: Path, fleets: tuple[int, ...]):
    with pytest.raises(ConfigError, match="fleet sizes"):
        run_robots_benchmark(tmp_path / "out", fleets=fleets, cache=tmp_path / "cache")
    assert not (tmp_path / "cache").exists()


@pytest.mark.parametrize("sequence", ["11", "7", "xx"])
def test_sequences_without_kitti_ground_truth_are_refused_before_any_work(tmp_path: Path, sequence: str):
    with pytest.raises(ConfigError, match="00-10"):
        run_robots_benchmark(tmp_path / "out", sequence=sequence, cache=tmp_path / "cache")
    assert not (tmp_path / "cache").exists()


def _line(x0: float, x1: float, y: float) -> np.ndarray:
    x = np.arange(x0, x1 + 0.5, 1.0)
    return np.column_stack([x, np.full_like(x, y), np.zeros_like(x)])


def test_overlap_is_the_length_of_path_near_another_path():
    a = _line(0.0, 200.0, 0.0)
    b = _line(100.0, 400.0, 5.0)  # beside a from x = 100 to 200 (5 m apart), then on its own
    c = _line(0.0, 300.0, 50.0)  # a parallel street 50 m away: never within 10 m
    o = overlaps_m([a, b, c])
    reach = np.sqrt(10.0**2 - 5.0**2)  # within 10 m of b's first point from this far before it
    assert o[0, 1] == pytest.approx(100.0 + reach, abs=1.5) and o[1, 0] == pytest.approx(100.0 + reach, abs=1.5)
    assert o[0, 2] == 0.0 and o[2, 1] == 0.0 and np.all(np.diag(o) == 0.0)


def test_robots_that_could_be_placed_are_linked_to_the_first_through_enough_shared_street():
    o = np.zeros((5, 5))
    o[0, 1] = 100.0  # r2 beside r1
    o[2, 1] = 60.0  # r3 beside r2 only (one way is enough)
    o[3, 0] = 20.0  # r4 touches r1 for 20 m: too little
    o[4, 3] = 300.0  # r5 beside r4 only: linked to nothing placeable
    assert overlapping(o).tolist() == [True, True, True, False, False]


def test_placement_judges_where_robots_were_placed_not_their_drift(tmp_path: Path):
    """Placement as ``bench heldout`` judges it: r1's heading error at its first pose turns the whole shared
    frame (the gauge, nobody's fault); r2 drifts 2.6 m along its drive (its shared-frame ATE beyond 2 m) but is
    placed right; r3 is placed 3 m off; r4 could not be placed and was (wrong); r5 could be and was not; r6
    neither could nor was."""
    from types import SimpleNamespace

    from shgm_slam.geometry.se3 import make_pose, rot_z
    from shgm_slam.io.trajectories import write_tum

    def drive(x0: float, y0: float, heading: float, n: int = 40) -> np.ndarray:
        s = np.arange(n) * 2.0
        xyz = np.c_[x0 + s * np.cos(heading) + 5 * np.sin(s / 20), y0 + s * np.sin(heading), np.zeros(n)]
        return make_pose(np.repeat(rot_z(heading)[None], n, axis=0), xyz)

    gt = {"r1": drive(0, 0, 0.0), "r2": drive(10, 30, 1.2), "r3": drive(-20, 10, 2.5), "r4": drive(40, -30, -0.7),
          "r5": drive(5, 5, 0.3), "r6": drive(90, 90, 0.0)}  # fmt: skip
    robots = {k: SimpleNamespace(gt_poses=v, timestamps_s=np.arange(len(v)) * 0.1) for k, v in gt.items()}
    T_shared_world = np.linalg.inv(gt["r1"][0])
    gauge = make_pose(rot_z(0.02), [0.3, -0.2, 0.0])  # the frame turned by r1's first estimated pose
    fused = {k: gauge @ T_shared_world @ v for k, v in gt.items()}
    fused["r2"][:, :3, 3] += np.linspace(0, 1, 40)[:, None] * [2.6, 0.0, 0.0]  # its own drift, 2.6 m by the end
    fused["r3"][:, :3, 3] += [3.0, 0.0, 0.0]  # placed 3 m off
    placed = {"r1", "r2", "r3", "r4"}
    for k in placed:
        write_tum(tmp_path / f"{k}_fused_tum.txt", robots[k].timestamps_s, fused[k])
    shared_ate = {"r1": 0.5, "r2": 2.5, "r3": 3.0, "r4": 1.0}
    summary = {"robots": [{"name": k, "localized": k in placed, "ate_fused_m": shared_ate.get(k, np.nan)}
                          for k in gt],
               "matches_tried": 9, "closures_accepted": 4, "wall_s": 1.0}  # fmt: skip
    can = {"r1": True, "r2": True, "r3": True, "r4": False, "r5": True, "r6": False}
    p = placement(summary, can, tmp_path, robots)
    assert (p["can_place"], p["placed"], p["placed_right"], p["placed_wrong"], p["not_placed_could"]) == (4, 4, 2, 2, 1)
    assert p["placement_m"]["r3"] == pytest.approx(3.0, abs=0.05) and p["placement_m"]["r2"] < PLACED_RIGHT_M
    assert p["fused_ate_median_m"] == pytest.approx(1.75) and p["fused_ate_max_m"] == pytest.approx(3.0)


def test_markdown_has_a_row_per_fleet_with_its_memory():
    rows = []
    for n in (1, 2):
        cost = FleetCost()
        for f in range(4):
            cost(_stats(f"r{n}", f, True, 10.0 * n, matches=n - 1))
        row = cost.row(n, 10.0) | {"can_place": n, "placed": n, "placed_right": n, "placed_wrong": 0,
                                   "not_placed_could": 0, "fused_ate_median_m": 1.0, "fused_ate_max_m": 2.0,
                                   "matches_tried": 0, "closures_accepted": 0, "wall_s": 1.0, "accepted_judged": 3,
                                   "accepted_gross": 1, "anchorings": None, "anchorings_gross": 0}  # fmt: skip
        rows.append(row)
    for r in rows:
        r["total_per_kf_over_smallest"] = r["total_ms_per_kf"] / rows[0]["total_ms_per_kf"]
    text = robots_markdown({"stretches": ["a", "b"], "stretch_frames": 567, "fleets": rows,
                            "memory": {"2": {"peak_rss_mb": 321.0, "wall_s": 3.0}}})  # fmt: skip
    lines = [ln for ln in text.splitlines() if ln.startswith("| ")]
    assert lines[1].startswith("| 1 | 4 |") and lines[1].endswith("| - |")
    ratio = f"| {rows[1]['total_per_kf_over_smallest']:.2f} |"
    assert lines[2].startswith("| 2 | 4 |") and ratio in lines[2] and lines[2].endswith("| 321 |")
    assert lines[4].startswith("| 1 | 1 | 1 | 0 | 0 |") and lines[4].endswith("| 3 | 1 | 0/? |")


def test_markdown_puts_the_worker_processes_run_beside_the_one_process_run():
    row = {"robots": 2, "keyframes": 4, "front_end_ms_per_kf": 1.0, "match_ms_per_kf": 1.0, "backend_ms_per_kf": 1.0,
           "server_other_ms_per_kf": 1.0, "total_ms_per_kf": 4.0, "cpu_ms_per_kf": 4.0,
           "total_per_kf_over_smallest": 1.0, "matches_per_kf": 0.0, "ms_per_match": 0.0, "nodes_per_match": 0.0,
           "cpu_s_per_driven_s": 1.0, "can_place": 2, "placed": 2, "placed_right": 2, "placed_wrong": 0,
           "not_placed_could": 0, "fused_ate_median_m": 1.0, "fused_ate_max_m": 1.0, "matches_tried": 1,
           "closures_accepted": 1, "wall_s": 30.0, "accepted_judged": 1, "accepted_gross": 0, "anchorings": 1,
           "anchorings_gross": 0, "jobs": 2, "jobs_wall_s": 20.0, "jobs_speedup": 1.5, "jobs_same_results": True}
    text = robots_markdown({"stretches": ["a", "b"], "stretch_frames": 5, "fleets": [row],
                            "memory": {"2": {"peak_rss_mb": 300.0, "wall_s": 3.0}},
                            "memory_jobs": {"2": {"peak_rss_mb": 700.0, "wall_s": 2.0}}})  # fmt: skip
    assert "| 2 | 30.0 | 2 | 20.0 | 1.50x | yes |" in text
    assert "2 worker processes: 700 MB, all processes together (300 MB in one process)" in text
    assert "**no**" in robots_markdown({"stretches": ["a"], "stretch_frames": 5,
                                        "fleets": [row | {"jobs_same_results": False}]})  # fmt: skip


def test_same_results_compares_every_results_file_but_not_the_timings(tmp_path: Path):
    import json

    from shgm_slam.bench.robots import same_results

    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "car_fused_tum.txt").write_text("0 1 2 3 0 0 0 1\n")
        (tmp_path / d / "pose_graph.g2o").write_text("VERTEX_SE3:QUAT 0\n")
        (tmp_path / d / "metrics.json").write_text(json.dumps({"robots": [1], "wall_s": len(d) + ord(d)}))
    assert same_results(tmp_path / "a", tmp_path / "b")
    (tmp_path / "b" / "car_fused_tum.txt").write_text("0 1 2 3.000001 0 0 0 1\n")
    assert not same_results(tmp_path / "a", tmp_path / "b")
    (tmp_path / "b" / "car_fused_tum.txt").write_text("0 1 2 3 0 0 0 1\n")
    (tmp_path / "b" / "metrics.json").write_text(json.dumps({"robots": [2], "wall_s": 1}))
    assert not same_results(tmp_path / "a", tmp_path / "b")
    (tmp_path / "b" / "metrics.json").write_text(json.dumps({"robots": [1], "wall_s": 1}))
    (tmp_path / "b" / "extra_odometry_tum.txt").write_text("")
    assert not same_results(tmp_path / "a", tmp_path / "b")


def test_a_stopped_fleet_ends_the_benchmark_and_the_fleets_finished_are_written(tiny_scenario: Path, tmp_path: Path,
                                                                               monkeypatch: pytest.MonkeyPatch):
    """Ctrl-C in the second fleet's run: the first fleet's row is written, marked interrupted, the larger fleets
    and the memory runs never start (before, the benchmark went on to the next fleet as if nothing happened)."""
    import shgm_slam.bench.robots as robots_bench
    from shgm_slam.bench.stopping import RunStopped

    world = tmp_path / "world"
    world.mkdir()
    (world / "kitti00").symlink_to(tiny_scenario / "car1", target_is_directory=True)
    monkeypatch.setattr(robots_bench, "_world", lambda *args, **kwargs: world)
    real_run, runs = robots_bench.run_to_end, []

    def stopped_in_second_fleet(robots, cfg, out, **kwargs):
        runs.append(Path(out).name)
        if Path(out).name == "fleet_2":
            raise RunStopped("stopped")
        return real_run(robots, cfg, out, **kwargs)

    monkeypatch.setattr(robots_bench, "run_to_end", stopped_in_second_fleet)
    out = tmp_path / "out"
    results = run_robots_benchmark(out, fleets=(1, 2, 4), sequence="00", cache=tmp_path / "cache", jobs=1)
    assert runs == ["fleet_1", "fleet_2"]
    assert results["interrupted"] and [r["robots"] for r in results["fleets"]] == [1] and "memory" not in results
    assert (out / "robots.md").read_text().startswith("**Interrupted**")
