"""Export well-known real networks to ONNX with the model card the shgm_slam adapters read.

Recipes (run with the ``export`` extra installed: ``pip install -e ".[export]"``)::

    python tools/export_onnx.py depth-anything-v2-metric-outdoor --out models/da2_metric_outdoor.onnx
    python tools/export_onnx.py segformer-cityscapes --out models/segformer_b0_cityscapes.onnx
    python tools/export_onnx.py segformer-cityscapes --out /tmp/seg_tiny.onnx --random-init --tiny

* ``depth-anything-v2-metric-outdoor``: Depth Anything V2 Metric Outdoor (``DepthAnythingForDepthEstimation``,
  fine-tuned on Virtual KITTI 2): metric z-depth in metres, ``sigmoid * max_depth`` (80 m).
* ``segformer-cityscapes``: SegFormer (``SegformerForSemanticSegmentation``) fine-tuned on Cityscapes:
  logits over the 19 Cityscapes train classes at 1/4 of the input resolution (the adapter resizes back).

Every export: ``torch.onnx.export`` (TorchScript exporter, no onnxscript needed) with a dynamic batch axis
and fixed H/W, the IR version capped at 10 (what onnxruntime >= 1.20 reads), ``onnx.checker``, an
onnxruntime session compared against the torch output on the same input, the card YAML written next
to the .onnx (same stem), and one run through ``shgm_slam.perception``'s adapter on a test image.

Only this script touches a model hub, and only when a real checkpoint is asked for (the default
without ``--random-init``). ``--random-init`` builds the same architecture from a local config
(``--tiny``: a few-kilobyte version for tests) and downloads nothing.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from shgm_slam.errors import ConfigError, ModelError, ShgmError
from shgm_slam.labels import CITYSCAPES_CLASSES, NUM_CLASSES
from shgm_slam.perception.card import (
    DepthCard,
    DepthKind,
    DepthOutputSpec,
    InputSpec,
    ResizeMode,
    SegmentationCard,
    SegOutputKind,
    SegOutputSpec,
    TaskKind,
    load_card,
)

MAX_IR_VERSION = 10  # onnxruntime >= 1.20 reads IR <= 10; onnx 1.23 would write newer by default
OPSET_RANGE = (14, 20)  # the TorchScript exporter's range that every onnxruntime >= 1.20 runs
DEFAULT_OPSET = 17
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
INPUT_NAME = "pixel_values"
DEFAULT_TEST_IMAGE = (
    Path(__file__).resolve().parents[1].parent / "shared/data/kitti/frames06/kitti06-12-color.png"
)


def _require_torch() -> tuple[Any, Any]:
    """Import torch and transformers, or explain how to install them."""
    try:
        import torch
        import transformers
    except ImportError as exc:
        raise ConfigError(
            f"tools/export_onnx.py needs torch and transformers ({exc}): install the export extra with "
            '`pip install -e ".[export]"` (torch==2.13.0, transformers>=4.44, onnx)'
        ) from None
    return torch, transformers


@dataclass(frozen=True)
class Provenance:
    """Where the weights come from and how their pixels are normalized (card ``source``/``license``/input).

    ``mean``/``std`` are per RGB channel after multiplying 0..255 pixels by ``scale``; ``normalization_from``
    says whether they were read from the checkpoint's preprocessor config or are the ImageNet defaults.
    """

    source: str
    license: str
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD
    scale: float = 1 / 255
    normalization_from: str = "ImageNet defaults"


def checkpoint_provenance(checkpoint: str, license_: str) -> Provenance:
    """Provenance of a real checkpoint, with the normalization of its preprocessor config when it has one
    (``preprocessor_config.json`` next to the weights), else the ImageNet defaults of both recipes."""
    source = checkpoint if Path(checkpoint).exists() else f"https://huggingface.co/{checkpoint}"
    try:
        from transformers import AutoImageProcessor

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            proc = AutoImageProcessor.from_pretrained(checkpoint)
    except Exception:  # no processor config (or offline): the recipe's documented defaults hold
        return Provenance(source, license_)
    mean, std = getattr(proc, "image_mean", None), getattr(proc, "image_std", None)
    if not getattr(proc, "do_normalize", True):
        mean, std = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    if mean is None or std is None or len(mean) != 3 or len(std) != 3:
        return Provenance(source, license_)
    scale = float(getattr(proc, "rescale_factor", 1 / 255)) if getattr(proc, "do_rescale", True) else 1.0
    return Provenance(
        source,
        license_,
        tuple(float(v) for v in mean),
        tuple(float(v) for v in std),
        scale,  # type: ignore[arg-type]
        normalization_from=f"{checkpoint} preprocessor config",
    )


def _input_spec(size_wh: tuple[int, int], prov: Provenance) -> InputSpec:
    """Both recipes: RGB NCHW float32 at a fixed size, stretched (the size keeps KITTI's aspect ratio)."""
    return InputSpec(
        name=INPUT_NAME,
        size=size_wh,
        resize=ResizeMode.STRETCH,
        scale=prov.scale,
        mean=prov.mean,
        std=prov.std,
    )


# --- recipes -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recipe:
    """How to build, wrap and describe one network.

    ``size_wh`` / ``tiny_size_wh`` are the fixed model input sizes (W, H) in pixels; both must be
    multiples of ``multiple_of`` (the network's total stride or patch size).
    """

    name: str
    task: TaskKind
    title: str
    default_checkpoint: str
    size_wh: tuple[int, int]
    tiny_size_wh: tuple[int, int]
    multiple_of: int
    output_name: str
    license: str
    build_random: Callable[[bool], Any]  # tiny -> HF model with random weights (no download)
    load_pretrained: Callable[[str], Any]  # checkpoint id or path -> HF model
    forward: Callable[[Any, Any], Any]  # (HF model, pixel_values NCHW) -> output tensor
    make_card: Callable[[Any, tuple[int, int], Provenance], DepthCard | SegmentationCard]


def _depth_config(tiny: bool) -> Any:
    """Depth Anything V2 Metric Outdoor *Small* architecture (ViT-S/14 DINOv2 + DPT head), or a tiny one."""
    from transformers import DepthAnythingConfig, Dinov2Config

    if tiny:
        backbone = Dinov2Config(
            hidden_size=32,
            num_hidden_layers=4,
            num_attention_heads=2,
            mlp_ratio=2,
            image_size=56,
            patch_size=14,
            out_indices=[1, 2, 3, 4],
            reshape_hidden_states=False,
        )
        return DepthAnythingConfig(
            backbone_config=backbone,
            reassemble_hidden_size=32,
            neck_hidden_sizes=[8, 16, 32, 32],
            fusion_hidden_size=16,
            head_hidden_size=8,
            depth_estimation_type="metric",
            max_depth=80,
        )
    backbone = Dinov2Config(
        hidden_size=384,
        num_hidden_layers=12,
        num_attention_heads=6,
        image_size=518,
        patch_size=14,
        out_indices=[3, 6, 9, 12],
        reshape_hidden_states=False,
    )
    return DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=384,
        neck_hidden_sizes=[48, 96, 192, 384],
        fusion_hidden_size=64,
        head_hidden_size=32,
        depth_estimation_type="metric",
        max_depth=80,
    )


