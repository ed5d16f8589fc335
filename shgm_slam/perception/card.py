"""Model cards: the YAML that tells the adapters how to feed an ONNX model and read its output.

A card sits next to the model with the same stem (``depth.onnx`` + ``depth.yaml``) or is passed
explicitly. Example of a depth card::

    task: depth
    input:  {layout: NCHW, size: [640, 192], resize: stretch, color_order: RGB,
             scale: 1/255, mean: [0.485, 0.456, 0.406], std: [0.229, 0.224, 0.225]}
    output: {name: depth, kind: metric, min_depth_m: 0.5, max_depth_m: 80}

and of a segmentation card for an ADE20K model (classes map to Cityscapes train ids)::

    task: segmentation
    input:  {size: [512, 512], resize: keep_aspect_pad, pad_value: 0}
    output: {kind: logits, classes: ade20k, mapping: {floor: 0}}

Input normalization, per model channel c: ``x = (pixel * scale - mean[c]) / std[c]`` with the
pixel in 0..255 (uint8-input models get the raw pixels). ``mean``/``std`` are in the model's
channel order (``color_order``).

Exporting a model (e.g. ``tools/``): pin ``ir_version <= 10`` and opset 17..21, give the batch axis a
symbolic name (``predict_batch`` then runs one session call), and for full-resolution segmentation
put the ArgMax inside the graph (``kind: label_map``): a 19-class argmax over 1242 x 375 costs
~5 ms in numpy/OpenCV on one core, inside the model it is nearly free.
"""

from __future__ import annotations

import difflib
import re
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from shgm_slam.errors import ModelError, parse_failure


class _CaseInsensitiveEnum(str, Enum):
    """String enum that parses its values case-insensitively (``nchw`` == ``NCHW``)."""

    @classmethod
    def _missing_(cls, value: object) -> Any:
        if isinstance(value, str):
            for member in cls:
                if member.value.lower() == value.lower().replace("-", "_"):
                    return member
        return None


class TaskKind(_CaseInsensitiveEnum):
    DEPTH = "depth"
    SEGMENTATION = "segmentation"


class Layout(_CaseInsensitiveEnum):
    NCHW = "NCHW"
    NHWC = "NHWC"


class ResizeMode(_CaseInsensitiveEnum):
    STRETCH = "stretch"  # resize to the model size, aspect ratio changes
    KEEP_ASPECT_PAD = "keep_aspect_pad"  # letterbox: fit inside, pad the rest with pad_value
    KEEP_ASPECT_CROP = "keep_aspect_crop"  # fill the model size, crop the centre (borders get no output)


class Interpolation(_CaseInsensitiveEnum):
    AUTO = "auto"  # area when shrinking by 2x or more, else bilinear (fast; matches most training code)
    LINEAR = "linear"
    AREA = "area"
    CUBIC = "cubic"
    NEAREST = "nearest"


class ColorOrder(_CaseInsensitiveEnum):
    RGB = "RGB"
    BGR = "BGR"


class InputDtype(_CaseInsensitiveEnum):
    FLOAT32 = "float32"  # normalized floats; a float16 or double input gets them cast to its type
    UINT8 = "uint8"  # raw pixels


class DepthKind(_CaseInsensitiveEnum):
    METRIC = "metric"  # depth_m = x
    INVERSE = "inverse"  # depth_m = 1 / (scale * x + shift)
    RELATIVE = "relative"  # depth_m = scale * x + shift
    DISPARITY = "disparity"  # depth_m = focal_x_baseline / disparity


class SegOutputKind(_CaseInsensitiveEnum):
    LOGITS = "logits"  # per-class scores; argmax over the class axis (C of NCHW, or last of NHWC)
    LABEL_MAP = "label_map"  # one class index per pixel


class LabelSpace(_CaseInsensitiveEnum):
    """Named class lists a card can give instead of spelling out ``classes``."""

    CITYSCAPES = "cityscapes"  # the 19 Cityscapes train classes (identity mapping)
    ADE20K = "ade20k"  # the 150 SceneParse150 classes (perception/labels.py maps them)


class _CardPart(BaseModel):
    model_config = ConfigDict(extra="forbid", use_enum_values=False, frozen=True, allow_inf_nan=False)


