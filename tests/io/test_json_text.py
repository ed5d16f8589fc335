"""Every JSON file and ``--json`` output is strict JSON: NaN and infinity are written as null."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.bench.report import write_report
from shgm_slam.io.json_text import to_json_text


def strict_loads(text: str) -> object:
    def refuse(token: str) -> object:
        raise AssertionError(f"{token} is not JSON")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_become_null() -> None:
    data = {"ate_m": float("nan"), "max": np.float32("inf"), "xs": np.array([1.0, np.nan]), "p": Path("a/b"),
            "n": np.int64(3), "rows": [(float("-inf"), 2.5)]}  # fmt: skip
    for text in (to_json_text(data), to_json_text(data, indent=None), to_json_text(data, compact=True)):
        assert strict_loads(text) == {"ate_m": None, "max": None, "xs": [1.0, None], "p": "a/b", "n": 3,
                                      "rows": [[None, 2.5]]}  # fmt: skip


def test_unknown_objects_are_refused() -> None:
    with pytest.raises(TypeError, match="object"):
        to_json_text({"x": object()})


def test_bench_reports_are_strict_json(tmp_path: Path) -> None:
    """A benchmark whose robot was not placed (ATE NaN) still writes a JSON file every parser reads."""
    results = {"runs": [{"robot": "uav", "placed": False, "ate_fused_m": float("nan"), "wall_s": np.float64(3.0)}]}
    write_report(tmp_path, "system", results, lambda r: "table\n")
    assert strict_loads((tmp_path / "system.json").read_text())["runs"][0] == {
        "robot": "uav", "placed": False, "ate_fused_m": None, "wall_s": 3.0}


def test_no_json_written_around_the_strict_writer() -> None:
    """Files and stdout get JSON only through ``to_json_text`` (``json.dumps`` writes bare NaN)."""
    root = Path(__file__).resolve().parents[2] / "shgm_slam"
    offenders = [
        f"{path.relative_to(root)}:{n}"
        for path in root.rglob("*.py") if path.name != "json_text.py"
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if re.search(r"(write_text|echo|print|_write_text_atomic)\(.*json\.dumps\(|json\.dump\(", line)
    ]  # fmt: skip
    assert not offenders
