"""check_model (library) and ``shgm-slam check-model`` (CLI): report, preview PNG, clear errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx import TensorProto, helper, numpy_helper
from typer.testing import CliRunner

from shgm_slam.cli import app
from shgm_slam.errors import DataError
from shgm_slam.perception.card import TaskKind
from shgm_slam.perception.preview import check_model, read_image_rgb, render_preview, synthetic_test_image
from tests.perception.onnx_builders import channel_model, conv_model, write_card


@pytest.fixture
def depth_model(tmp_path: Path) -> Path:
    path = conv_model(tmp_path / "depth.onnx", out_channels=1)
    write_card(
        tmp_path / "depth.yaml",
        {
            "task": "depth",
            "input": {"size": [160, 48]},
            "output": {"kind": "relative", "scale": 10, "shift": 1},
        },
    )
    return path


@pytest.fixture
def seg_model(tmp_path: Path) -> Path:
    path = conv_model(tmp_path / "seg.onnx", out_channels=19)
    write_card(tmp_path / "seg.yaml", {"task": "segmentation", "input": {"size": [160, 48]}})
    return path


def test_check_depth_model_writes_preview(tmp_path: Path, depth_model: Path) -> None:
    report = check_model(depth_model, preview_path=tmp_path / "out" / "preview.png", runs=2, threads=1)
    assert report.task is TaskKind.DEPTH
    assert report.card_path == tmp_path / "depth.yaml"
    assert tuple(report.input_shape[1:]) == (3, 48, 160)
    assert report.fed_shape == (1, 3, 48, 160) and report.raw_output_shape == (1, 1, 48, 160)
    assert report.image_wh == (1242, 375) and "synthetic" in report.image_source
    assert 1.0 <= report.value_min <= report.value_max and report.valid_fraction == 1.0
    assert report.timings_ms["total_ms"] >= report.timings_ms["inference_ms"] > 0
    preview = read_image_rgb(report.preview_path)
    assert preview.shape == (375, 2 * 1242, 3)
    np.testing.assert_array_equal(preview[:, :1242], synthetic_test_image())  # left panel is the image


def test_check_segmentation_model_reports_label_fractions(tmp_path: Path, seg_model: Path) -> None:
    report = check_model(seg_model, preview_path=tmp_path / "seg.png", runs=1, threads=1)
    assert report.task is TaskKind.SEGMENTATION
    assert sum(report.label_fractions.values()) == pytest.approx(1.0)
    assert 0 <= report.value_min <= report.value_max <= 18
    assert read_image_rgb(tmp_path / "seg.png").shape == (375, 2 * 1242, 3)


def test_check_model_on_an_image_file_and_nominal_intrinsics(tmp_path: Path) -> None:
    model = channel_model(tmp_path / "disp.onnx")
    card = {
        "task": "depth",
        "input": {"size": [32, 16], "scale": 1},
        "output": {"kind": "disparity", "baseline_m": 0.5},
    }
    write_card(tmp_path / "card.yaml", card)
    image = np.full((40, 80, 3), 20, dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "img.png"), image)
    report = check_model(model, tmp_path / "card.yaml", tmp_path / "img.png", runs=1, threads=1)
    assert report.image_wh == (80, 40) and report.preview_path is None
    assert any("nominal intrinsics" in n for n in report.notes)
    fx = 718.856 / 1242 * 80
    assert report.value_min == pytest.approx(fx * 0.5 / (20 * 80 / 32), rel=1e-4)  # 20 px at 32/80 scale


def test_corrupt_or_missing_images_are_data_errors(tmp_path: Path, depth_model: Path) -> None:
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(DataError, match=r"bad\.png cannot be decoded"):
        check_model(depth_model, image_path=tmp_path / "bad.png", runs=1)
    with pytest.raises(DataError, match="does not exist"):
        check_model(depth_model, image_path=tmp_path / "none.png", runs=1)


def test_render_preview_panels() -> None:
    img = synthetic_test_image(64, 20)
    depth = np.linspace(0, 30, 64 * 20, dtype=np.float32).reshape(20, 64)
    labels = np.full((20, 64), 255, dtype=np.uint8)
    panel = render_preview(img, depth, labels)
    assert panel.shape == (20, 3 * 64, 3)
    assert (panel[0, 64] == 0).all()  # invalid depth (0 m) is black
    assert (panel[:, 128:] == 0).all()  # ignore labels are black


def test_cli_check_model_refuses_a_one_pixel_depth_output(tmp_path: Path) -> None:
    """A depth output of (N, 1, 1, 1), resized to the image: one value, give or take float32 noise (~2e-7 of it),
    which the exact min == max test let through (exit 0, a depth "map" of one distance)."""
    value = helper.make_tensor_value_info
    path = tmp_path / "pool.onnx"
    graph = helper.make_graph(
        [helper.make_node("GlobalAveragePool", ["x"], ["p"]), helper.make_node("ReduceMean", ["p"], ["m"], axes=[1]),
         helper.make_node("Abs", ["m"], ["a"]), helper.make_node("Add", ["a", "five"], ["out"])],
        "pool", [value("x", TensorProto.FLOAT, ["N", 3, 48, 160])], [value("out", TensorProto.FLOAT, ["N", 1, 1, 1])],
        [numpy_helper.from_array(np.array([5.0], np.float32), "five")],
    )  # fmt: skip
    path.write_bytes(helper.make_model(graph, ir_version=10, opset_imports=[helper.make_opsetid("", 17)])
                     .SerializeToString())  # fmt: skip
    write_card(tmp_path / "pool.yaml", {"task": "depth", "input": {"size": [160, 48]}, "output": {"kind": "metric"}})
    report = check_model(path, None, None, None, runs=1, threads=1)
    assert report.value_max - report.value_min < 1e-5 * report.value_max  # one value, give or take float noise
    result = CliRunner().invoke(app, ["check-model", str(path), "--runs", "1", "--threads", "1"],
                                env={"COLUMNS": "1000"})  # fmt: skip
    assert result.exit_code == 2, result.output
    assert "constant output" in " ".join(result.output.split())


def test_cli_check_model_smoke(tmp_path: Path, depth_model: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "cli.png"
    result = runner.invoke(app, ["check-model", str(depth_model), "--preview", str(out), "--runs", "1"])
    assert result.exit_code == 0, result.output
    assert "depth model" in result.output and "ms/frame" in result.output
    assert out.is_file()
    orphan = channel_model(tmp_path / "orphan.onnx")
    wide = {"COLUMNS": "1000"}  # long temporary paths would wrap inside a word
    result = runner.invoke(app, ["check-model", str(orphan)], env=wide)
    assert result.exit_code == 2
    assert "orphan.yaml not found" in " ".join(result.output.split())
    result = runner.invoke(app, ["check-model", str(tmp_path / "missing.onnx")], env=wide)  # not "card missing.yaml"
    assert result.exit_code == 2 and "missing.onnx does not exist" in " ".join(result.output.split())


@pytest.mark.parametrize(
    ("where", "says"), [("preview", "give it a .png"), ("afile/p.png", "afile is a file, not a folder")]
)
def test_cli_check_model_bad_preview_path_is_one_line(tmp_path: Path, depth_model: Path, where: str, says: str) -> None:
    (tmp_path / "afile").write_text("a file where a folder is wanted")
    args = ["check-model", str(depth_model), "--preview", str(tmp_path / where), "--runs", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, (result.output, repr(result.exception))
    assert says in " ".join(result.output.split()) and "Traceback" not in result.output


def test_cli_check_model_prints_a_model_name_with_brackets_literally(tmp_path: Path, depth_model: Path) -> None:
    odd = tmp_path / "[bold]m.onnx"
    depth_model.rename(odd)
    depth_model.with_suffix(".yaml").rename(odd.with_suffix(".yaml"))
    result = CliRunner().invoke(app, ["check-model", str(odd), "--runs", "1"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "[bold]m.onnx: depth model" in result.output


def test_check_model_on_a_real_kitti_frame(tmp_path: Path, depth_model: Path, shared_data: Path) -> None:
    image = shared_data / "kitti" / "frames06" / "kitti06-12-color.png"
    report = check_model(
        depth_model, image_path=image, preview_path=tmp_path / "kitti.png", runs=1, threads=1
    )
    H, W = read_image_rgb(image).shape[:2]
    assert report.image_wh == (W, H) and report.valid_fraction == 1.0
    assert read_image_rgb(tmp_path / "kitti.png").shape == (H, 2 * W, 3)
