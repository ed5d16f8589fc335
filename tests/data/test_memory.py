"""Sequences held in memory (``data.memory.ArraySequence``): the same frames as a folder, checked."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from shgm_slam.data import SequenceWriter, open_sequence
from shgm_slam.data.base import SequenceView
from shgm_slam.data.memory import ArraySequence
from shgm_slam.errors import DataError
from shgm_slam.perception.perceive import depth_model_of
from shgm_slam.types import DepthOrigin, Intrinsics, Sequence
from tests.data.conftest import INTRINSICS, make_frames


def memory_of(frames, **kwargs) -> ArraySequence:
    """An ArraySequence of ``make_frames`` frames (stacked arrays)."""
    return ArraySequence(
        np.stack([f.image_rgb for f in frames]),
        INTRINSICS,
        np.array([f.timestamp_s for f in frames]),
        depth_m=np.stack([f.depth_m for f in frames]),
        label_ids=np.stack([f.label_ids for f in frames]),
        T_world_cam=np.stack([f.T_world_cam for f in frames]),
        **kwargs,
    )


def test_frames_in_memory_are_the_frames_a_folder_gives(tmp_path: Path) -> None:
    frames = make_frames(6)
    with SequenceWriter(tmp_path / "seq", INTRINSICS) as writer:
        for f in frames:
            writer.write(f)
    folder = open_sequence(tmp_path / "seq")
    loaded = [folder[i] for i in range(len(folder))]  # depth rounded to 1/256 m by the PNGs, as the run reads it
    memory = ArraySequence(
        [f.image_rgb for f in loaded], folder.intrinsics, folder.timestamps_s,
        depth_m=[f.depth_m for f in loaded], label_ids=[f.label_ids for f in loaded], T_world_cam=folder.gt_poses,
    )  # fmt: skip
    assert isinstance(memory, Sequence)
    assert len(memory) == len(folder) and memory.has_depth and memory.has_labels
    np.testing.assert_array_equal(memory.timestamps_s, folder.timestamps_s)
    for a, b in zip(memory, loaded, strict=True):
        assert (a.index, a.source_index, a.timestamp_s, a.intrinsics) == (b.index, b.source_index, b.timestamp_s,
                                                                           b.intrinsics)  # fmt: skip
        for field in ("image_rgb", "depth_m", "label_ids", "T_world_cam"):
            x, y = getattr(a, field), getattr(b, field)
            assert x.dtype == y.dtype and x.shape == y.shape, field
            np.testing.assert_array_equal(x, y, err_msg=field)
    assert depth_model_of(memory) is None  # measured depth: KISS-ICP, never rescaled


def test_invalid_depth_becomes_zero_and_grey_images_get_three_channels() -> None:
    frames = make_frames(3)  # depth holds NaN, inf and a negative value at (0, 0..2)
    grey = [f.image_rgb[:, :, 0] for f in frames]
    seq = ArraySequence(grey, INTRINSICS, [f.timestamp_s for f in frames], depth_m=[f.depth_m for f in frames])
    frame = seq[-1]
    assert frame.index == 2 and frame.label_ids is None and not seq.has_labels and seq.gt_poses is None
    assert frame.image_rgb.shape == (INTRINSICS.height, INTRINSICS.width, 3)
    np.testing.assert_array_equal(frame.image_rgb[:, :, 2], grey[2])
    assert frame.depth_m.dtype == np.float32 and np.isfinite(frame.depth_m).all() and (frame.depth_m >= 0).all()
    np.testing.assert_array_equal(frame.depth_m[0, :3], 0.0)
    kept = np.isfinite(frames[2].depth_m) & (frames[2].depth_m > 0)
    np.testing.assert_array_equal(frame.depth_m[kept], frames[2].depth_m[kept])
    assert grey[2].shape == (INTRINSICS.height, INTRINSICS.width)  # the caller's arrays are left as they were


def test_predicted_depth_is_said_so_and_a_view_keeps_it() -> None:
    from shgm_slam.data import SequenceView

    seq = memory_of(make_frames(4), depth_origin=DepthOrigin.PREDICTED, name="cam0")
    assert depth_model_of(seq) == {"path": "predicted depth of cam0"}
    assert depth_model_of(SequenceView(seq, 1, 3)) == {"path": "predicted depth of cam0"}


def test_frames_are_loaded_only_when_asked_for() -> None:
    frames = make_frames(5)
    asked: list[int] = []

    class Loader:
        def __len__(self) -> int:
            return len(frames)

        def __getitem__(self, i: int) -> np.ndarray:
            asked.append(i)
            return frames[i].image_rgb

    seq = ArraySequence(Loader(), INTRINSICS, [f.timestamp_s for f in frames])
    assert asked == []
    np.testing.assert_array_equal(seq[3].image_rgb, frames[3].image_rgb)
    assert asked == [3]


def test_it_pickles_for_worker_processes() -> None:
    seq = memory_of(make_frames(3))
    again = pickle.loads(pickle.dumps(seq))
    np.testing.assert_array_equal(again[1].depth_m, seq[1].depth_m)
    assert not again.timestamps_s.flags.writeable and not again.gt_poses.flags.writeable


def test_the_robots_own_odometry_rides_with_its_frames_through_views_and_pickles() -> None:
    frames = make_frames(4)
    own = np.stack([f.T_world_cam for f in frames])
    own[:, :3, 3] *= 0.5  # (not the ground truth)
    seq = ArraySequence(np.stack([f.image_rgb for f in frames]), INTRINSICS, np.arange(4) * 0.1 + 1000.0,
                        T_odom_cam=own)  # fmt: skip
    assert seq.gt_poses is None and not seq.odometry_poses.flags.writeable
    np.testing.assert_array_equal(seq[2].T_odom_cam, own[2])
    view = SequenceView(pickle.loads(pickle.dumps(seq)), 1, 3)
    np.testing.assert_array_equal(view.odometry_poses, own[1:3])
    np.testing.assert_array_equal(view[0].T_odom_cam, own[1])
    assert memory_of(frames).odometry_poses is None and memory_of(frames)[0].T_odom_cam is None


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda k: k.update(depth_m=k["depth_m"][:2]), "2 depth_m maps for 3 images"),
        (lambda k: k.update(label_ids=k["label_ids"][:1]), "1 label_ids maps for 3 images"),
        (lambda k: k.update(timestamps_s=k["timestamps_s"][:2]), "timestamps_s has shape (2,) for 3 images"),
        (lambda k: k.update(timestamps_s=k["timestamps_s"][::-1].copy()), "frame 1 (1000.1"),
        (lambda k: k.update(timestamps_s=k["timestamps_s"] * 1e3), "timestamps must be in seconds"),
        (lambda k: k["timestamps_s"].__setitem__(1, np.nan), "frame 1 holds nan"),
        (lambda k: k.update(T_world_cam=k["T_world_cam"][:, :3]), "T_world_cam has shape (3, 3, 4)"),
        (lambda k: k["T_world_cam"].__setitem__((2, 0, 0), 3.0), "T_world_cam of frame 2 is not a rigid"),
        (lambda k: k["T_world_cam"].__setitem__((1, 3, 3), np.inf), "T_world_cam of frame 1 is not finite"),
        (lambda k: k.update(T_odom_cam=k["T_world_cam"][:2]), "T_odom_cam has shape (2, 4, 4)"),
        (lambda k: k.update(T_odom_cam=k["T_world_cam"] * 2.0), "T_odom_cam of frame 0 is not a rigid"),
        (lambda k: k.update(images_rgb=[]), "has no images"),
        (lambda k: k.update(intrinsics=Intrinsics(0.0, 50.0, 10.0, 10.0, 32, 24)), "positive focal lengths"),
        (lambda k: k.update(intrinsics=(50.0, 50.0, 10.0, 10.0)), "must be an Intrinsics"),
        # what a calib.txt is refused for, in memory too (a LiveRun's cameras included): before, a principal point
        # a million pixels off the image, or a focal length in other units, ran and back-projected garbage
        (lambda k: k.update(intrinsics=Intrinsics(50.0, 50.0, 1e6, 10.0, 32, 24)), "principal point (1e"),
        (lambda k: k.update(intrinsics=Intrinsics(50.0, 50.0, 10.0, -3.0, 32, 24)), "lies outside the 32x24 image"),
        (lambda k: k.update(intrinsics=Intrinsics(50.0, 50.0, 10.0, np.nan, 32, 24)), "finite principal point"),
        (lambda k: k.update(intrinsics=Intrinsics(5e4, 5e4, 10.0, 10.0, 32, 24)), "degree field of view"),
        (lambda k: k.update(intrinsics=Intrinsics(50.0, 500.0, 10.0, 10.0, 32, 24)), "differ 10-fold"),
        # fields that are no numbers, or a size that is no whole number of pixels: a float width ran until numpy's
        # array constructors refused it deep inside the run (TypeError), its results folder left incomplete
        (lambda k: k.update(intrinsics=Intrinsics(50.0, 50.0, 10.0, 10.0, 32.5, 24)), "width 32.5 is not a whole"),
        (lambda k: k.update(intrinsics=Intrinsics("50", 50.0, 10.0, 10.0, 32, 24)), "intrinsics fx is str '50'"),
        (lambda k: k.update(intrinsics=Intrinsics(50.0, 50.0, 10.0, 10.0, 32, None)), "height is NoneType"),
        # ground truth in millimetres (a motion-capture system's) gave an ATE of 16 km without a word
        (lambda k: k["T_world_cam"][:, :3, 3].__imul__(1000.0), "T_world_cam moves at .*in millimetres"),
        # Python's ValueError and TypeError before
        (lambda k: k.update(depth_origin="network"), "depth_origin 'network' is none of 'measured', 'predicted'"),
        (lambda k: k.update(images_rgb=iter(k["images_rgb"])), "images_rgb (iterator) cannot be read by frame"),
        (lambda k: k.update(depth_m=(d for d in k["depth_m"])), "depth_m (generator) cannot be read by frame"),
        (lambda k: k.update(timestamps_s=[object()] * 3), "timestamps_s holds values that are not numbers"),
    ],
)
def test_what_cannot_be_a_sequence_is_refused_at_once(change, message: str) -> None:
    frames = make_frames(3)
    kwargs = {
        "images_rgb": np.stack([f.image_rgb for f in frames]), "intrinsics": INTRINSICS,
        "timestamps_s": np.array([1000.0, 1000.1, 1000.2]), "depth_m": np.stack([f.depth_m for f in frames]),
        "label_ids": np.stack([f.label_ids for f in frames]), "T_world_cam": np.stack([f.T_world_cam for f in frames]),
    }  # fmt: skip
    change(kwargs)
    with pytest.raises(DataError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ArraySequence(**kwargs)


def test_intrinsics_of_numpy_scalars_or_whole_floats_become_plain_numbers() -> None:
    """A camera driver's numpy scalars and a width of 32.0 are taken, as Python floats and ints (a float width
    reached numpy's array constructors inside the run); timestamps may come from a generator."""
    frames = make_frames(3)
    given = Intrinsics(np.float32(50.0), np.float64(52.0), np.float32(15.5), 11.25, 32.0, np.int64(24))
    seq = ArraySequence([f.image_rgb for f in frames], given, (f.timestamp_s for f in frames))
    assert seq.intrinsics == INTRINSICS
    fields = [getattr(seq.intrinsics, n) for n in ("fx", "fy", "cx", "cy", "width", "height")]
    assert [type(v) for v in fields] == [float] * 4 + [int] * 2
    assert seq[2].image_rgb.shape == (24, 32, 3) and len(seq) == 3


