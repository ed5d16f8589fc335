"""``perceive``: the networks run once over a sequence, written as a sequence that reads back.

Uses the committed demo models (skips without them) on a small simulated sequence and, when present,
on the real KITTI frames in ../shared/data/kitti.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.data import ShgmSequence, open_sequence
from shgm_slam.data.kitti import frame_file
from shgm_slam.errors import ConfigError, DataError, ModelError
from shgm_slam.perception import DepthModel, SegmentationModel
from shgm_slam.perception.perceive import MANIFEST, ImageMode, depth_model_of, perceive

MODELS = Path(__file__).resolve().parents[2] / "models"
DEPTH_ONNX, SEG_ONNX = MODELS / "demo_depth.onnx", MODELS / "demo_seg.onnx"


@pytest.fixture(scope="module")
def models() -> dict[str, Path]:
    if not (DEPTH_ONNX.is_file() and SEG_ONNX.is_file()):
        pytest.skip("demo models are absent (train them with tools/train_demo_models.py)")
    return {"depth_model": DEPTH_ONNX, "seg_model": SEG_ONNX}


@pytest.fixture(scope="module")
def sim_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """car1 of a compact airsim-like world: 10 frames at 320x96 with depth, labels and poses."""
    from shgm_slam.sim.simulate import simulate

    out = tmp_path_factory.mktemp("perceive_sim")
    simulate("airsim-like", out, resolution=(320, 96), fps=4.0, compact=True, max_frames=10)
    return out / "car1"


def _run(spec, out, models, **kwargs):
    return perceive(spec, out, threads=1, **models, **kwargs)


def test_outputs_round_trip_through_the_sequence_reader(sim_seq, models, tmp_path):
    out = tmp_path / "p"
    result = _run(f"{sim_seq}:2-9", out, models, batch_size=3)
    assert result.complete and (result.frames, result.computed, result.reused) == (7, 7, 0)
    assert set(result.providers) == {"depth", "segmentation"}
    seq = open_sequence(out)
    src = open_sequence(f"{sim_seq}:2-9")
    assert isinstance(seq, ShgmSequence) and len(seq) == 7 and seq.has_depth and seq.has_labels
    assert seq.intrinsics == src.intrinsics
    np.testing.assert_allclose(seq.gt_poses, src.gt_poses, atol=1e-9)
    np.testing.assert_allclose(seq.timestamps_s, src.timestamps_s, atol=1e-9)
    depth_model, seg_model = DepthModel(DEPTH_ONNX, threads=1), SegmentationModel(SEG_ONNX, threads=1)
    for i in (0, 4, 6):
        frame, source = seq[i], src[i]
        np.testing.assert_array_equal(frame.image_rgb, source.image_rgb)
        np.testing.assert_allclose(frame.depth_m, depth_model.predict(source.image_rgb), atol=1 / 256 + 1e-6)
        np.testing.assert_array_equal(frame.label_ids, seg_model.predict(source.image_rgb))
    assert (out / "image_2" / "000000.png").is_symlink()
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["complete"] and (manifest["start"], manifest["end"]) == (2, 9)
    # the depth model's input size for these images (the visual odometry's corner-depth window grows from it)
    wh = (src.intrinsics.width, src.intrinsics.height)
    assert manifest["depth_model"]["input_wh"] == list(depth_model.target_size(wh))
    assert depth_model_of(seq) == manifest["depth_model"]  # a run treats this depth as predicted


def test_resume_skips_done_frames_and_redoes_missing_or_partial_ones(sim_seq, models, tmp_path):
    out = tmp_path / "p"
    _run(sim_seq, out, models, images=ImageMode.COPY)
    again = _run(sim_seq, out, models)
    assert (again.computed, again.reused) == (0, 10)
    good = (out / "depth" / "000003.png").read_bytes()
    (out / "depth" / "000003.png").write_bytes(good[: len(good) // 2])  # a half-written file
    (out / "semantic" / "000007.png").unlink()
    (out / "depth" / ".000005.png.123.part").write_bytes(b"junk")  # a temp file of a killed run
    labels = out / "semantic" / "000002.png"
    right = labels.read_bytes()
    shape = cv2.imread(str(labels), cv2.IMREAD_UNCHANGED).shape
    cv2.imwrite(str(labels), np.full(shape, 200, np.uint8))  # no train id: was reused as it was
    resumed = _run(sim_seq, out, models)
    assert (resumed.computed, resumed.reused) == (3, 7)
    assert labels.read_bytes() == right
    assert (out / "depth" / "000003.png").read_bytes() == good
    assert not list((out / "depth").glob("*.part"))
    assert len(open_sequence(out)) == 10 and open_sequence(out)[7].label_ids is not None


def test_interrupted_run_keeps_whole_files_and_finishes_on_the_next_run(sim_seq, models, tmp_path):
    out = tmp_path / "p"

    def stop_after_first_batch(done: int, total: int) -> None:
        if done >= 4:
            raise KeyboardInterrupt

    first = _run(sim_seq, out, models, batch_size=4, progress=stop_after_first_batch)
    assert first.interrupted and not first.complete and first.computed in (4, 8)  # + the batch being written
    assert len(list((out / "depth").glob("*.png"))) == len(list((out / "semantic").glob("*.png"))) == first.computed
    assert not json.loads((out / MANIFEST).read_text())["complete"]
    with pytest.raises(DataError, match=r"unfinished `shgm-slam perceive` output .* run the same perceive command"):
        open_sequence(out)  # an unfinished folder is not mistaken for a shorter sequence
    second = _run(sim_seq, out, models, batch_size=4)
    assert second.complete and (second.computed, second.reused) == (10 - first.computed, first.computed)
    assert len(open_sequence(out)) == 10


def test_an_unreadable_image_is_a_skip_that_the_next_run_redoes(sim_seq, models, tmp_path):
    import shutil

    src = tmp_path / "src"
    shutil.copytree(sim_seq, src)
    image = next(src / d / "000004.png" for d in ("image_2", "image_0") if (src / d).is_dir())
    good = image.read_bytes()
    image.write_bytes(good[:100])  # a truncated PNG
    out = tmp_path / "p"
    first = _run(src, out, models, batch_size=4)
    assert first.complete and set(first.unreadable) == {4} and "000004.png" in first.unreadable[4]
    assert json.loads((out / MANIFEST).read_text())["unreadable"] == [4]
    seq = open_sequence(out)  # every frame has its outputs: the folder reads
    assert len(seq) == 10 and seq[3].depth_m.max() > 0
    blank = ShgmSequence(out)._read_single_channel(out / "depth", 4, np.uint16, "depth")
    assert not blank.any()  # no valid depth for the unreadable frame
    with pytest.raises(DataError, match="cannot read image"):
        seq[4]  # `run` skips the frame as it skips any unreadable image
    image.write_bytes(good)  # the file re-exported
    second = _run(src, out, models, batch_size=4)
    assert second.complete and not second.unreadable and (second.computed, second.reused) == (1, 9)
    assert "unreadable" not in json.loads((out / MANIFEST).read_text())
    assert open_sequence(out)[4].depth_m.max() > 0


def test_one_model_writes_one_modality(sim_seq, models, tmp_path):
    result = _run(f"{sim_seq}:0-3", tmp_path / "d", {"depth_model": models["depth_model"]})
    seq = open_sequence(tmp_path / "d")
    assert result.complete and seq.has_depth and not seq.has_labels


def test_clear_errors(sim_seq, models, tmp_path):
    with pytest.raises(ConfigError, match="--depth-model and/or --seg-model"):
        perceive(sim_seq, tmp_path / "a")
    with pytest.raises(ModelError, match="does not exist"):
        perceive(sim_seq, tmp_path / "a", depth_model=tmp_path / "missing.onnx")
    with pytest.raises(ConfigError, match="batch-size"):
        _run(sim_seq, tmp_path / "a", models, batch_size=0)
    with pytest.raises(DataError, match="the source sequence itself"):
        _run(sim_seq, sim_seq, models)
    with pytest.raises(DataError, match="frame range"):
        _run(f"{sim_seq}:5-50", tmp_path / "a", models)
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(DataError, match="not written by perceive"):
        _run(sim_seq, other, models)
    _run(f"{sim_seq}:0-2", tmp_path / "b", models)
    with pytest.raises(DataError, match="end changed"):
        _run(f"{sim_seq}:0-3", tmp_path / "b", models)
    assert _run(f"{sim_seq}:0-3", tmp_path / "b", models, overwrite=True).computed == 3
    # a manifest that is JSON but no object (was an AttributeError), or no JSON (was "another source")
    for text in ("[]", "7", "[" * 100_000, "{bad", ""):
        (tmp_path / "b" / "perceive.json").write_text(text)
        with pytest.raises(DataError, match=r"perceive\.json is unreadable .* pass --overwrite"):
            _run(f"{sim_seq}:0-3", tmp_path / "b", models)
    assert _run(f"{sim_seq}:0-3", tmp_path / "b", models, overwrite=True).computed == 3


_HOLD = """
import sys
from pathlib import Path
from shgm_slam.io.export import _lock_results_dir
_lock_results_dir(Path(sys.argv[1]))  # as a perceive job writing the folder holds it
print("held", flush=True)
sys.stdin.read()
"""


def test_a_folder_another_job_writes_is_refused_and_kept(sim_seq, models, tmp_path):
    """Two perceive jobs on one --out (the second with --overwrite and another model) removed each other's
    depth/ mid-run ("cannot write ...: No such file or directory; free space ...") or left PNGs of two models under
    one manifest; the second is now refused, nothing of the first touched. A job refused before writing (a missing
    model) leaves no empty folder behind."""
    import subprocess
    import sys

    out = tmp_path / "p"
    _run(f"{sim_seq}:0-2", out, models)
    before = {f: f.read_bytes() for f in sorted((out / "depth").iterdir())}
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True)  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(DataError, match=rf"in use by another shgm-slam process \(pid {holder.pid}\)"):
            _run(f"{sim_seq}:0-3", out, models, overwrite=True)
        assert {f: f.read_bytes() for f in sorted((out / "depth").iterdir())} == before
    finally:
        holder.communicate("")
    assert _run(f"{sim_seq}:0-2", out, models).reused == 2  # the lock went with its holder
    assert not (out / ".shgm-slam.lock").exists()
    with pytest.raises(ModelError, match="does not exist"):
        perceive(sim_seq, tmp_path / "new", depth_model=tmp_path / "missing.onnx")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("fails", ["mkdir", "symlink", "write_bytes"])
def test_an_unwritable_or_full_out_is_one_clear_error(sim_seq, models, tmp_path, monkeypatch, fails):
    """A read-only --out (as a user without root meets it) or a full disk while the folder is laid out:
    one DataError naming the file, no traceback."""
    import errno
    import os

    code = errno.ENOSPC if fails == "write_bytes" else errno.EACCES

    def refuse(*args, **kwargs):
        raise OSError(code, os.strerror(code), str(args[0]))

    target = {"mkdir": (Path, "mkdir"), "symlink": (os, "symlink"), "write_bytes": (Path, "write_bytes")}[fails]
    monkeypatch.setattr(*target, refuse)
    with pytest.raises(DataError, match=r"cannot write .*; "):
        _run(f"{sim_seq}:0-3", tmp_path / "p", models)


def test_cli_perceive_then_reads_as_a_robot(sim_seq, models, tmp_path):
    out = tmp_path / "p"
    args = ["perceive", f"{sim_seq}:0-4", "--out", str(out), "--depth-model", str(DEPTH_ONNX),
            "--seg-model", str(SEG_ONNX), "--threads", "1", "--batch-size", "2"]  # fmt: skip
    res = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "4 frame(s) computed" in " ".join(res.output.split())
    assert len(open_sequence(out)) == 4  # what `run --robot car1=OUT` opens
    res = CliRunner().invoke(app, [*args[:4], "--depth-model", str(tmp_path / "none.onnx")])
    assert res.exit_code == 2 and "does not exist" in " ".join(res.output.split())
    res = CliRunner().invoke(app, [*args, "--provider", "gpu"])
    assert res.exit_code == 2 and "choose auto, cpu or cuda" in " ".join(res.output.split())


def test_real_kitti_frames(shared_data, models, tmp_path):
    spec = f"{shared_data / 'kitti' / 'sequences' / '07'}:5-15"
    result = _run(spec, tmp_path / "k", models, batch_size=4)
    assert result.complete and result.computed == 10
    seq, src = open_sequence(tmp_path / "k"), open_sequence(spec)
    assert len(seq) == 10 and seq.intrinsics == src.intrinsics
    np.testing.assert_allclose(seq.gt_poses, src.gt_poses, atol=1e-8)  # same camera, no double offset
    frame = seq[3]
    np.testing.assert_array_equal(frame.image_rgb, src[3].image_rgb)
    assert frame.depth_m.shape == frame.label_ids.shape == frame.image_rgb.shape[:2]
    assert (frame.depth_m > 0).mean() > 0.5
    assert frame_file(tmp_path / "k" / "image_0", 0).resolve() == frame_file(
        shared_data / "kitti" / "sequences" / "07" / "image_0", 5
    ).resolve()


def test_cli_stopped_by_sigterm_resumes(shared_data, models, tmp_path):
    """A real stop mid-run (SIGTERM, as Ctrl-C): exit 130 with a resume hint, then the rerun finishes."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "k"
    cmd = [sys.executable, "-m", "shgm_slam", "perceive", f"{shared_data / 'kitti' / 'sequences' / '07'}:0-60",
           "--out", str(out), "--depth-model", str(DEPTH_ONNX), "--seg-model", str(SEG_ONNX), "--threads", "1",
           "--batch-size", "1"]  # fmt: skip
    env = {**os.environ, "COLUMNS": "200"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True)
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline and not (out / "semantic" / "000001.png").is_file():
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    output = proc.communicate(timeout=120)[0]
    if proc.returncode == 0:
        pytest.skip("the run finished before it could be stopped")
    assert proc.returncode == 130, output
    assert "run the same command again" in " ".join(output.split())
    done = len(list((out / "semantic").glob("*.png")))
    assert done >= 2
    rerun = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert f"{60 - done} frame(s) computed, {done} reused" in " ".join(rerun.stdout.split())
    assert len(open_sequence(out)) == 60


def test_cuda_fallback_is_reported_or_refused(monkeypatch):
    import onnxruntime as ort

    from shgm_slam.perception.perceive import Provider, check_providers, session_providers

    cpu, both = ["CPUExecutionProvider"], ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert check_providers(Provider.AUTO, {"depth": cpu}, cpu) == []  # plain onnxruntime: CPU, nothing to say
    assert check_providers(Provider.AUTO, {"depth": both}, both) == []
    (note,) = check_providers(Provider.AUTO, {"depth": both, "segmentation": cpu}, both)
    assert "segmentation" in note and "cuDNN" in note
    with pytest.raises(ModelError, match="--provider cuda"):
        check_providers(Provider.CUDA, {"depth": cpu}, both)
    assert check_providers(Provider.CPU, {"depth": cpu}, both) == []
    assert session_providers(Provider.CPU) == cpu and session_providers(Provider.AUTO) is None
    monkeypatch.setattr(ort, "get_available_providers", lambda: both)
    assert session_providers(Provider.CUDA) == both