def _depth_random(tiny: bool) -> Any:
    from transformers import DepthAnythingForDepthEstimation

    return DepthAnythingForDepthEstimation(_depth_config(tiny))


def _depth_pretrained(checkpoint: str) -> Any:
    from transformers import DepthAnythingForDepthEstimation

    model = DepthAnythingForDepthEstimation.from_pretrained(checkpoint)
    if getattr(model.config, "depth_estimation_type", "relative") != "metric":
        raise ConfigError(
            f"checkpoint {checkpoint} predicts relative (affine-invariant inverse) depth, not metres: use a "
            "metric one such as depth-anything/Depth-Anything-V2-Metric-Outdoor-Small-hf"
        )
    return model


def _depth_card(model: Any, size_wh: tuple[int, int], prov: Provenance) -> DepthCard:
    max_depth_m = float(model.config.max_depth)
    return DepthCard(
        task=TaskKind.DEPTH,
        name="Depth Anything V2 Metric Outdoor",
        description=(
            "metric z-depth in metres (sigmoid * max_depth); trained on Virtual KITTI 2, so it expects "
            "KITTI-like street views and intrinsics; exported by tools/export_onnx.py"
        ),
        source=prov.source,
        license=prov.license,
        input=_input_spec(size_wh, prov),
        output=DepthOutputSpec(name="depth", kind=DepthKind.METRIC, min_depth_m=0.1, max_depth_m=max_depth_m),
    )


