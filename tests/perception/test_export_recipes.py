"""tools/export_onnx.py: tiny random-init versions of the real-model recipes, exported and read back
through the project's adapters with the written cards, cross-checked against the torch models.

Needs torch + transformers (the ``export`` extra); skips cleanly without them (CI installs only ``dev``).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")
onnx = pytest.importorskip("onnx")

from shgm_slam.errors import ConfigError  # noqa: E402
from shgm_slam.labels import CITYSCAPES_CLASSES, IGNORE_ID, NUM_CLASSES  # noqa: E402
from shgm_slam.perception.card import DepthKind, SegOutputKind, TaskKind, load_card  # noqa: E402
from shgm_slam.perception.depth import DepthModel  # noqa: E402
from shgm_slam.perception.labels import output_class_names  # noqa: E402
from shgm_slam.perception.segmentation import SegmentationModel  # noqa: E402

TOOL = Path(__file__).resolve().parents[2] / "tools" / "export_onnx.py"
DEPTH = "depth-anything-v2-metric-outdoor"
SEG = "segformer-cityscapes"


def _load_tool():
    spec = importlib.util.spec_from_file_location("shgm_export_onnx", TOOL)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


export_onnx = _load_tool()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Both recipes exported once (tiny random init): recipe name -> ExportResult."""
    out = tmp_path_factory.mktemp("export")
    return {
        name: export_onnx.export_recipe(name, out / f"{name}.onnx", random_init=True, tiny=True)
        for name in (DEPTH, SEG)
    }


def _adapter(result):
    cls = DepthModel if result.card.task is TaskKind.DEPTH else SegmentationModel
    return cls(result.onnx_path, threads=1)


def _street_image(w: int, h: int, seed: int = 0) -> np.ndarray:
    """A structured RGB uint8 image (gradients + noise + a box) so the random networks vary spatially."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    image = np.stack([x * 255 // w, y * 255 // h, 255 - (x + y) * 255 // (w + h)], axis=-1).astype(np.int32)
    image[h // 3 : 2 * h // 3, w // 4 : w // 2] = (200, 30, 30)
    image += rng.integers(-20, 21, size=image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


def _normalize(image_rgb: np.ndarray, card) -> np.ndarray:
    """(H, W, 3) uint8 -> (1, 3, H, W) float32 with the card's scale/mean/std (ground truth, numpy)."""
    spec = card.input
    x = image_rgb.astype(np.float64) * spec.effective_scale
    x = (x - np.asarray(spec.mean)) / np.asarray(spec.std)
    return x.transpose(2, 0, 1)[None].astype(np.float32)


