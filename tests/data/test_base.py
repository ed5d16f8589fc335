"""Sequence specs, layout detection, the reader registry and frame-range views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shgm_slam.data import (
    SEQUENCE_READERS,
    KittiSequence,
    SequenceLayout,
    SequenceView,
    ShgmSequence,
    detect_layout,
    open_sequence,
    parse_sequence_spec,
)
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.types import Frame, Sequence


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("data/08", (Path("data/08"), 0, None)),
        ("data/08:0-1500", (Path("data/08"), 0, 1500)),
        ("data/08:100-", (Path("data/08"), 100, None)),
        ("data/08:-500", (Path("data/08"), 0, 500)),
        ("data/08:-", (Path("data/08"), 0, None)),
        (Path("data/08:1-2"), (Path("data/08:1-2"), 0, None)),
    ],
)
def test_parse_sequence_spec(spec, expected) -> None:
    assert parse_sequence_spec(spec) == expected


@pytest.mark.parametrize("spec", ["data/08:5-5", "data/08:9-3", "data/08:abc", "data/08:1-2-3", ":0-5"])
def test_bad_specs_are_data_errors(spec: str) -> None:
    with pytest.raises(DataError, match=f"sequence spec '{spec}'"):
        parse_sequence_spec(spec)


def test_existing_folder_with_colon_is_a_path(tmp_path: Path) -> None:
    folder = tmp_path / "run:a"
    folder.mkdir()
    assert parse_sequence_spec(str(folder)) == (folder, 0, None)


def test_registry_and_detection(seq_dir: Path) -> None:
    assert SEQUENCE_READERS == {SequenceLayout.KITTI: KittiSequence, SequenceLayout.SHGM: ShgmSequence}
    assert detect_layout(seq_dir) is SequenceLayout.SHGM
    assert type(open_sequence(seq_dir)) is ShgmSequence
    assert type(open_sequence(seq_dir, SequenceLayout.KITTI)) is KittiSequence


def test_frame_range_view(seq_dir: Path, frames: list[Frame]) -> None:
    full = open_sequence(seq_dir)
    view = open_sequence(f"{seq_dir}:2-6")
    assert isinstance(view, SequenceView) and isinstance(view, Sequence)
    assert len(view) == 4 and view.name == "seq:2-6"
    assert view.has_depth and view.has_labels and view.intrinsics == full.intrinsics
    np.testing.assert_array_equal(view.timestamps_s, full.timestamps_s[2:6])
    np.testing.assert_array_equal(view.gt_poses, full.gt_poses[2:6])
    got = list(view)
    assert [f.index for f in got] == [0, 1, 2, 3]
    assert [f.source_index for f in got] == [2, 3, 4, 5]
    np.testing.assert_array_equal(got[0].image_rgb, frames[2].image_rgb)
    np.testing.assert_array_equal(view[-1].T_world_cam, full.gt_poses[5])
    with pytest.raises(IndexError):
        view[4]


def test_open_ended_ranges(seq_dir: Path) -> None:
    assert [f.source_index for f in open_sequence(f"{seq_dir}:5-")] == [5, 6, 7]
    assert len(open_sequence(f"{seq_dir}:-3")) == 3
    assert type(open_sequence(f"{seq_dir}:0-")) is ShgmSequence


@pytest.mark.parametrize("rng", ["8-", "3-9", "100-200"])
def test_ranges_beyond_the_sequence(seq_dir: Path, rng: str) -> None:
    with pytest.raises(DataError, match="does not fit seq with 8 frames"):
        open_sequence(f"{seq_dir}:{rng}")


def test_a_layout_by_name_is_taken_and_what_is_none_refused(seq_dir: Path) -> None:
    """A layout named in capitals was a KeyError of the reader registry, a spec that is no path an AttributeError."""
    assert type(open_sequence(seq_dir, "KITTI")) is KittiSequence
    with pytest.raises(ConfigError, match="sequence layout 'euroc' is none of 'kitti', 'shgm'"):
        open_sequence(seq_dir, "euroc")
    with pytest.raises(DataError, match="sequence spec 8 is no path"):
        open_sequence(8)


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="nowhere"):
        open_sequence(tmp_path / "nowhere")
    with pytest.raises(DataError, match="nowhere"):
        open_sequence(f"{tmp_path / 'nowhere'}:0-5")


def test_indexing_protocol(seq_dir: Path) -> None:
    seq = open_sequence(seq_dir)
    assert seq[-1].index == 7
    with pytest.raises(IndexError):
        seq[8]
    assert seq.timestamps_s.flags.writeable is False


def test_a_slice_of_a_sequence_is_the_view_its_frame_range_gives(seq_dir: Path) -> None:
    full = open_sequence(seq_dir)
    view = full[2:6]
    assert isinstance(view, SequenceView) and view.name == "seq:2-6"
    assert [f.source_index for f in view] == [f.source_index for f in open_sequence(f"{seq_dir}:2-6")]
    assert [f.index for f in view] == [0, 1, 2, 3]
    np.testing.assert_array_equal(view.gt_poses, full.gt_poses[2:6])
    assert [f.source_index for f in full[-3:]] == [5, 6, 7]  # Python's rules: from the end, clipped
    assert len(full[:100]) == len(full)
    inner = view[1:3]  # a view of a view is a range of the same folder, not a chain
    assert inner.base is full and inner.name == "seq:3-5"
    assert [f.source_index for f in inner] == [3, 4]


@pytest.mark.parametrize(("key", "message"), [(slice(0, 6, 2), "consecutive frames"), (slice(5, 2), "no frame")])
def test_slices_that_take_no_run_are_refused(seq_dir: Path, key: slice, message: str) -> None:
    with pytest.raises(DataError, match=message):
        open_sequence(seq_dir)[key]
    with pytest.raises(DataError, match=message):
        open_sequence(f"{seq_dir}:1-7")[key]
