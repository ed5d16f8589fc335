"""Sparse map-like localization benchmark: pairs as specified, deterministic by seed, scored honestly."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.bench.localization_sparse import (
    MAP_KINDS,
    MAX_NODES,
    MIN_COMMON,
    MIN_NODES,
    NEGATIVE_GAP_M,
    UP_WORLD,
    SparseOptions,
    SparseOutcome,
    SparseResults,
    make_pairs,
    run_sparse_benchmark,
    sparse_markdown,
)
from shgm_slam.bench.seeds import parse_seeds
from shgm_slam.config import MatchingConfig
from shgm_slam.errors import ConfigError
from shgm_slam.geometry.se3 import make_pose, rot_z, transform_points
from shgm_slam.labels import Label
from shgm_slam.matching import judge_alignment
from shgm_slam.sim.city import CityParams, build_city
from shgm_slam.sim.shapes import KIND_LABEL

SEED = 10  # a tuning seed


@pytest.fixture(scope="module")
def world():
    return build_city(CityParams(), seed=SEED)


def test_pairs_are_sparse_map_like_and_deterministic(world):
    opt = SparseOptions(seeds=(SEED,), pairs_per_seed=3)
    pairs = make_pairs(world, SEED, opt, 10.0)
    again = make_pairs(world, SEED, opt, 10.0)
    assert [p.overlapping for p in pairs] == [True] * 3 + [False] * 3
    map_labels = {KIND_LABEL[k] for k in MAP_KINDS}
    assert Label.CAR not in map_labels
    for p, q in zip(pairs, again, strict=True):
        np.testing.assert_array_equal(p.graph_b.positions_xyz, q.graph_b.positions_xyz)
        for g in (p.graph_a, p.graph_b):
            assert MIN_NODES <= len(g) <= MAX_NODES
            assert set(np.unique(g.label_ids).tolist()) <= map_labels
        if p.overlapping:
            assert p.common >= MIN_COMMON
        else:  # B mapped back into A's frame stays far from everything A mapped
            pb = transform_points(p.T_a_b, p.graph_b.positions_xyz)
            gap = np.linalg.norm(p.graph_a.positions_xyz[:, None, :2] - pb[None, :, :2], axis=2).min()
            assert gap > NEGATIVE_GAP_M - 2 * 40.0  # lanes are apart; objects lie within 40 m of them


def test_maps_without_heights_are_the_same_pairs_at_height_zero(world):
    """``--no-heights`` (map layers of [x, y] positions): the same pairs, every node on one level plane of each map's
    frame, and the truth still lays B's shared objects onto A's."""
    opt = SparseOptions(seeds=(SEED,), pairs_per_seed=2)
    flat_opt = SparseOptions(seeds=(SEED,), pairs_per_seed=2, heights=False)
    for p, q in zip(make_pairs(world, SEED, opt, 10.0), make_pairs(world, SEED, flat_opt, 10.0), strict=True):
        np.testing.assert_array_equal(p.graph_a.label_ids, q.graph_a.label_ids)
        np.testing.assert_allclose(p.graph_a.positions_xyz[:, :2], q.graph_a.positions_xyz[:, :2], atol=1e-9)
        np.testing.assert_allclose(p.T_a_b, q.T_a_b)
        for g in (q.graph_a, q.graph_b):
            assert np.ptp(g.positions_xyz[:, 2]) < 1e-9  # one height (each frame is moved up or down as a whole)
        assert np.ptp(p.graph_a.positions_xyz[:, 2]) > 1.0  # with heights, objects stand at their heights
        pb = transform_points(q.T_a_b, q.graph_b.positions_xyz)
        assert abs(pb[:, 2].mean() - q.graph_a.positions_xyz[:, 2].mean()) < 1e-9
    assert "no heights" in flat_opt.conditions_note() and flat_opt.conditions()["heights"] is False


def test_true_transform_maps_shared_objects_onto_each_other(world):
    """Under the true T_a_b, B's nodes land near same-label nodes of A (noise + confusions only)."""
    pair = make_pairs(world, SEED, SparseOptions(seeds=(SEED,), pairs_per_seed=1), 10.0)[0]
    pb = transform_points(pair.T_a_b, pair.graph_b.positions_xyz)
    d = np.linalg.norm(pair.graph_a.positions_xyz[:, None] - pb[None], axis=2)
    same = pair.graph_a.label_ids[:, None] == pair.graph_b.label_ids[None]
    close = (np.where(same, d, np.inf) < 6.0).any(axis=0).sum()
    assert close >= 0.5 * pair.common