def _seg_config(tiny: bool) -> Any:
    """SegFormer-B0 with a 19-class Cityscapes head, or a tiny one."""
    from transformers import SegformerConfig

    labels = {i: name for i, name in enumerate(CITYSCAPES_CLASSES)}
    if tiny:
        return SegformerConfig(
            hidden_sizes=[8, 16, 24, 32],
            depths=[1, 1, 1, 1],
            num_attention_heads=[1, 1, 1, 1],
            decoder_hidden_size=16,
            num_labels=NUM_CLASSES,
            id2label=labels,
            label2id={v: k for k, v in labels.items()},
        )
    return SegformerConfig(
        num_labels=NUM_CLASSES, id2label=labels, label2id={v: k for k, v in labels.items()}
    )


def _seg_random(tiny: bool) -> Any:
    from transformers import SegformerForSemanticSegmentation

    return SegformerForSemanticSegmentation(_seg_config(tiny))


def _seg_pretrained(checkpoint: str) -> Any:
    from transformers import SegformerForSemanticSegmentation

    return SegformerForSemanticSegmentation.from_pretrained(checkpoint)


def _normalize_name(name: str) -> str:
    return str(name).strip().lower().replace("_", " ").replace("-", " ")


def cityscapes_classes_of(id2label: dict[Any, str], where: str) -> tuple[str, ...]:
    """The model's class names in output order, checked to be the 19 Cityscapes train classes.

    Raises:
        ConfigError: the model has another class list (it is not a Cityscapes checkpoint).
    """
    names = tuple(str(id2label[k]) for k in sorted(id2label, key=int))
    if len(names) != NUM_CLASSES or any(
        _normalize_name(n) != c for n, c in zip(names, CITYSCAPES_CLASSES, strict=True)
    ):
        raise ConfigError(
            f"{where} has classes {list(names)[:6]}... ({len(names)} in all), not the 19 Cityscapes train "
            "classes in train-id order: pick a *-finetuned-cityscapes-* checkpoint, or write the card's "
            "output.mapping by hand (see shgm_slam/perception/card.py)"
        )
    return names


def _seg_card(model: Any, size_wh: tuple[int, int], prov: Provenance) -> SegmentationCard:
    classes = cityscapes_classes_of(model.config.id2label, f"model {prov.source}")
    return SegmentationCard(
        task=TaskKind.SEGMENTATION,
        name="SegFormer Cityscapes",
        description=(
            "logits over the 19 Cityscapes train classes at 1/4 of the input size (the adapter argmaxes "
            "and resizes back); exported by tools/export_onnx.py"
        ),
        source=prov.source,
        license=prov.license,
        input=_input_spec(size_wh, prov),
        output=SegOutputSpec(
            name="logits",
            kind=SegOutputKind.LOGITS,
            classes=classes,
            mapping={i: i for i in range(NUM_CLASSES)},  # train-id order: identity
        ),
    )