MAX_NORMALIZED_INPUT = 1e4
"""Largest magnitude the input normalization may give a pixel (0..255): beyond it the scale, mean or std are
wrong (ImageNet's normalization gives at most ~2.6, raw pixels 255)."""


def _parse_fraction(value: Any) -> Any:
    """Accept ``1/255`` style strings for scale factors (YAML has no expressions)."""
    if isinstance(value, str) and "/" in value:
        num, _, den = value.partition("/")
        try:
            return float(num) / float(den)
        except (ValueError, ZeroDivisionError):
            raise ValueError(f"cannot read {value!r} as a fraction like 1/255") from None
    return value


class InputSpec(_CardPart):
    """How images are turned into the model's input tensor.

    ``size`` is ``[W, H]`` for a model with a fixed input size (a model whose input dims are fixed
    in the graph needs none: the adapter reads them). ``size: null`` + ``multiple_of`` declares a
    model that takes any size: the image is then padded/cropped/stretched to a multiple of it.
    """

    name: str | None = Field(None, description="input tensor name; default: the model's only input")
    layout: Layout = Layout.NCHW
    size: tuple[int, int] | None = Field(None, description="[W, H] pixels fed to the model")
    multiple_of: int | None = Field(None, ge=1, description="any-size models: W and H multiples of this")
    resize: ResizeMode = ResizeMode.STRETCH
    interpolation: Interpolation = Interpolation.AUTO
    pad_value: float = Field(0.0, ge=0, le=255, description="padding colour, 0..255 pixel units")
    color_order: ColorOrder = ColorOrder.RGB
    scale: float | None = Field(None, gt=0, description="pixel factor; default 1/255 (float32), 1 (uint8)")
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    dtype: InputDtype = InputDtype.FLOAT32

    _scale = field_validator("scale", mode="before")(_parse_fraction)

    @field_validator("size")
    @classmethod
    def _positive_size(cls, size: tuple[int, int] | None) -> tuple[int, int] | None:
        if size is not None and min(size) < 1:
            raise ValueError(f"size must be [W, H] with positive entries, got {list(size)}")
        return size

    @field_validator("std")
    @classmethod
    def _nonzero_std(cls, std: tuple[float, float, float]) -> tuple[float, float, float]:
        if any(s == 0 for s in std):
            raise ValueError("std entries must be non-zero")
        return std

    @model_validator(mode="after")
    def _uint8_is_raw(self) -> InputSpec:
        if self.dtype is InputDtype.UINT8 and (
            self.scale not in (None, 1.0) or self.mean != (0.0, 0.0, 0.0) or self.std != (1.0, 1.0, 1.0)
        ):
            raise ValueError("uint8 inputs take raw 0..255 pixels: drop scale/mean/std or use dtype float32")
        return self

    @model_validator(mode="after")
    def _normalization_is_plausible(self) -> InputSpec:
        pixels = [0.0, 255.0 * self.effective_scale]
        largest = max(abs((p - m) / s) for p in pixels for m, s in zip(self.mean, self.std, strict=True))
        if largest > MAX_NORMALIZED_INPUT:
            raise ValueError(
                f"scale, mean and std map pixels 0..255 to values up to {largest:.3g} (more than "
                f"{MAX_NORMALIZED_INPUT:g}): check them (ImageNet: scale 1/255, mean [0.485, 0.456, 0.406], "
                "std [0.229, 0.224, 0.225])"
            )
        return self

    @property
    def effective_scale(self) -> float:
        """The pixel multiplier actually applied (1/255 for float32 inputs unless the card says otherwise)."""
        if self.scale is not None:
            return self.scale
        return 1.0 if self.dtype is InputDtype.UINT8 else 1.0 / 255.0