def test_benchmark_runs_scores_and_summarizes(world):
    opt = SparseOptions(seeds=(SEED,), pairs_per_seed=2, full_rotation=True)
    results = run_sparse_benchmark(opt)
    summary = results.summary()
    assert set(summary) == {"4dof", "6dof"}
    for s in summary.values():
        assert s["overlapping_pairs"] == 2 and s["negatives"] == 2
        assert s["localized"] + s["wrong_claims"] <= 2 and s["median_ms"] > 0
    for o in results.outcomes:
        assert not (o.success and not o.overlapping) or not o.correct  # a negative is never "correct"
        assert o.correct == (o.trans_err_m < 2.0 and o.rot_err_deg < 5.0)
    for s in summary.values():  # a perfect search localizes at least what this one did
        assert s["localized"] <= s["search_ceiling"] <= s["overlapping_pairs"]
    for o in results.outcomes:
        assert np.isnan(o.truth_margin_nats) != o.overlapping  # measured for overlapping pairs only
    assert "| 4dof |" in sparse_markdown(results, opt.seeds) and "search ceiling" in sparse_markdown(results, opt.seeds)
    for key, s in summary.items():  # the farthest wrong claim, or None without one
        errors = [o.trans_err_m for o in results.outcomes
                  if f"{o.dof}dof" == key and o.overlapping and o.success and not o.correct]  # fmt: skip
        assert s["worst_wrong_m"] == (max(errors) if errors else None)
    doc = results.to_json()
    assert len(doc["outcomes"]) == 8


def test_noisier_maps_localize_fewer_pairs_and_say_so_in_the_report():
    """The same pairs (seed 10) with centroids 3 m off instead of 0.3 m: what the whole-overlap evidence can
    support shrinks (the search ceiling with it), and the report names the conditions it ran under."""
    def run(noise_m):
        opt = SparseOptions(seeds=(SEED,), pairs_per_seed=4, full_rotation=False, noise_range_m=noise_m)
        return run_sparse_benchmark(opt)

    precise, noisy = run((0.3, 0.3)), run((3.0, 3.0))
    assert precise.summary()["4dof"]["search_ceiling"] > noisy.summary()["4dof"]["search_ceiling"]
    assert precise.summary()["4dof"]["localized"] > noisy.summary()["4dof"]["localized"]
    assert noisy.to_json()["conditions"]["noise_range_m"] == [3.0, 3.0]
    assert "centroid noise 3-3 m (specified: 0.5-2 m)" in sparse_markdown(noisy, (SEED,))
    assert "unlike the specification" not in sparse_markdown(run_sparse_benchmark(
        SparseOptions(seeds=(SEED,), pairs_per_seed=1, full_rotation=False)), (SEED,))


@pytest.mark.parametrize(
    "conditions",
    [{"miss_range": (0.6, 0.3)}, {"noise_range_m": (0.5, float("nan"))}, {"confusion_rate": 1.5},
     {"share_range_m": (5.0, 50.0)}],
)
def test_map_conditions_outside_their_bounds_are_config_errors(conditions):
    with pytest.raises(ConfigError, match="within"):
        SparseOptions(**conditions)


def test_seed_parsing():
    assert parse_seeds("10-12") == (10, 11, 12)
    assert parse_seeds("200,205") == (200, 205)
    with pytest.raises(ConfigError):
        parse_seeds("ten")


def test_the_truth_is_judged_as_a_hypothesis_would_be(world):
    """``judge_alignment``: the true alignment of an overlapping pair is far beyond chance; the same pair with B
    put 60 m along and turned 90 degrees is not (what the benchmark's search ceiling rests on)."""
    cfg = MatchingConfig().model_copy(update={"up_axis": UP_WORLD, "gravity_aligned": True})
    pair = make_pairs(world, SEED, SparseOptions(seeds=(SEED,), pairs_per_seed=1), 10.0)[0]
    truth = judge_alignment(pair.graph_a, pair.graph_b, pair.T_a_b, cfg)
    off = make_pose(rot_z(np.pi / 2), np.array([60.0, 0.0, 0.0])) @ pair.T_a_b
    wrong = judge_alignment(pair.graph_a, pair.graph_b, off, cfg)
    assert truth.llr > np.log(1 / cfg.false_alarm_rate) and truth.support >= 6
    assert wrong.llr < truth.llr - 10.0