RECIPES: dict[str, Recipe] = {
    r.name: r
    for r in (
        Recipe(
            name="depth-anything-v2-metric-outdoor",
            task=TaskKind.DEPTH,
            title="Depth Anything V2 Metric Outdoor",
            default_checkpoint="depth-anything/Depth-Anything-V2-Metric-Outdoor-Small-hf",
            # KITTI's 3.3:1 aspect with about as many 14x14 patches (66 x 20) as the 518 x 518 training crops
            size_wh=(924, 280),
            tiny_size_wh=(112, 56),
            multiple_of=14,
            output_name="depth",
            license="Small: Apache-2.0; Base/Large: CC-BY-NC-4.0 (see the checkpoint's model card)",
            build_random=_depth_random,
            load_pretrained=_depth_pretrained,
            forward=lambda m, x: m(pixel_values=x).predicted_depth,
            make_card=_depth_card,
        ),
        Recipe(
            name="segformer-cityscapes",
            task=TaskKind.SEGMENTATION,
            title="SegFormer Cityscapes",
            default_checkpoint="nvidia/segformer-b0-finetuned-cityscapes-1024-1024",
            size_wh=(1024, 320),  # KITTI's aspect; SegFormer takes any multiple of 32
            tiny_size_wh=(128, 64),
            multiple_of=32,
            output_name="logits",
            license="NVIDIA Source Code License for SegFormer (non-commercial; see the model card)",
            build_random=_seg_random,
            load_pretrained=_seg_pretrained,
            forward=lambda m, x: m(pixel_values=x).logits,
            make_card=_seg_card,
        ),
    )
}


# --- export --------------------------------------------------------------------------------------------


@dataclass
class ExportResult:
    """What an export wrote and the torch module it came from (for cross-checks).

    Attributes:
        onnx_path / card_path: the written model and its card (same stem, ``.yaml``).
        card: the card as written.
        module: the wrapped torch module (``module(pixel_values (N,3,H,W) float32) -> output``), eval mode.
        size_wh: the fixed model input size (W, H) in pixels.
        ir_version / opset: of the saved model.
        max_abs_diff: largest |onnxruntime - torch| on the export check input.
        export_s: wall-clock seconds of torch.onnx.export.
        normalization_from: where the card's mean/std/scale came from.
    """

    onnx_path: Path
    card_path: Path
    card: DepthCard | SegmentationCard
    module: Any
    size_wh: tuple[int, int]
    ir_version: int
    opset: int
    max_abs_diff: float
    export_s: float
    normalization_from: str