def _torch_out(result, blob: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return result.module(torch.from_numpy(blob)).numpy()


@pytest.mark.parametrize("name", [DEPTH, SEG])
def test_export_writes_readable_versions_and_shapes(exported, name):
    result = exported[name]
    model = onnx.load(str(result.onnx_path))
    onnx.checker.check_model(model)
    assert model.ir_version <= export_onnx.MAX_IR_VERSION
    opset = next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
    assert export_onnx.OPSET_RANGE[0] <= opset <= export_onnx.OPSET_RANGE[1]
    W, H = result.size_wh
    (inp,) = model.graph.input
    dims = [d.dim_param or d.dim_value for d in inp.type.tensor_type.shape.dim]
    assert dims == ["batch", 3, H, W]  # dynamic batch, fixed H/W
    assert result.max_abs_diff < 1e-4


def test_depth_card_is_metric_80m(exported):
    result = exported[DEPTH]
    card = load_card(result.onnx_path)  # the YAML next to the model, through the project's loader
    assert card == result.card
    assert card.task is TaskKind.DEPTH
    assert card.output.kind is DepthKind.METRIC and card.output.max_depth_m == 80.0
    assert card.input.size == result.size_wh
    assert card.input.mean == export_onnx.IMAGENET_MEAN and card.input.std == export_onnx.IMAGENET_STD


@pytest.mark.parametrize("name", [DEPTH, SEG])
def test_random_init_cards_use_imagenet_normalization(exported, name):
    from transformers.utils.constants import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD

    spec = exported[name].card.input
    np.testing.assert_allclose(spec.mean, IMAGENET_DEFAULT_MEAN)
    np.testing.assert_allclose(spec.std, IMAGENET_DEFAULT_STD)
    assert spec.effective_scale == pytest.approx(1 / 255)


def _save_checkpoint(name: str, folder: Path, mean, std, **config) -> None:
    """A local Hugging Face checkpoint folder (tiny random weights + preprocessor config), no download."""
    from transformers import DPTImageProcessor, SegformerImageProcessor

    model = export_onnx.RECIPES[name].build_random(True)
    for key, value in config.items():
        setattr(model.config, key, value)
    model.save_pretrained(folder)
    processor = DPTImageProcessor if name == DEPTH else SegformerImageProcessor
    processor(image_mean=list(mean), image_std=list(std)).save_pretrained(folder)


@pytest.mark.parametrize("name", [DEPTH, SEG])
def test_export_from_local_checkpoint_uses_its_weights_and_processor(tmp_path, name):
    mean, std = (0.5, 0.4, 0.3), (0.2, 0.25, 0.3)
    ckpt = tmp_path / "ckpt"
    _save_checkpoint(name, ckpt, mean, std)
    result = export_onnx.export_recipe(name, tmp_path / "m.onnx", checkpoint=str(ckpt))
    card = load_card(result.onnx_path)
    assert card.source == str(ckpt)
    np.testing.assert_allclose(card.input.mean, mean)
    np.testing.assert_allclose(card.input.std, std)
    assert "preprocessor" in result.normalization_from
    # the exported weights are the checkpoint's: same output as the saved model loaded on its own
    W, H = result.size_wh
    blob = _normalize(_street_image(W, H, seed=5), card)
    reference = export_onnx.RECIPES[name].load_pretrained(str(ckpt)).eval()
    with torch.no_grad():
        expected = export_onnx.RECIPES[name].forward(reference, torch.from_numpy(blob)).numpy()
    adapter = _adapter(result)
    (got,) = adapter.session.run(None, {adapter.input_spec.name: blob})
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-4)


def test_relative_depth_checkpoint_is_rejected(tmp_path):
    ckpt = tmp_path / "relative"
    _save_checkpoint(
        DEPTH, ckpt, export_onnx.IMAGENET_MEAN, export_onnx.IMAGENET_STD, depth_estimation_type="relative"
    )
    with pytest.raises(ConfigError, match="relative"):
        export_onnx.export_recipe(DEPTH, tmp_path / "m.onnx", checkpoint=str(ckpt))
    assert not (tmp_path / "m.onnx").exists()


def test_missing_checkpoint_is_a_model_error(tmp_path):
    from shgm_slam.errors import ModelError

    # an absolute path with several slashes is neither a folder nor a valid hub id: no network call
    with pytest.raises(ModelError, match="cannot load checkpoint"):
        export_onnx.export_recipe(SEG, tmp_path / "m.onnx", checkpoint=str(tmp_path / "no-such-folder"))