def test_wrong_claims_name_the_farthest():
    """A wrong claim a few metres off (the right street placed imprecisely) reads differently from an alias."""

    def outcome(index, overlapping, success, err_m, sigma_m=float("nan")):
        margin = 1.0 if overlapping else float("nan")
        return SparseOutcome(seed=1, index=index, overlapping=overlapping, dof=4, nodes=(40, 50), common=15,
                             success=success, correct=success and err_m < 2.0, trans_err_m=err_m, rot_err_deg=1.0,
                             ms=5.0, cpu_ms=5.0, reason="", truth_margin_nats=margin, sigma_m=sigma_m)  # fmt: skip

    nan = float("nan")
    results = SparseResults([outcome(0, True, True, 0.4, 0.3), outcome(1, True, True, 3.8, 1.5),
                             outcome(2, True, True, 2.6, 1.4), outcome(3, True, False, nan),
                             outcome(4, False, False, nan)])  # fmt: skip
    s = results.summary()["4dof"]
    assert s["wrong_claims"] == 2 and s["worst_wrong_m"] == 3.8 and s["localized"] == 1
    assert s["median_error_m"] == 2.6  # of the three accepted overlapping pairs (0.4, 2.6, 3.8 m)
    assert "| 2 (<= 3.8 m) | 2.60 |" in sparse_markdown(results, (1,))
    # the precision each accepted match predicted: 0.4 and 2.6 m within twice theirs, 3.8 m not (2 of 3)
    assert s["within_2_sigma"] == pytest.approx(2 / 3)
    assert "(`centroid_sigma_m`): 4dof 67 %." in sparse_markdown(results, (1,)).replace("\n", " ")
    # each wrong claim named, farthest first, so that it can be looked at; accepted negatives after them
    results.outcomes.append(outcome(5, False, True, nan))
    assert ("the RMS error the match predicted there): 1/1 4dof 3.8 m (predicted 1.5 m), 1/2 4dof 2.6 m (predicted "
            "1.4 m), 1/5 4dof negative.") in sparse_markdown(results, (1,)).replace("\n", " ")
    clean = SparseResults([outcome(0, True, True, 0.4)])
    assert "Wrong claims and" not in sparse_markdown(clean, (1,))
    assert clean.summary()["4dof"]["worst_wrong_m"] is None and "| 0 | 0.40 |" in sparse_markdown(clean, (1,))
    none = SparseResults([outcome(0, True, False, nan)])
    assert none.summary()["4dof"]["median_error_m"] is None and "| 0 | - |" in sparse_markdown(none, (1,))


def test_the_report_breaks_the_pairs_down_by_shared_objects():
    """Where the misses lie: per bin of objects both maps hold, the overlapping pairs, those localized (negatives
    and wrong claims never count as localized; empty bins are left out) and the search ceiling (localized, or the
    truth beyond the threshold), which sums to the summary's."""

    def outcome(common, overlapping=True, success=True, correct=True, margin=-1.0):
        return SparseOutcome(seed=1, index=common, overlapping=overlapping, dof=4, nodes=(40, 50), common=common,
                             success=success, correct=correct, trans_err_m=0.5 if correct else 6.0, rot_err_deg=0.1,
                             ms=5.0, cpu_ms=5.0, reason="", truth_margin_nats=margin)  # fmt: skip

    results = SparseResults([outcome(12), outcome(14, success=False, correct=False, margin=0.5),
                             outcome(13, correct=False), outcome(22), outcome(29, success=False, correct=False),
                             outcome(41), outcome(60, overlapping=False, success=True, margin=3.0)])  # fmt: skip
    summary = results.summary()["4dof"]
    bins = summary["by_common"]
    assert bins == [{"common": "12-14", "pairs": 3, "localized": 1, "search_ceiling": 2},
                    {"common": "20-29", "pairs": 2, "localized": 1, "search_ceiling": 1},
                    {"common": "30+", "pairs": 1, "localized": 1, "search_ceiling": 1}]  # fmt: skip
    assert sum(b["search_ceiling"] for b in bins) == summary["search_ceiling"] == 4
    assert ("(overlapping pairs; the search ceiling in brackets): 4dof 12-14: 1 of 3 (2), 20-29: 1 of 2 (1), "
            "30+: 1 of 1 (1).") in sparse_markdown(results, (1,))  # fmt: skip
    assert SparseResults([outcome(60, overlapping=False)]).summary()["4dof"]["by_common"] == []
    assert SparseResults([outcome(9)]).summary()["4dof"]["by_common"] == [
        {"common": "<12", "pairs": 1, "localized": 1, "search_ceiling": 1}]