@pytest.mark.parametrize(
    ("field", "bad", "message"),
    [
        ("images_rgb", np.zeros((24, 32, 3), np.float32), "the image is float32"),
        ("images_rgb", np.zeros((24, 31, 3), np.uint8), "expected 24 x 32"),
        ("images_rgb", np.zeros((24, 32, 4), np.uint8), r"give \(H, W, 3\) uint8 RGB"),
        ("depth_m", np.zeros((24, 32), np.uint16), r"depth_m is uint16 .*millimetres.*depth / 1000\.0"),
        ("depth_m", np.zeros((12, 32), np.float32), "depth_m has shape"),
        ("label_ids", np.zeros((24, 32), np.float32), "label_ids is float32"),
        ("label_ids", np.full((24, 32), 300, np.int32), "outside 0-255"),
    ],
)
def test_a_bad_frame_is_refused_when_read_naming_the_frame(field: str, bad: np.ndarray, message: str) -> None:
    frames = make_frames(3)
    arrays = {
        "images_rgb": [f.image_rgb for f in frames], "depth_m": [f.depth_m for f in frames],
        "label_ids": [f.label_ids for f in frames],
    }  # fmt: skip
    arrays[field][1] = bad
    seq = ArraySequence(arrays.pop("images_rgb"), INTRINSICS, [f.timestamp_s for f in frames], **arrays, name="cam")
    seq[0]  # the others are fine
    with pytest.raises(DataError, match="sequence 'cam' frame 1: .*" + message):
        seq[1]
    with pytest.raises(IndexError):
        seq[3]