class DepthOutputSpec(_CardPart):
    """How the depth output becomes metric z-depth in metres.

    Disparity is in pixels of the model *input*; ``focal_x_baseline`` is fx in pixels of the
    original image times the stereo baseline in metres (or give ``baseline_m`` and the adapter uses
    the frame's fx). The adapter converts for any resize in between.
    """

    name: str | None = Field(None, description="output tensor name; default: the model's only output")
    kind: DepthKind = DepthKind.METRIC
    scale: float = 1.0
    shift: float = 0.0
    focal_x_baseline: float | None = Field(None, gt=0, description="disparity: fx [px] * baseline [m]")
    baseline_m: float | None = Field(None, gt=0, description="disparity: baseline; fx from the frame")
    min_depth_m: float = Field(0.1, ge=0)
    max_depth_m: float = Field(80.0, gt=0)

    _scale = field_validator("scale", "shift", mode="before")(_parse_fraction)

    @model_validator(mode="after")
    def _consistent(self) -> DepthOutputSpec:
        if self.kind is DepthKind.DISPARITY and (self.focal_x_baseline is None) == (self.baseline_m is None):
            raise ValueError("kind disparity needs exactly one of focal_x_baseline or baseline_m")
        if self.min_depth_m >= self.max_depth_m:
            raise ValueError(f"min_depth_m {self.min_depth_m} must be below max_depth_m {self.max_depth_m}")
        if self.kind in (DepthKind.METRIC, DepthKind.DISPARITY) and (self.scale, self.shift) != (1.0, 0.0):
            raise ValueError(
                f"scale and shift apply to kind inverse and relative; a {self.kind.value} output is used as it is, "
                "so they would be ignored: drop them (or give the kind they belong to)"
            )
        return self


class SegOutputSpec(_CardPart):
    """How the segmentation output becomes Cityscapes train ids.

    ``classes`` names the model's classes in output order (or a ``LabelSpace`` name);
    ``mapping`` maps a model class (index or name) to a train id, a Cityscapes class name, or
    255 / ``ignore``. Classes without an entry map by name when they are Cityscapes classes
    (or by the label space's table); any class left unmapped is an error.
    """

    name: str | None = Field(None, description="output tensor name; default: the model's only output")
    kind: SegOutputKind = SegOutputKind.LOGITS
    layout: Layout | None = Field(None, description="logits layout; default: the input layout")
    classes: tuple[str, ...] | LabelSpace = LabelSpace.CITYSCAPES
    mapping: dict[int | str, int | str] = Field(default_factory=dict)

    @field_validator("mapping")
    @classmethod
    def _index_keys(cls, mapping: dict[int | str, int | str]) -> dict[int | str, int | str]:
        """Keys "3" (YAML/JSON strings) mean class index 3."""
        return {int(k) if isinstance(k, str) and k.strip().isdigit() else k: v for k, v in mapping.items()}

    @field_validator("classes")
    @classmethod
    def _some_classes(cls, classes: tuple[str, ...] | LabelSpace) -> tuple[str, ...] | LabelSpace:
        if isinstance(classes, tuple) and len(classes) == 0:
            raise ValueError("classes must name at least one class")
        return classes


class _CardBase(_CardPart):
    name: str | None = None
    description: str | None = None
    source: str | None = Field(None, description="where the model comes from (URL, training script)")
    license: str | None = None
    input: InputSpec = InputSpec()


class DepthCard(_CardBase):
    """Card of a monocular depth model."""

    task: Literal[TaskKind.DEPTH]
    output: DepthOutputSpec = DepthOutputSpec()


class SegmentationCard(_CardBase):
    """Card of a semantic segmentation model."""

    task: Literal[TaskKind.SEGMENTATION]
    output: SegOutputSpec = SegOutputSpec()


ModelCard = Annotated[DepthCard | SegmentationCard, Field(discriminator="task")]
_CARD_ADAPTER: TypeAdapter[DepthCard | SegmentationCard] = TypeAdapter(ModelCard)
CARD_SUFFIXES = (".yaml", ".yml")


def default_card_path(model_path: Path | str) -> Path:
    """The card path next to a model: same stem, ``.yaml`` (or an existing ``.yml``)."""
    model_path = Path(model_path)
    for suffix in CARD_SUFFIXES:
        if model_path.with_suffix(suffix).is_file():
            return model_path.with_suffix(suffix)
    return model_path.with_suffix(".yaml")