def test_a_ctrl_c_keeps_the_seeds_finished(monkeypatch):
    """An interrupted `bench sparse` wrote nothing of the seeds it had finished."""
    import shgm_slam.bench.localization_sparse as ls

    def fake_seed(seed, opt, dcfg, mcfg, gcfg, results, progress):
        results.outcomes.append(SparseOutcome(seed, 0, True, 4, (20, 20), 10, True, True, 0.1, 0.1, 5.0, 5.0, "", 9.0))
        if seed == 12:
            raise KeyboardInterrupt  # halfway through its pairs

    monkeypatch.setattr(ls, "_run_seed", fake_seed)
    res = run_sparse_benchmark(SparseOptions(seeds=(10, 11, 12, 13)))
    assert res.interrupted and res.seeds_done == [10, 11]
    assert [o.seed for o in res.outcomes] == [10, 11]  # not the seed it stopped in
    assert "interrupted" in sparse_markdown(res, (10, 11, 12, 13)) and res.to_json()["interrupted"]
    with pytest.raises(KeyboardInterrupt):  # nothing finished: nothing to keep
        run_sparse_benchmark(SparseOptions(seeds=(12,)))


@pytest.mark.xfail(strict=True, reason="open: an intersection's layout repeats one block along the street, which "
                   "the chance model does not measure (docs/benchmarks.md, Session of 2026-12-04, third)")
def test_an_alias_one_block_along_the_shared_street_is_refused():
    """Seed 988 pair 7 (run once, never tuned on): B's 32 nodes shifted one block (88 m) along the street both
    drove match A's next intersection beyond chance while the truth stays below it. When the verification
    refuses this alias (or places B right) this test passes, and strict xfail makes that visible."""
    from shgm_slam.config import DescriptorConfig, GraphConfig
    from shgm_slam.matching import match_graphs

    pair = make_pairs(build_city(CityParams(), seed=988), 988, SparseOptions(), GraphConfig().connectivity_m)[7]
    cfg = MatchingConfig().model_copy(update={"up_axis": UP_WORLD, "gravity_aligned": True})
    r = match_graphs(pair.graph_a, pair.graph_b, DescriptorConfig(), cfg)
    c = pair.graph_b.positions_xyz.mean(axis=0, keepdims=True)
    assert not r.success or np.linalg.norm(transform_points(r.T_a_b, c) - transform_points(pair.T_a_b, c)) < 2.0


@pytest.mark.parametrize(
    ("seed", "index", "noise_m"),
    [(1024, 1, (1.5, 2.5)), (1020, 14, None)],
    ids=["alias-146m-on-noisy-maps", "far-apart-negative"],
)
def test_wrong_alignments_a_second_fit_would_lift_stay_refused(seed, index, noise_m):
    """Seeds run once (2026-12-05): a near miss polished and judged again (a second look, tried and reverted) lifted
    these wrong alignments 4-5.5 nats over the threshold, an alias 146 m off and a far-apart pair; the matcher as it
    is refuses them (or places B right), in 4-DoF and 6-DoF."""
    from shgm_slam.bench.localization_sparse import rotate_fully
    from shgm_slam.config import DescriptorConfig, GraphConfig
    from shgm_slam.matching import match_graphs

    opt = SparseOptions() if noise_m is None else SparseOptions(noise_range_m=noise_m)
    pairs = make_pairs(build_city(CityParams(), seed=seed), seed, opt, GraphConfig().connectivity_m)
    rng = np.random.default_rng(seed + 5)  # the benchmark's 6-DoF draw
    turned = [rotate_fully(p, rng) for p in pairs]
    for pair, gravity in ((pairs[index], True), (turned[index], False)):
        cfg = MatchingConfig().model_copy(update={"up_axis": UP_WORLD, "gravity_aligned": gravity})
        r = match_graphs(pair.graph_a, pair.graph_b, DescriptorConfig(), cfg)
        if r.success:
            assert pair.overlapping, "a far-apart pair was accepted"
            c = pair.graph_b.positions_xyz.mean(axis=0, keepdims=True)
            assert np.linalg.norm(transform_points(r.T_a_b, c) - transform_points(pair.T_a_b, c)) < 2.0
