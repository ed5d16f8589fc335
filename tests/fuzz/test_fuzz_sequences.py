"""Corrupted sequences (bad or truncated PNGs, wrong sizes and dtypes, NaN depth, broken text files):
opening, probing and reading every frame gives frames or ``ShgmError``s, never another exception."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from shgm_slam.data import open_sequence
from shgm_slam.data.validate import check_sequence_start
from shgm_slam.errors import ShgmError
from tests.data.conftest import make_frames, write_frames
from tests.fuzz.conftest import fuzz_settings, scratch

N_FRAMES = 6
FOLDERS = ("image_2", "depth", "semantic")


@pytest.fixture(scope="module")
def clean_sequence(tmp_path_factory) -> Path:
    return write_frames(tmp_path_factory.mktemp("fuzz_seq") / "seq", make_frames(N_FRAMES))


def _png_bytes(rng: np.random.Generator, kind: str) -> bytes:
    shapes = {"tiny": (3, 2), "wide": (24, 64), "right": (24, 32)}
    h, w = shapes[rng.choice(list(shapes))]
    dtype = {"u8": np.uint8, "u16": np.uint16}[kind]
    channels = int(rng.choice([1, 3, 4]))
    array = rng.integers(0, np.iinfo(dtype).max, (h, w, channels) if channels > 1 else (h, w), dtype=dtype)
    ok, buf = cv2.imencode(".png", array)
    assert ok
    return buf.tobytes()


CORRUPTIONS = ("garbage", "truncate", "empty", "delete", "png_u8", "png_u16", "rename")
TEXT_CORRUPTIONS = ("times_garbage", "times_short", "times_nan", "poses_garbage", "poses_short", "calib_binary")


def _corrupt(root: Path, kind: str, folder: str, index: int, rng: np.random.Generator) -> None:
    path = root / folder / f"{index:06d}.png"
    if kind == "garbage":
        path.write_bytes(rng.bytes(int(rng.integers(1, 200))))
    elif kind == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: int(rng.integers(0, max(len(data), 1)))])
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "delete":
        path.unlink()
    elif kind in ("png_u8", "png_u16"):
        path.write_bytes(_png_bytes(rng, kind[4:]))
    elif kind == "rename":
        path.rename(path.with_name(f"{index + 100:06d}.png"))
    elif kind == "times_garbage":
        (root / "times.txt").write_text("0.0\nabc\n" * 3)
    elif kind == "times_short":
        (root / "times.txt").write_text("0.0\n0.1\n")
    elif kind == "times_nan":
        (root / "times.txt").write_text("".join(f"{v}\n" for v in ["nan", "0.1", "inf", "0.3", "0.4", "-1"]))
    elif kind == "poses_garbage":
        (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 x\n" * N_FRAMES)
    elif kind == "poses_short":
        (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    elif kind == "calib_binary":
        (root / "calib.txt").write_bytes(rng.bytes(64))


def _read_everything(root: Path) -> None:
    """Open, probe and read every frame the way ``run`` does; only ShgmErrors may come out."""
    try:
        seq = open_sequence(root)
    except ShgmError:
        return
    try:
        check_sequence_start("fuzz", seq, lambda f: (f.depth_m, f.label_ids))
    except ShgmError:
        pass
    for i in range(len(seq)):
        try:
            frame = seq[i]
        except ShgmError:
            continue  # the run skips such a frame with the reason
        assert frame.image_rgb is not None and frame.image_rgb.dtype == np.uint8
        h, w = frame.image_rgb.shape[:2]
        assert frame.depth_m is None or (frame.depth_m.shape == (h, w) and frame.depth_m.dtype == np.float32)
        assert frame.label_ids is None or frame.label_ids.shape == (h, w)


@fuzz_settings(100)
@given(
    corruptions=st.lists(
        st.tuples(st.sampled_from(CORRUPTIONS), st.sampled_from(FOLDERS), st.integers(0, N_FRAMES - 1)),
        min_size=1, max_size=N_FRAMES * 2,
    ),
    text=st.lists(st.sampled_from(TEXT_CORRUPTIONS), max_size=2),
    seed=st.integers(0, 2**16),
)
def test_corrupted_sequences_give_frames_or_shgm_errors(clean_sequence, corruptions, text, seed):
    rng = np.random.default_rng(seed)
    with scratch() as d:
        root = d / "seq"
        shutil.copytree(clean_sequence, root)
        for kind, folder, index in corruptions:
            if (root / folder / f"{index:06d}.png").exists():
                _corrupt(root, kind, folder, index, rng)
        for kind in text:
            _corrupt(root, kind, "", 0, rng)
        _read_everything(root)


@fuzz_settings(50)
@given(
    fill=st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -1.0, 1e30]),
    fraction=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**16),
)
def test_nan_or_invalid_model_depth_is_a_clean_error_or_accepted(clean_sequence, fill, fraction, seed):
    """Depth as a model might give it (NaN, inf, negative, absurd): the probe accepts it or raises ModelError."""
    rng = np.random.default_rng(seed)
    seq = open_sequence(clean_sequence)

    def perceive(frame):
        depth = frame.depth_m.copy()
        depth[rng.random(depth.shape) < fraction] = fill
        return depth, frame.label_ids

    try:
        check_sequence_start("fuzz", seq, perceive, depth_model="fuzz.onnx")
    except ShgmError as exc:
        assert "fuzz.onnx" in str(exc) or "fuzz" in str(exc)
