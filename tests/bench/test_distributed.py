"""The distributed benchmark's own parts: recovery timing side by side, and the tables it prints."""

from __future__ import annotations

from shgm_slam.bench.distributed import distributed_markdown, time_recovery
from tests.server.conftest import cfg, robots  # noqa: F401  (fixtures half_run needs)
from tests.server.test_snapshot import half_run, with_snapshots  # noqa: F401


def test_recovery_is_timed_from_snapshots_and_from_the_journal_alone(half_run, cfg) -> None:  # noqa: F811
    out, first, *_ = half_run
    t = time_recovery(out, with_snapshots(cfg, 1), "car1", "half")
    assert t.journal_records == first.journal.records
    assert t.snapshot_records == first.journal.records and t.replayed == 0
    assert 0 < t.snapshot_s and 0 < t.journal_only_s and t.snapshot_bytes > 0


def test_markdown_has_the_readme_tables() -> None:
    traffic = {"bytes_per_keyframe": 900.0, "messages_by_kind": {"keyframe": 10},
               "bytes_sent_by_kind": {"correction": 5000, "status": 300}}  # fmt: skip
    result = {
        "runs": [
            {"label": "run", "placed": {"a": True, "b": False}, "ate_fused_m": {"a": 1.234, "b": float("nan")},
             "wall_s": 10.0, "traffic": {}, "error": ""},
            {"label": "server + 2 robot processes", "placed": {"a": True, "b": True},
             "ate_fused_m": {"a": 1.0, "b": 2.0}, "wall_s": 12.0, "error": "", "traffic": traffic,
             "kb_per_s_per_robot_at_10hz": {"a": 3.61, "b": 4.0}, "kb_per_s_down_per_robot_at_10hz": {"a": 0.5}},
            {"label": "broken", "placed": {}, "ate_fused_m": {}, "wall_s": float("nan"), "traffic": {},
             "error": "the server exited early (2)"},
        ],
        "recovery": [{"label": "at the kill", "journal_records": 300, "snapshot_records": 200, "replayed": 100,
                      "snapshot_s": 2.0, "journal_only_s": 10.0, "snapshot_bytes": 1_234_000}],
    }  # fmt: skip
    md = distributed_markdown(result)
    assert "| run | yes / 1.23 | no / nan | 10 |" in md
    assert "| server + 2 robot processes | 900 | 10 | a 3.6, b 4.0 | a 0.50 | 5 + 0 |" in md
    assert "failed: the server exited early (2)" in md
    assert "| at the kill | 300 | 200 | 100 | 1.23 | 2.0 | 10.0 | 5.0x |" in md