def test_seg_card_lists_cityscapes_identity(exported):
    result = exported[SEG]
    card = load_card(result.onnx_path)
    assert card == result.card
    assert card.output.kind is SegOutputKind.LOGITS
    assert output_class_names(card.output) == CITYSCAPES_CLASSES
    adapter = _adapter(result)
    np.testing.assert_array_equal(adapter.class_to_train_id, np.arange(NUM_CLASSES))
    W, H = result.size_wh
    assert tuple(adapter.output_spec.shape) == ("batch", NUM_CLASSES, H // 4, W // 4)  # logits at 1/4


@pytest.mark.parametrize("name", [DEPTH, SEG])
def test_onnx_matches_torch_on_preprocessed_input(exported, name):
    result = exported[name]
    W, H = result.size_wh
    blob = _normalize(_street_image(W, H), result.card)
    adapter = _adapter(result)
    (onnx_out,) = adapter.session.run(None, {adapter.input_spec.name: blob})
    torch_out = _torch_out(result, blob)
    assert onnx_out.shape == torch_out.shape
    np.testing.assert_allclose(onnx_out, torch_out, rtol=1e-4, atol=1e-4)
    assert np.ptp(torch_out) > 0  # the check compares something that varies


def test_depth_adapter_end_to_end_equals_torch(exported):
    """Image at the model size: the adapter's depth is the torch depth (clamped to the card's range)."""
    result = exported[DEPTH]
    W, H = result.size_wh
    image = _street_image(W, H, seed=1)
    depth_m = _adapter(result).predict(image)
    expected = np.clip(_torch_out(result, _normalize(image, result.card))[0], 0.1, 80.0)
    assert depth_m.shape == (H, W) and depth_m.dtype == np.float32
    np.testing.assert_allclose(depth_m, expected, rtol=1e-4, atol=1e-3)


def test_seg_adapter_end_to_end_equals_torch(exported):
    """Image at the model size: the adapter's labels are the torch argmax, resized back from 1/4."""
    result = exported[SEG]
    W, H = result.size_wh
    image = _street_image(W, H, seed=2)
    labels = _adapter(result).predict(image)
    logits = _torch_out(result, _normalize(image, result.card))[0]
    expected = cv2.resize(np.argmax(logits, axis=0).astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)
    assert labels.shape == (H, W) and labels.dtype == np.uint8
    assert np.mean(labels == expected) > 0.99  # ties between near-equal logits may flip a pixel


@pytest.mark.parametrize("name", [DEPTH, SEG])
def test_adapter_on_other_image_size_and_batch(exported, name):
    result = exported[name]
    adapter = _adapter(result)
    images = [_street_image(203, 61, seed=3), _street_image(203, 61, seed=4)]  # not the model's size/aspect
    outputs = adapter.predict_batch(images)  # batch 2 through the dynamic batch axis
    assert len(outputs) == 2
    for out in outputs:
        assert out.shape == (61, 203)
        if name == DEPTH:
            assert out.dtype == np.float32 and np.isfinite(out).all() and (out >= 0).all()
            assert out.max() <= 80.0 and (out[out > 0] >= 0.1).all()
        else:
            assert out.dtype == np.uint8
            assert set(np.unique(out)) <= set(range(NUM_CLASSES)) | {IGNORE_ID}
    single = adapter.predict(images[1])
    np.testing.assert_allclose(single, outputs[1], atol=1e-4)  # batching does not change the result


def test_cityscapes_class_check():
    names = {i: n.replace(" ", "_").title() for i, n in enumerate(CITYSCAPES_CLASSES)}
    assert export_onnx.cityscapes_classes_of(names, "m") == tuple(names.values())
    with pytest.raises(ConfigError, match="Cityscapes"):
        export_onnx.cityscapes_classes_of({0: "wall", 1: "building", 2: "sky"}, "an ADE20K model")
    shuffled = dict(names)
    shuffled[0], shuffled[1] = names[1], names[0]
    with pytest.raises(ConfigError, match="train-id order"):
        export_onnx.cityscapes_classes_of(shuffled, "m")


def test_cli_exports_and_verifies(tmp_path, capsys):
    image_path = tmp_path / "frame.png"
    cv2.imwrite(str(image_path), _street_image(160, 48)[:, :, ::-1])
    out = tmp_path / "models" / "seg.onnx"
    code = export_onnx.main(
        [SEG, "--out", str(out), "--random-init", "--tiny", "--size", "96", "32", "--image", str(image_path)]
    )
    assert code == 0
    assert out.is_file() and out.with_suffix(".yaml").is_file()
    assert load_card(out).input.size == (96, 32)
    printed = capsys.readouterr().out
    assert "shape: (48, 160)" in printed and "onnxruntime vs torch" in printed


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--tiny"], "--random-init"),
        (["--random-init", "--tiny", "--size", "100", "56"], "multiples of 14"),
        (["--random-init", "--checkpoint", "some/model"], "exclude each other"),
        (["--random-init", "--tiny", "--opset", "25"], "--opset"),
    ],
)
def test_cli_rejects_bad_options(tmp_path, capsys, args, message):
    out = tmp_path / "d.onnx"
    assert export_onnx.main([DEPTH, "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and message in err
    assert not out.exists()


def test_cli_rejects_non_onnx_out(tmp_path, capsys):
    assert export_onnx.main([DEPTH, "--out", str(tmp_path / "d.pt"), "--random-init", "--tiny"]) == 2
    assert ".onnx" in capsys.readouterr().err
