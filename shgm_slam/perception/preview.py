"""Check a model once and look at what it sees: ``check_model`` behind ``shgm-slam check-model``.

``check_model`` validates the card against the model, runs it a few times on an image (or a
synthetic street-like test image), reports shapes, value ranges and median timings, and writes a
preview PNG: image | depth (turbo, near = red) | labels (Cityscapes colours).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from shgm_slam.errors import DataError, ModelError
from shgm_slam.labels import IGNORE_ID, colorize_labels, label_name
from shgm_slam.perception.card import TaskKind, default_card_path, load_card
from shgm_slam.perception.depth import DepthModel
from shgm_slam.perception.onnx_model import OnnxModel, check_image, measure_overhead
from shgm_slam.perception.segmentation import SegmentationModel
from shgm_slam.types import Intrinsics

KITTI_FX_PER_WIDTH = 718.856 / 1242.0
"""KITTI's focal length as a fraction of image width: nominal intrinsics for images without calibration."""


@dataclass
class ModelReport:
    """What ``check_model`` found (rendered by the CLI, asserted by tests).

    ``input_shape``/``output_shape`` are as the model declares them (after pinning dynamic axes);
    ``fed_shape``/``raw_output_shape`` are the tensors of the actual run. Timings are medians (ms).
    """

    model_path: Path
    card_path: Path
    task: TaskKind
    providers: list[str]
    input_name: str
    input_shape: tuple[int | str | None, ...]
    input_type: str
    output_name: str
    output_shape: tuple[int | str | None, ...]
    output_type: str
    image_source: str
    image_wh: tuple[int, int]
    fed_shape: tuple[int, ...]
    raw_output_shape: tuple[int, ...]
    value_min: float
    value_max: float
    valid_fraction: float
    timings_ms: dict[str, float]
    label_fractions: dict[str, float] = field(default_factory=dict)
    preview_path: Path | None = None
    notes: list[str] = field(default_factory=list)


def synthetic_test_image(width: int = 1242, height: int = 375) -> np.ndarray:
    """A deterministic street-like (H, W, 3) uint8 RGB image: sky, buildings, a tree, a car, the road."""
    v = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None]
    img = np.empty((height, width, 3), dtype=np.uint8)
    img[:] = (np.array([110, 160, 220]) * (1.0 - 0.4 * v[..., None])).astype(np.uint8)  # sky gradient
    horizon = int(0.45 * height)
    img[horizon:] = (105, 105, 110)  # road
    for x0, x1, top, colour in ((0.0, 0.3, 0.1, (150, 120, 100)), (0.7, 1.0, 0.05, (170, 170, 160))):
        img[int(top * height) : horizon, int(x0 * width) : int(x1 * width)] = colour  # buildings
    cv2.circle(img, (int(0.4 * width), int(0.3 * height)), int(0.12 * height), (60, 120, 40), -1)  # tree
    cv2.rectangle(img, (int(0.5 * width), int(0.4 * height)), (int(0.62 * width), int(0.6 * height)),
                  (30, 30, 140), -1)  # car  # fmt: skip
    noise = np.random.default_rng(0).integers(-6, 7, img.shape)
    return np.clip(img.astype(np.int16) + noise, 0, 255).astype(np.uint8)


def read_image_rgb(path: Path | str) -> np.ndarray:
    """Read a colour or grayscale image file as (H, W, 3) uint8 RGB.

    Raises:
        DataError: the file is missing or is not a readable image.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"image {path} does not exist")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None or bgr.size == 0:
        raise DataError(f"image {path} cannot be decoded (corrupt or unsupported format): use a PNG or JPEG")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""File types a preview can be written as."""


def _check_image_suffix(path: Path) -> None:
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise DataError(f"cannot write image {path}: give it a .png (or .jpg) extension, e.g. {path}.png")