def parse_card(data: Any, where: str = "model card") -> DepthCard | SegmentationCard:
    """Validate a card given as a mapping (as read from YAML).

    Raises:
        ModelError: naming ``where`` and the first invalid field.
    """
    if not isinstance(data, dict):
        raise ModelError(f"{where} must be a YAML mapping with task/input/output, got {type(data).__name__}")
    data = dict(data)
    if "task" not in data:
        raise ModelError(f"{where}: field 'task' is missing: add `task: depth` or `task: segmentation`")
    if isinstance(data["task"], str):
        data["task"] = data["task"].lower()
    try:
        return _CARD_ADAPTER.validate_python(data)
    except ValidationError as exc:
        first = _first_error(exc)
        tags = {t.value for t in TaskKind}
        field = ".".join(str(p) for p in first["loc"][1:] if str(p) not in tags) or "task"
        if first["type"] == "union_tag_invalid":
            raise ModelError(
                f"{where}: field 'task' must be 'depth' or 'segmentation', got {data['task']!r}"
            ) from None
        raise ModelError(
            f"{where}: field '{field}': {first['msg']}{_hint(first, data['task'])} ({exc.error_count()} error(s); "
            "the card format is documented in shgm_slam/perception/card.py)"
        ) from None


def _first_error(exc: ValidationError) -> Any:
    """pydantic's first error; for a field of several types (``classes``: a list or a label space name, whose
    errors are located at ``classes.tuple[str, ...]``) one error on the field itself that names both."""
    first = exc.errors()[0]
    if not first["loc"] or "[" not in str(first["loc"][-1]):
        return first
    field = first["loc"][:-1]
    names = [e for e in exc.errors() if e["type"] == "enum" and e["loc"][:-1] == field]
    if not names:
        return {**first, "loc": field}
    return {**names[0], "loc": field, "msg": f"Input should be a list of class names, or {names[0]['ctx']['expected']}"}


def _hint(error: Any, task: Any) -> str:
    """'; did you mean X?' for a misspelt field or choice (``error``: pydantic's first error), else the fields
    allowed there for an unknown field; '' otherwise."""
    if error["type"] == "enum":
        choices = re.findall(r"'([^']*)'", error.get("ctx", {}).get("expected", ""))
        by_lower = {c.lower(): c for c in choices}
        close = difflib.get_close_matches(str(error["input"]).lower(), list(by_lower), n=1)
        return f", got {error['input']!r}" + (f"; did you mean {by_lower[close[0]]!r}?" if close else "")
    if error["type"] != "extra_forbidden":
        return ""
    part: Any = DepthCard if task == TaskKind.DEPTH.value else SegmentationCard
    for name in error["loc"][1:-1]:  # the section (input, output) holding the unknown field
        part = part.model_fields[name].annotation if name in part.model_fields else None
        if not (isinstance(part, type) and issubclass(part, BaseModel)):
            return ""
    known = [k for k in part.model_fields if k != "task"]
    close = difflib.get_close_matches(str(error["loc"][-1]), known, n=1)
    return f"; did you mean {close[0]}?" if close else f"; known here: {', '.join(known)}"


def load_card(model_path: Path | str, card_path: Path | str | None = None) -> DepthCard | SegmentationCard:
    """Load the card of ``model_path``: ``card_path`` if given, else the YAML next to the model.

    Raises:
        ModelError: the card is missing, is not YAML, or has a missing/invalid field.
    """
    path = Path(card_path) if card_path is not None else default_card_path(model_path)
    if not path.is_file():
        raise ModelError(
            f"model card {path} not found for model {model_path}: write a YAML card with task/input/output "
            "next to the model (same stem) or pass it with --card"
        )
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ModelError(f"model card {path} is not valid YAML: {exc}") from None
    except (ValueError, RecursionError) as exc:  # an integer of thousands of digits, nesting too deep
        raise ModelError(f"model card {path} cannot be read: {parse_failure(exc)}") from None
    return parse_card(data, where=f"model card {path}")


def card_to_yaml(card: DepthCard | SegmentationCard) -> str:
    """The card as YAML text that ``load_card`` reads back (defaults omitted)."""
    data = card.model_dump(mode="json", exclude_defaults=True)
    data = {"task": card.task.value, **data}
    return yaml.safe_dump(data, sort_keys=False)


def write_card(card: DepthCard | SegmentationCard, path: Path | str) -> Path:
    """Write ``card`` as YAML to ``path`` (e.g. next to an exported model); returns the path."""
    path = Path(path)
    path.write_text(card_to_yaml(card))
    return path
