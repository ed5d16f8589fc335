"""The ``run`` command on corrupted sequences: exit 2 with one line, or exit 0 with every skip reported."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st
from typer.testing import CliRunner

from shgm_slam.cli import app
from tests.data.conftest import make_frames, write_frames
from tests.fuzz.conftest import fuzz_settings, scratch
from tests.fuzz.test_fuzz_sequences import CORRUPTIONS, FOLDERS, N_FRAMES, _corrupt


@pytest.fixture(scope="module")
def clean_sequence(tmp_path_factory) -> Path:
    return write_frames(tmp_path_factory.mktemp("fuzz_run") / "seq", make_frames(N_FRAMES))


@fuzz_settings(20)
@given(
    corruptions=st.lists(
        st.tuples(st.sampled_from(CORRUPTIONS), st.sampled_from(FOLDERS), st.integers(0, N_FRAMES - 1)),
        min_size=1, max_size=4,
    ),
    seed=st.integers(0, 2**16),
)
def test_run_on_a_corrupted_sequence_exits_cleanly(clean_sequence, corruptions, seed):
    rng = np.random.default_rng(seed)
    with scratch() as d:
        root = d / "seq"
        shutil.copytree(clean_sequence, root)
        for kind, folder, index in corruptions:
            if (root / folder / f"{index:06d}.png").exists():
                _corrupt(root, kind, folder, index, rng)
        res = CliRunner().invoke(app, ["run", "--robot", f"car={root}", "--rerun", "off", "--out", str(d / "out")])
        assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
        assert res.exit_code in (0, 2), res.output
        event(f"exit {res.exit_code}")
        if res.exit_code == 2:
            assert "error:" in res.output
            return
        metrics = json.loads((d / "out" / "metrics.json").read_text())
        (robot,) = metrics["robots"]
        assert robot["frames_processed"] + robot["frames_skipped"] == robot["frames"]
        assert len(metrics["skipped"]) == robot["frames_skipped"]
        if robot["frames_skipped"]:
            assert "frame(s) skipped" in " ".join(res.output.split())