def test_a_pose_slightly_off_a_rotation_is_made_one() -> None:
    """Poses within the tolerance but 1e-3 off orthonormal (rounding, a float32 pipeline) were kept as given, and
    a robot's own odometry so given ended the run where the first keyframe was encoded (the wire takes 1e-5); they
    are re-orthonormalized as a poses file's rows are."""
    frames = make_frames(3)
    own = np.stack([f.T_world_cam for f in frames])
    own[:, :3, 3] *= 0.01
    own[:, :3, :3] = own[:, :3, :3] @ (np.eye(3) + np.diag([1e-3, 0.0, 0.0]))
    seq = ArraySequence(np.stack([f.image_rgb for f in frames]), INTRINSICS, np.arange(3) * 0.1, T_odom_cam=own)
    R = seq[1].T_odom_cam[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R, own[1, :3, :3], atol=2e-3)  # the nearest rotation
    np.testing.assert_array_equal(seq[1].T_odom_cam[:3, 3], own[1, :3, 3])


def test_odometry_not_in_metres_is_refused_at_once() -> None:
    """Odometry in millimetres cut every step as an odometry failure (10 km/s) until the robot had used its share
    of the pose graph; it is refused when the sequence is made, naming the fix."""
    frames = make_frames(4)
    own = np.tile(np.eye(4), (4, 1, 1))
    own[:, 0, 3] = np.arange(4) * 1.5  # 15 m/s
    images, times = np.stack([f.image_rgb for f in frames]), np.arange(4) * 0.1
    ArraySequence(images, INTRINSICS, times, T_odom_cam=own)
    own[:, :3, 3] *= 1000.0
    with pytest.raises(DataError, match=r"sequence 'in memory': T_odom_cam moves at 1.5e\+04 m/s .*in millimetres"):
        ArraySequence(images, INTRINSICS, times, T_odom_cam=own)


def test_frames_in_memory_slice_like_a_folder() -> None:
    seq = memory_of(make_frames(6))
    view = seq[1:4]
    assert isinstance(view, SequenceView) and len(view) == 3
    assert [f.source_index for f in view] == [1, 2, 3] and view[0].index == 0
    np.testing.assert_array_equal(view.timestamps_s, seq.timestamps_s[1:4])