def write_png(path: Path | str, image_rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 RGB image as PNG (or JPEG by its suffix; parent folders are created).

    Raises:
        DataError: the path has no image suffix, its folder cannot be created (e.g. a file is in the
            way) or the image cannot be written.
    """
    path = Path(path)
    _check_image_suffix(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        ok = cv2.imwrite(str(path), cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))
    except (OSError, cv2.error) as exc:
        if isinstance(exc, FileExistsError | NotADirectoryError):
            why = f"{exc.filename} is a file, not a folder"
        else:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc).strip().splitlines()[-1]
        raise DataError(f"cannot write image {path}: {why}; choose another path") from None
    if not ok:
        raise DataError(f"cannot write image {path}: check that its folder is writable")
    return path


def colorize_depth(depth_m: np.ndarray, max_depth_m: float | None = None) -> np.ndarray:
    """(H, W) metric depth -> (H, W, 3) uint8 RGB turbo colours, near = red, far = blue, invalid = black.

    ``max_depth_m`` defaults to the 99th percentile of the valid depths.
    """
    valid = np.isfinite(depth_m) & (depth_m > 0)
    if max_depth_m is None:
        max_depth_m = float(np.percentile(depth_m[valid], 99)) if valid.any() else 1.0
    t = np.clip(np.where(valid, depth_m, 0) / max(max_depth_m, 1e-6), 0.0, 1.0)
    grey = np.round(255.0 * (1.0 - t)).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[~valid] = 0
    return rgb


def render_preview(
    image_rgb: np.ndarray, depth_m: np.ndarray | None = None, label_ids: np.ndarray | None = None
) -> np.ndarray:
    """Panels side by side: image | depth (if given) | labels (if given); (H, k*W, 3) uint8 RGB."""
    panels = [check_image(image_rgb)]
    if depth_m is not None:
        panels.append(colorize_depth(depth_m))
    if label_ids is not None:
        panels.append(colorize_labels(label_ids))
    return np.concatenate(panels, axis=1)


def open_model(
    model_path: Path | str, card_path: Path | str | None = None, threads: int = 2
) -> DepthModel | SegmentationModel:
    """The adapter the card asks for (``DepthModel`` or ``SegmentationModel``).

    Raises:
        ModelError: the model file is missing (named before its card), or what the card or adapter raise.
    """
    if not Path(model_path).is_file():
        what = "is a folder" if Path(model_path).is_dir() else "does not exist"
        raise ModelError(f"model file {model_path} {what} (pass the path of an .onnx file)")
    card = load_card(model_path, card_path)
    cls = DepthModel if card.task is TaskKind.DEPTH else SegmentationModel
    return cls(model_path, card, threads=threads)


def check_model(
    model_path: Path | str,
    card_path: Path | str | None = None,
    image_path: Path | str | None = None,
    preview_path: Path | str | None = None,
    *,
    runs: int = 5,
    threads: int = 2,
    intrinsics: Intrinsics | None = None,
) -> ModelReport:
    """Validate a model + card, run it ``runs`` times on one image, report and optionally write a preview.

    Args:
        model_path: the .onnx file.
        card_path: its card; default the YAML next to the model.
        image_path: an image to run on; default ``synthetic_test_image()`` (1242 x 375, KITTI size).
        preview_path: where to write the preview PNG (image | depth | labels); None = no preview.
        runs: timed runs after one warm-up; timings are medians.
        threads: intra-op threads.
        intrinsics: for disparity cards with ``baseline_m``; default KITTI-like nominal intrinsics.

    Raises:
        ModelError: the card is missing/invalid or does not fit the model.
        DataError: the image cannot be read, or the preview path is not an image file name.
    """
    model_path = Path(model_path)
    if preview_path is not None:
        _check_image_suffix(Path(preview_path))  # before the model runs
    model = open_model(model_path, card_path, threads=threads)
    image = read_image_rgb(image_path) if image_path is not None else synthetic_test_image()
    H, W = image.shape[:2]
    notes = []
    kwargs = {}
    if isinstance(model, DepthModel):
        if model.needs_intrinsics and intrinsics is None:
            fx = KITTI_FX_PER_WIDTH * W
            intrinsics = Intrinsics(fx, fx, (W - 1) / 2, (H - 1) / 2, W, H)
            notes.append(f"nominal intrinsics fx = {fx:.1f} px (KITTI-like) for the disparity conversion")
        kwargs["intrinsics"] = intrinsics
    timings = measure_overhead(model, image, repeats=runs, **kwargs)
    result = model.predict(image, **kwargs)
    if isinstance(model, SegmentationModel) and model.last_unlisted[1] > 0:
        largest, share = model.last_unlisted
        notes.append(
            f"{100 * share:.1f} % of the pixels have class indices up to {largest}, beyond the "
            f"{model.class_to_train_id.size} classes the card lists (output.classes); they read as ignore: list "
            "every model class in output order"
        )
    if isinstance(model, DepthModel) and (clamped := clamp_note(result, model.card.output)) is not None:
        notes.append(clamped)
    report = _describe(
        model,
        result,
        card_path=Path(card_path) if card_path is not None else default_card_path(model_path),
        image_source=str(image_path) if image_path is not None else f"synthetic {W}x{H} test image",
        timings_ms={k: v for k, v in timings.items() if k != "repeats"},
        notes=notes,
    )
    if preview_path is not None:
        depth = result if isinstance(model, DepthModel) else None
        labels = result if isinstance(model, SegmentationModel) else None
        report.preview_path = write_png(preview_path, render_preview(image, depth, labels))
    return report


CLAMPED_SHARE = 0.5
"""``check-model`` notes a depth output whose valid pixels sit at the card's ``min_depth_m`` or ``max_depth_m`` for
more than this share: clamped, not measured (a wrong output kind or scale; inverse depth declared metric reads
0.1-0.15 m, every pixel at the lower bound)."""


def clamp_note(depth_m: np.ndarray, output) -> str | None:
    """A note when most valid (> 0) pixels of ``depth_m`` (H, W, metres) sit at a bound of ``output`` (the card's
    depth output: ``min_depth_m``, ``max_depth_m``), else None."""
    values = depth_m[depth_m > 0]
    if not values.size:
        return None
    for bound, what in ((output.min_depth_m, "min_depth_m"), (output.max_depth_m, "max_depth_m")):
        share = float(np.mean(np.isclose(values, bound, rtol=1e-5, atol=1e-6)))
        if share > CLAMPED_SHARE:
            return (f"{100 * share:.0f} % of the valid depth sits at the card's {what} ({bound:g} m): clamped, not "
                    "measured; check output.kind and its scale (an inverse or disparity output declared metric, or "
                    "the reverse?) with --preview on a frame whose distances you know")
    return None


def _describe(
    model: OnnxModel,
    result: np.ndarray,
    *,
    card_path: Path,
    image_source: str,
    timings_ms: dict[str, float],
    notes: list[str],
) -> ModelReport:
    """Shapes and value statistics of one model output on the image grid."""
    label_fractions: dict[str, float] = {}
    if isinstance(model, DepthModel):
        valid = result > 0
        values = result[valid]
    else:
        valid = result != IGNORE_ID
        values = result[valid]
        ids, counts = np.unique(result, return_counts=True)
        order = np.argsort(-counts)
        label_fractions = {label_name(int(ids[i])): float(counts[i] / result.size) for i in order}
    return ModelReport(
        model_path=model.model_path,
        card_path=card_path,
        task=model.task,
        providers=list(model.providers),
        input_name=model.input_spec.name,
        input_shape=model.input_spec.shape,
        input_type=model.input_spec.type,
        output_name=model.output_spec.name,
        output_shape=model.output_spec.shape,
        output_type=model.output_spec.type,
        image_source=image_source,
        image_wh=(result.shape[1], result.shape[0]),
        fed_shape=model.last_input_shape,
        raw_output_shape=model.last_output_shape,
        value_min=float(values.min()) if values.size else float("nan"),
        value_max=float(values.max()) if values.size else float("nan"),
        valid_fraction=float(valid.mean()),
        timings_ms=timings_ms,
        label_fractions=label_fractions,
        notes=notes,
    )