def _wrap(recipe: Recipe, hf_model: Any) -> Any:
    """An nn.Module returning the recipe's single output tensor (what torch.onnx.export traces)."""
    import torch

    class Wrapped(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = hf_model

        def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
            return recipe.forward(self.model, pixel_values)

    return Wrapped().eval()


def build_module(recipe: Recipe, checkpoint: str | None, random_init: bool, tiny: bool, seed: int = 0) -> Any:
    """The recipe's network wrapped for export (eval mode, float32).

    Raises:
        ConfigError: inconsistent options (``--tiny`` without ``--random-init``, a checkpoint with it).
        ModelError: the checkpoint cannot be loaded.
    """
    torch, _ = _require_torch()
    if tiny and not random_init:
        raise ConfigError(
            "--tiny builds a small random network: add --random-init (tiny real checkpoints do not exist)"
        )
    if random_init and checkpoint is not None:
        raise ConfigError("--checkpoint and --random-init exclude each other: drop one of them")
    torch.manual_seed(seed)
    if random_init:
        hf_model = recipe.build_random(tiny)
    else:
        ckpt = checkpoint or recipe.default_checkpoint
        try:
            hf_model = recipe.load_pretrained(ckpt)
        except ShgmError:
            raise
        except Exception as exc:  # transformers/huggingface_hub raise many unrelated classes (OSError, HTTP)
            raise ModelError(
                f"cannot load checkpoint {ckpt!r} ({type(exc).__name__}: {str(exc)[:300]}): check the id or "
                "local path and your internet access (or export offline with --random-init)"
            ) from None
    return _wrap(recipe, hf_model.float())


def _check_size(recipe: Recipe, size_wh: tuple[int, int]) -> None:
    m = recipe.multiple_of
    if min(size_wh) < m or any(v % m for v in size_wh):
        raise ConfigError(
            f"--size {size_wh[0]} {size_wh[1]}: {recipe.title} needs W and H that are multiples of {m}; "
            f"try --size {max(m, round(size_wh[0] / m) * m)} {max(m, round(size_wh[1] / m) * m)}"
        )


def _check_opset(opset: int) -> None:
    if not OPSET_RANGE[0] <= opset <= OPSET_RANGE[1]:
        raise ConfigError(
            f"--opset {opset}: choose {OPSET_RANGE[0]}..{OPSET_RANGE[1]} (onnxruntime >= 1.20 runs them)"
        )


def export_module(
    module: Any, onnx_path: Path, size_wh: tuple[int, int], output_name: str, opset: int = DEFAULT_OPSET
) -> tuple[int, int, float, float]:
    """Export ``module`` with a dynamic batch axis and fixed H/W, cap the IR version, check and verify.

    Args:
        module: torch module mapping (N, 3, H, W) float32 -> one tensor.
        onnx_path: where the .onnx goes (parent folders are created).
        size_wh: fixed input (W, H) pixels.
        output_name: name of the ONNX output.
        opset: ai.onnx opset, within ``OPSET_RANGE``.

    Returns:
        (ir_version, opset, max |onnxruntime - torch| on a random input of batch 2, export seconds).

    Raises:
        ConfigError: opset out of range. ModelError: export, checker or onnxruntime failed.
    """
    import onnx
    import onnxruntime as ort
    import torch

    _check_opset(opset)
    W, H = size_wh
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    example = torch.zeros(1, 3, H, W)
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # TracerWarnings: H/W are fixed on purpose
            torch.onnx.export(
                module,
                (example,),
                str(onnx_path),
                dynamo=False,
                opset_version=opset,
                input_names=[INPUT_NAME],
                output_names=[output_name],
                dynamic_axes={INPUT_NAME: {0: "batch"}, output_name: {0: "batch"}},
                do_constant_folding=True,
            )
    except Exception as exc:  # torch's exporter raises many classes
        raise ModelError(
            f"torch.onnx.export failed for {onnx_path} ({type(exc).__name__}: {str(exc)[:300]})"
        ) from None
    export_s = time.perf_counter() - t0

    probe = torch.from_numpy(np.random.default_rng(0).normal(size=(2, 3, H, W)).astype(np.float32))
    with torch.no_grad():
        expected = module(probe).numpy()
    model = onnx.load(str(onnx_path))
    model.ir_version = min(model.ir_version, MAX_IR_VERSION)
    _set_output_shape(model, ("batch", *expected.shape[1:]))
    model.metadata_props.add(key="exported_by", value="shgm_slam tools/export_onnx.py")
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        raise ModelError(f"{onnx_path} fails onnx.checker after export: {str(exc)[:300]}") from None
    onnx.save(model, str(onnx_path))
    try:
        session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
        (got,) = session.run([output_name], {INPUT_NAME: probe.numpy()})
    except Exception as exc:  # onnxruntime's pybind exception classes
        raise ModelError(f"onnxruntime cannot run the exported {onnx_path}: {str(exc)[:300]}") from None
    if got.shape != expected.shape:
        raise ModelError(f"{onnx_path}: onnxruntime output {got.shape} differs from torch's {expected.shape}")
    opset_used = next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
    return model.ir_version, opset_used, float(np.abs(got - expected).max()), export_s


def _set_output_shape(model: Any, dims: tuple[int | str, ...]) -> None:
    """Replace the exporter's symbolic output dims by the known ones (batch stays symbolic)."""
    shape = model.graph.output[0].type.tensor_type.shape
    while len(shape.dim) < len(dims):
        shape.dim.add()
    del shape.dim[len(dims) :]
    for dim, value in zip(shape.dim, dims, strict=True):
        dim.Clear()
        if isinstance(value, str):
            dim.dim_param = value
        else:
            dim.dim_value = int(value)


def export_recipe(
    name: str,
    out: Path | str,
    checkpoint: str | None = None,
    random_init: bool = False,
    tiny: bool = False,
    size_wh: tuple[int, int] | None = None,
    opset: int = DEFAULT_OPSET,
    seed: int = 0,
) -> ExportResult:
    """Build the recipe's network, export it to ``out`` and write its card next to it.

    Args:
        name: a key of ``RECIPES``.
        out: the .onnx path; the card goes to the same stem with ``.yaml``.
        checkpoint: Hugging Face id or local folder (default: the recipe's); downloads when it is an id.
        random_init / tiny: random weights of the real (or a tiny) architecture, nothing downloaded.
        size_wh: fixed input (W, H) in pixels; default the recipe's (tiny: its tiny size).
        opset: ai.onnx opset.
        seed: torch seed for random weights.

    Raises:
        ConfigError: unknown recipe or bad options. ModelError: loading or exporting failed.
    """
    if name not in RECIPES:
        raise ConfigError(f"unknown recipe {name!r}: choose one of {', '.join(RECIPES)}")
    recipe = RECIPES[name]
    onnx_path = Path(out)
    if onnx_path.suffix != ".onnx":
        raise ConfigError(
            f"--out {onnx_path}: give a path ending in .onnx (the card goes next to it as .yaml)"
        )
    size = tuple(size_wh) if size_wh is not None else (recipe.tiny_size_wh if tiny else recipe.size_wh)
    _check_size(recipe, size)  # type: ignore[arg-type]
    _check_opset(opset)
    module = build_module(recipe, checkpoint, random_init, tiny, seed)
    ir_version, opset_used, diff, export_s = export_module(module, onnx_path, size, recipe.output_name, opset)
    if random_init:
        prov = Provenance(
            f"random weights ({'tiny' if tiny else 'full-size'} {recipe.title} architecture, seed {seed})",
            "none (random weights)",
        )
    else:
        prov = checkpoint_provenance(checkpoint or recipe.default_checkpoint, recipe.license)
    card = recipe.make_card(module.model, size, prov)
    card_path = write_full_card(card, onnx_path)
    return ExportResult(  # type: ignore[arg-type]
        onnx_path,
        card_path,
        card,
        module,
        size,
        ir_version,
        opset_used,
        diff,
        export_s,
        prov.normalization_from,
    )


def write_full_card(card: DepthCard | SegmentationCard, onnx_path: Path) -> Path:
    """Write ``card`` next to ``onnx_path`` (same stem, ``.yaml``) with every field spelled out, so a reader
    sees the whole input/output contract; the file is read back with ``load_card`` to prove it validates.

    Raises:
        ModelError: the written card does not read back as the same card.
    """
    import yaml

    data = {"task": card.task.value, **card.model_dump(mode="json", exclude_none=True, exclude={"task"})}
    card_path = onnx_path.with_suffix(".yaml")
    card_path.write_text(yaml.safe_dump(data, sort_keys=False, width=110))
    if load_card(onnx_path) != card:
        raise ModelError(
            f"{card_path} does not read back as the card that was written (a card schema change?)"
        )
    return card_path


# --- verification through the project's adapter -----------------------------------------------------------


def load_test_image(path: Path | None, size_wh: tuple[int, int]) -> tuple[np.ndarray, str]:
    """The RGB uint8 test image: ``path``, else the shared KITTI frame, else a synthetic street-like image."""
    candidate = path or (DEFAULT_TEST_IMAGE if DEFAULT_TEST_IMAGE.is_file() else None)
    if candidate is not None:
        bgr = cv2.imread(str(candidate), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ConfigError(f"--image {candidate}: not a readable image file")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), str(candidate)
    W, H = size_wh[0] * 2, size_wh[1] * 2
    y, x = np.mgrid[0:H, 0:W]
    image = np.stack([x * 255 // W, y * 255 // H, (x + y) * 127 // (W + H)], axis=-1).astype(np.uint8)
    return image, f"synthetic {W}x{H} gradient"


def verify_with_adapter(result: ExportResult, image_rgb: np.ndarray, repeats: int = 5) -> dict[str, Any]:
    """Run the exported model through ``DepthModel`` / ``SegmentationModel`` with its card.

    Returns:
        dict with the output ``shape``, ``dtype``, value ``range`` (depth, metres) or ``labels`` (train ids
        present), and the median ``ms_per_frame`` (pre + inference + postprocess) over ``repeats`` runs.
    """
    from shgm_slam.perception.depth import DepthModel
    from shgm_slam.perception.onnx_model import measure_overhead
    from shgm_slam.perception.segmentation import SegmentationModel

    cls = DepthModel if result.card.task is TaskKind.DEPTH else SegmentationModel
    adapter = cls(result.onnx_path, threads=2)
    out = adapter.predict(image_rgb)
    timings = measure_overhead(adapter, image_rgb, repeats=repeats)
    report: dict[str, Any] = {
        "shape": out.shape,
        "dtype": str(out.dtype),
        "ms_per_frame": timings["total_ms"],
        "inference_ms": timings["inference_ms"],
    }
    if result.card.task is TaskKind.DEPTH:
        valid = out > 0
        report["range"] = (float(out[valid].min()), float(out[valid].max())) if valid.any() else None
        report["valid_fraction"] = float(valid.mean())
    else:
        ids, counts = np.unique(out, return_counts=True)
        report["labels"] = {
            CITYSCAPES_CLASSES[i] if i < NUM_CLASSES else "ignore": round(c / out.size, 3)
            for i, c in zip(ids.tolist(), counts.tolist(), strict=True)
        }
    return report


# --- command line --------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python tools/export_onnx.py",
        description="Export a real network to ONNX with its shgm_slam model card (see docs/real_models.md).",
    )
    p.add_argument("recipe", choices=sorted(RECIPES), help="which network")
    p.add_argument(
        "--out", type=Path, required=True, help="output .onnx path; the card is written next to it"
    )
    p.add_argument("--checkpoint", help="Hugging Face id or local folder (default: the recipe's)")
    p.add_argument("--random-init", action="store_true", help="random weights, no download")
    p.add_argument("--tiny", action="store_true", help="with --random-init: a tiny architecture (tests)")
    p.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), help="fixed model input size in pixels")
    p.add_argument(
        "--opset", type=int, default=DEFAULT_OPSET, help=f"ai.onnx opset {OPSET_RANGE} (default 17)"
    )
    p.add_argument("--image", type=Path, help="test image for the adapter check (default: a KITTI frame)")
    p.add_argument("--no-verify", action="store_true", help="skip the adapter check on the test image")
    return p


def main(argv: list[str] | None = None) -> int:
    """Command-line entry; returns the exit code (0 ok, 2 error with one clear line on stderr)."""
    args = _parser().parse_args(argv)
    try:
        result = export_recipe(
            args.recipe,
            args.out,
            checkpoint=args.checkpoint,
            random_init=args.random_init,
            tiny=args.tiny,
            size_wh=tuple(args.size) if args.size else None,
            opset=args.opset,
        )
        size_mb = result.onnx_path.stat().st_size / 1e6
        print(
            f"wrote {result.onnx_path} ({size_mb:.1f} MB, IR {result.ir_version}, opset {result.opset}, "
            f"input 1x3x{result.size_wh[1]}x{result.size_wh[0]}, export {result.export_s:.1f} s)"
        )
        print(f"wrote {result.card_path} (normalization: {result.normalization_from})")
        print(f"onnxruntime vs torch: max |diff| = {result.max_abs_diff:.2e}")
        if not args.no_verify:
            image, what = load_test_image(args.image, result.size_wh)
            report = verify_with_adapter(result, image)
            print(f"adapter on {what} ({image.shape[1]}x{image.shape[0]}):")
            for key, value in report.items():
                print(f"  {key}: {value}")
    except ShgmError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
