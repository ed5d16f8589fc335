"""ONNX Runtime sessions and the shared adapter: card validation, preprocessing, resize geometry.

``OnnxModel`` opens one session per model (CUDA first when available, else CPU; a few intra-op
threads, no spinning: the CPU is shared with KISS-ICP), checks the card against the model's real
inputs and outputs, turns RGB images into the input tensor (resize / pad / crop per
``perception/resize.py``, colour order, scale/mean/std, layout) and records per-call
``PerceptionTimings``. ``DepthModel`` and
``SegmentationModel`` add the output side.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
import onnxruntime as ort

from shgm_slam.errors import DataError, ModelError
from shgm_slam.perception.card import (
    ColorOrder,
    DepthCard,
    InputDtype,
    Interpolation,
    Layout,
    SegmentationCard,
    TaskKind,
    load_card,
)
from shgm_slam.perception.resize import ResizePlan, any_size_target, plan_resize

MAX_IR_VERSION_HINT = 10
MAX_OPSET_HINT = 21
_FLOAT_TYPES = ("tensor(float)", "tensor(float16)", "tensor(double)")
_CV_INTERPOLATION = {
    Interpolation.LINEAR: cv2.INTER_LINEAR,
    Interpolation.AREA: cv2.INTER_AREA,
    Interpolation.CUBIC: cv2.INTER_CUBIC,
    Interpolation.NEAREST: cv2.INTER_NEAREST,
}
_INPUT_TYPES = {
    InputDtype.FLOAT32: ("tensor(float)", np.float32),
    InputDtype.UINT8: ("tensor(uint8)", np.uint8),
}
_FLOAT_INPUTS = {"tensor(float)": np.float32, "tensor(float16)": np.float16, "tensor(double)": np.float64}
"""Float input types a ``dtype: float32`` card feeds: the normalized image is cast to the model's own type."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PerceptionTimings:
    """Wall-clock milliseconds of one adapter call (a whole batch for ``predict_batch``)."""

    preprocess_ms: float = 0.0
    inference_ms: float = 0.0
    postprocess_ms: float = 0.0

    @property
    def overhead_ms(self) -> float:
        """Time spent outside the model: preprocessing + postprocessing."""
        return self.preprocess_ms + self.postprocess_ms

    @property
    def total_ms(self) -> float:
        return self.preprocess_ms + self.inference_ms + self.postprocess_ms

    def as_dict(self, prefix: str = "") -> dict[str, float]:
        """``{prefix}preprocess`` / ``inference`` / ``postprocess`` in ms."""
        return {
            f"{prefix}preprocess": self.preprocess_ms,
            f"{prefix}inference": self.inference_ms,
            f"{prefix}postprocess": self.postprocess_ms,
        }


@dataclass(frozen=True)
class TensorSpec:
    """A model input/output as ONNX Runtime reports it; dims are int, str (symbolic) or None."""

    name: str
    shape: tuple[int | str | None, ...]
    type: str

    @staticmethod
    def of(node: Any) -> TensorSpec:
        return TensorSpec(node.name, tuple(node.shape), node.type)


def execution_providers() -> list[str]:
    """CUDA first when this onnxruntime build has it, CPU always."""
    available = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


def open_session(
    model_path: Path | str,
    *,
    threads: int = 2,
    free_dims: dict[str, int] | None = None,
    providers: Sequence[str] | None = None,
) -> ort.InferenceSession:
    """Open an ONNX Runtime session tuned for a shared CPU.

    Args:
        model_path: the .onnx file.
        threads: intra-op threads (0 = onnxruntime's default, all physical cores).
        free_dims: symbolic dimension name -> fixed value (pins dynamic axes, e.g. height/width).
        providers: execution providers; default ``execution_providers()``.

    Raises:
        ModelError: the file is missing or corrupt, or its IR version / opset is newer than this
            onnxruntime reads (the message names the re-export fix).
    """
    model_path = Path(model_path)
    if not model_path.is_file():
        raise ModelError(f"model file {model_path} does not exist (pass the path of an .onnx file)")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 4  # fatal only: a failing run raises, and onnxruntime's own log line would precede ours
    for name, value in (free_dims or {}).items():
        so.add_free_dimension_override_by_name(name, int(value))
    try:
        return ort.InferenceSession(
            str(model_path), sess_options=so, providers=list(providers or execution_providers())
        )
    except Exception as exc:  # onnxruntime raises its own pybind classes, all plain Exception subclasses
        raise ModelError(_explain_load_error(model_path, str(exc))) from None


_ORT_PREFIX = re.compile(r"^\s*\[ONNXRuntimeError\]\s*:\s*\d+\s*:\s*\w+\s*:\s*")
"""The ``[ONNXRuntimeError] : 1 : FAIL : `` head of onnxruntime's messages."""
_ORT_SOURCE = re.compile(r"^/\S+:\d+ .*?\) (?=[A-Z])")
"""The ``/onnxruntime_src/...h:46 void f(...) `` source location and C++ signature some messages start with."""
_UNKNOWN_OP = re.compile(
    r"(?:Fatal error: (?P<custom>\S+?)\(-?\d+\) is not a registered function/op)"
    r"|(?:No Op registered for (?P<op>\S+) with domain_version of (?P<version>\d+))"
)
_MISSING_DOMAIN = re.compile(r"No opset import for domain '(?P<domain>[^']*)'")
_OPSET_LIMIT = re.compile(r"Opset (?P<opset>\d+) is under development.*?till opset (?P<limit>\d+)", re.S)
_EXTERNAL_DATA = re.compile(r'External data path does not exist: "?(?P<path>[^"\n]+)"?')
_ORT_SOURCE_ANYWHERE = re.compile(r"/\S+\.(?:h|cc|cpp):\d+ [^()]*\([^)]*\) ")
"""A ``/onnxruntime_src/...h:91 void f(...) `` source location and C++ signature inside a message."""


def _explain_run_error(message: str) -> str:
    """onnxruntime's message on a failed ``session.run`` without its prefix and C++ source locations (one line)."""
    detail = _ORT_SOURCE_ANYWHERE.sub("", _ORT_PREFIX.sub("", message.strip()))
    return " ".join(detail.replace("Status Message: ", "").split())[:300]


def _explain_load_error(model_path: Path, message: str) -> str:
    """One line on why onnxruntime refused ``model_path`` (its ``message``), with what to do about it."""
    detail = " ".join(_ORT_SOURCE.sub("", _ORT_PREFIX.sub("", message.strip())).split())
    if (unknown := _UNKNOWN_OP.search(message)) is not None:
        if unknown["custom"]:
            op, why = unknown["custom"], "a custom operator of another runtime"
        else:
            op, why = unknown["op"], f"not an ONNX operator of opset {unknown['version']}, which the model imports"
        return (
            f"model {model_path} uses the operator {op}, which onnxruntime {ort.__version__} does not implement "
            f"({why}): re-export it with standard ONNX operators of opset <= {MAX_OPSET_HINT}"
        )
    if (missing := _MISSING_DOMAIN.search(message)) is not None:
        return (
            f"model {model_path} is invalid: a node uses the operator domain '{missing['domain']}', which the "
            "model does not import (opset_imports): re-export it with standard ONNX operators only"
        )
    fix = (
        f"re-export it with ir_version <= {MAX_IR_VERSION_HINT} and opset <= {MAX_OPSET_HINT} "
        f"(onnx: helper.make_model(..., ir_version={MAX_IR_VERSION_HINT}, opset_imports=[make_opsetid('', "
        f"{MAX_OPSET_HINT})]); torch: torch.onnx.export(..., opset_version={MAX_OPSET_HINT}))"
    )
    newer = f"is newer than onnxruntime {ort.__version__} reads"
    if "IR version" in message:
        return f"model {model_path}: its ONNX IR version {newer} ({detail}): {fix}"
    if (opset := _OPSET_LIMIT.search(message)) is not None:
        return f"model {model_path}: its opset {opset['opset']} {newer} (up to {opset['limit']}): {fix}"
    if "opset" in message.lower():
        return f"model {model_path}: its opset {newer} ({detail[-90:]}): {fix}"
    if (data := _EXTERNAL_DATA.search(message)) is not None:
        return (
            f"model {model_path} keeps its weights in the file {data['path']}, which does not exist: put the weights "
            "file the export wrote beside the model, under that name"
        )
    if "protobuf" in message.lower():
        return f"model {model_path} is not a valid ONNX file (protobuf parsing failed): re-export it"
    return f"model {model_path} cannot be loaded by onnxruntime {ort.__version__}: {detail[:300]}"


def check_image(image_rgb: Any, where: str = "image_rgb") -> np.ndarray:
    """Validate an RGB image: (H, W, 3) uint8 (grayscale (H, W) / (H, W, 1) is replicated to 3 channels).

    Raises:
        DataError: not an array of that shape and dtype.
    """
    if not isinstance(image_rgb, np.ndarray):
        raise DataError(f"{where} must be an (H, W, 3) uint8 numpy array, got {type(image_rgb).__name__}")
    img = image_rgb
    if img.dtype != np.uint8:
        raise DataError(f"{where} must be uint8 (0..255), got dtype {img.dtype}: convert it to uint8 RGB")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise DataError(f"{where} must have shape (H, W, 3), got {img.shape}")
    return img


class OnnxModel:
    """Base adapter: one ONNX model + its card, with validation and preprocessing.

    Args:
        model_path: the .onnx file.
        card: a parsed card, a card path, or None for the YAML next to the model.
        threads: intra-op threads of the session (0 = onnxruntime default).
        providers: execution providers; default CUDA when available, else CPU.

    Attributes:
        last_timings: ``PerceptionTimings`` of the latest call.
        input_spec / output_spec: the model's tensors as the session reports them (after pinning).
        batch_size: images per session call (a fixed batch axis, one for an output without a batch axis or a
            model that failed on a batch), or None: every image of a ``predict_batch`` in one call.
        batch_why: why ``batch_size`` is set (for people: ``perceive`` reports it), or None.
    """

    task: ClassVar[TaskKind]

    def __init__(
        self,
        model_path: Path | str,
        card: DepthCard | SegmentationCard | Path | str | None = None,
        threads: int = 2,
        providers: Sequence[str] | None = None,
    ) -> None:
        self.model_path = Path(model_path)
        if not self.model_path.is_file():
            raise ModelError(f"model file {self.model_path} does not exist (pass the path of an .onnx file)")
        if card is None or isinstance(card, (str, Path)):
            card = load_card(self.model_path, card)
        if card.task is not self.task:
            raise ModelError(
                f"the card of {self.model_path} says task '{card.task.value}' but a {self.task.value} model "
                f"was expected: fix `task:` in the card or pass the model as the right kind"
            )
        self.card = card
        self.where = f"model {self.model_path.name}"
        session = open_session(self.model_path, threads=threads, providers=providers)
        self.input_spec = self._select_input(session)
        self.fixed_wh, free_dims = self._resolve_size()
        if free_dims:
            session = open_session(self.model_path, threads=threads, free_dims=free_dims, providers=providers)
            self.input_spec = self._select_input(session)
        self.session = session
        self.output_spec = self._select_output(session, card.output.name)
        self._check_output(self.output_spec)
        self.providers: list[str] = session.get_providers()
        batch = self.input_spec.shape[0]
        self.batch_size: int | None = batch if isinstance(batch, int) and batch > 0 else None
        self.batch_why: str | None = None
        if self.batch_size is not None:
            self.batch_why = f"its input '{self.input_spec.name}' has a fixed batch axis of {self.batch_size}"
        self._output_batched = len(self.output_spec.shape) != 2
        if not self._output_batched:  # an (H, W) map: one image per session call
            self.batch_why = f"its output '{self.output_spec.name}' has no batch axis"
            if self.batch_size not in (None, 1):
                raise ModelError(
                    f"{self.where}: output '{self.output_spec.name}' (shape {list(self.output_spec.shape)}) has no "
                    f"batch axis but input '{self.input_spec.name}' takes a batch of {self.batch_size}: export the "
                    "model with a batch axis on its output"
                )
            self.batch_size = 1
        self._input_dtype = _INPUT_TYPES[card.input.dtype][1]
        self._feed_dtype = _FLOAT_INPUTS.get(self.input_spec.type, self._input_dtype)
        self._prepare_normalization()
        self.last_timings = PerceptionTimings()
        self.last_input_shape: tuple[int, ...] = ()
        self.last_output_shape: tuple[int, ...] = ()

    # --- validation ---------------------------------------------------------------------------------
    def _select_input(self, session: ort.InferenceSession) -> TensorSpec:
        inputs = [TensorSpec.of(i) for i in session.get_inputs()]
        spec = self.card.input
        names = ", ".join(i.name for i in inputs)
        if spec.name is not None and spec.name not in {i.name for i in inputs}:
            raise ModelError(
                f"{self.where}: card input.name '{spec.name}' is not an input of the model (inputs: {names})"
            )
        if len(inputs) > 1:  # inputs with defaults (initializers) are not listed: these all need a value
            raise ModelError(
                f"{self.where} needs {len(inputs)} inputs ({names}) but the adapter feeds one, the image: export the "
                "model with the image as its only input (the others as constants, or with default values)"
            )
        tensor = inputs[0]
        if len(tensor.shape) != 4:
            raise ModelError(
                f"{self.where}: input '{tensor.name}' has rank {len(tensor.shape)} (shape "
                f"{list(tensor.shape)}); the adapter feeds rank-4 image batches ({spec.layout.value}): "
                "export the model with a batch axis"
            )
        c_axis = 1 if spec.layout is Layout.NCHW else 3
        channels = tensor.shape[c_axis]
        if not isinstance(channels, int) and tensor.shape[4 - c_axis] == 3:
            other = Layout.NHWC if spec.layout is Layout.NCHW else Layout.NCHW
            raise ModelError(
                f"{self.where}: input '{tensor.name}' (shape {list(tensor.shape)}) has 3 channels on axis "
                f"{4 - c_axis}, not on axis {c_axis} as input.layout {spec.layout.value} says: set layout: "
                f"{other.value} in the card"
            )
        if isinstance(channels, int) and channels != 3:
            other = Layout.NHWC if spec.layout is Layout.NCHW else Layout.NCHW
            hint = (
                f"the card's input.layout is probably wrong: set layout: {other.value}"
                if tensor.shape[4 - c_axis] == 3
                else "the adapter feeds 3-channel RGB images: use a 3-channel model"
            )
            raise ModelError(
                f"{self.where}: input '{tensor.name}' has {channels} channel(s) on axis {c_axis} "
                f"({spec.layout.value}, shape {list(tensor.shape)}); {hint}"
            )
        want_type = _INPUT_TYPES[spec.dtype][0]
        fits = tensor.type in _FLOAT_INPUTS if spec.dtype is InputDtype.FLOAT32 else tensor.type == want_type
        if not fits:
            fix = (
                "fix input.dtype in the card (float32 for float, float16 and double inputs; uint8)"
                if tensor.type in (*_FLOAT_INPUTS, "tensor(uint8)")
                else "the adapter feeds float or uint8 images: export the model with such an input"
            )
            raise ModelError(
                f"{self.where}: input '{tensor.name}' is {tensor.type} but the card says input.dtype "
                f"{spec.dtype.value} ({want_type}): {fix}"
            )
        return tensor

    def _hw_axes(self) -> tuple[int, int]:
        return (2, 3) if self.card.input.layout is Layout.NCHW else (1, 2)

    def _resolve_size(self) -> tuple[tuple[int, int] | None, dict[str, int]]:
        """Fixed (W, H) fed to the model (None = any size) and symbolic dims to pin."""
        spec = self.card.input
        h_axis, w_axis = self._hw_axes()
        dims = {"W": self.input_spec.shape[w_axis], "H": self.input_spec.shape[h_axis]}
        if spec.size is None:
            if all(isinstance(d, int) for d in dims.values()):
                return (int(dims["W"]), int(dims["H"])), {}  # type: ignore[arg-type]
            if spec.multiple_of is not None:
                return None, {}
            raise ModelError(
                f"{self.where}: input '{self.input_spec.name}' has dynamic height/width "
                f"(shape {list(self.input_spec.shape)}) and the card gives no size: set input.size: [W, H] "
                "(or input.multiple_of: 32 for a model that takes any image size)"
            )
        free: dict[str, int] = {}
        for axis_name, dim, want in (("W", dims["W"], spec.size[0]), ("H", dims["H"], spec.size[1])):
            if isinstance(dim, int) and dim != want:
                raise ModelError(
                    f"{self.where}: card input.size {list(spec.size)} (W, H) disagrees with the model's "
                    f"fixed {axis_name} = {dim} (input shape {list(self.input_spec.shape)}): fix input.size"
                )
            if isinstance(dim, str) and dim:
                free[dim] = want if free.get(dim, want) == want else -1
        return spec.size, {name: v for name, v in free.items() if v > 0}  # H, W sharing a name: unpinned

    def _select_output(self, session: ort.InferenceSession, name: str | None) -> TensorSpec:
        outputs = [TensorSpec.of(o) for o in session.get_outputs()]
        names = ", ".join(o.name for o in outputs)
        if name is not None:
            found = [o for o in outputs if o.name == name]
            if not found:
                raise ModelError(
                    f"{self.where}: card output.name '{name}' is not an output of the model "
                    f"(outputs: {names})"
                )
            return found[0]
        if len(outputs) == 1:
            return outputs[0]
        raise ModelError(f"{self.where} has {len(outputs)} outputs ({names}): set output.name in the card")

    def _check_output(self, output: TensorSpec) -> None:
        """Subclasses check rank/channels/dtype of their output."""

    # --- preprocessing ------------------------------------------------------------------------------
    def _prepare_normalization(self) -> None:
        spec = self.card.input
        order = [0, 1, 2] if spec.color_order is ColorOrder.RGB else [2, 1, 0]
        self._channel_order = np.array(order)
        std = np.asarray(spec.std, dtype=np.float64)
        self._gain = (spec.effective_scale / std).astype(np.float32)
        self._bias = (-np.asarray(spec.mean, dtype=np.float64) / std).astype(np.float32)
        pad = np.full(3, spec.pad_value)
        self._pad_input = (
            (pad * self._gain + self._bias).astype(self._input_dtype)
            if spec.dtype is InputDtype.FLOAT32
            else pad.astype(np.uint8)
        )

    def target_size(self, image_wh: tuple[int, int]) -> tuple[int, int]:
        """(W, H) of the model input for an image of ``image_wh``."""
        if self.fixed_wh is not None:
            return self.fixed_wh
        return any_size_target(image_wh, int(self.card.input.multiple_of or 1), self.card.input.resize)

    def _preprocess(self, images: Sequence[np.ndarray]) -> tuple[np.ndarray, list[ResizePlan]]:
        """Stack images into one input tensor; returns it and the per-image resize plans."""
        sizes = {(im.shape[1], im.shape[0]) for im in images}
        targets = {self.target_size(wh) for wh in sizes}
        if len(targets) != 1:
            raise DataError(
                f"{self.where} takes any image size, so a batch must hold images of one size; "
                f"got {sorted(sizes)}"
            )
        Wt, Ht = targets.pop()
        nchw = self.card.input.layout is Layout.NCHW
        shape = (len(images), 3, Ht, Wt) if nchw else (len(images), Ht, Wt, 3)
        blob = np.empty(shape, dtype=self._input_dtype)
        plans = []
        for i, image in enumerate(images):
            plan = plan_resize(
                (image.shape[1], image.shape[0]),
                (Wt, Ht),
                self.card.input.resize,
                fixed_size=self.fixed_wh is not None,
            )
            plans.append(plan)
            self._fill(blob[i], image, plan, nchw)
        return blob.astype(self._feed_dtype, copy=False), plans

    def _fill(self, out: np.ndarray, image: np.ndarray, plan: ResizePlan, nchw: bool) -> None:
        """Write one image into its (3, Ht, Wt) / (Ht, Wt, 3) slot of the input tensor."""
        sx0, sy0, sx1, sy1 = plan.src_box
        dx0, dy0, dx1, dy1 = plan.dst_box
        crop = image[sy0:sy1, sx0:sx1]
        dw, dh = dx1 - dx0, dy1 - dy0
        if (dw, dh) != (crop.shape[1], crop.shape[0]):
            flag = self._interpolation(crop.shape[1] / dw, crop.shape[0] / dh)
            crop = cv2.resize(crop, (dw, dh), interpolation=flag)
        if (dw, dh) != plan.target_wh:  # padding: fill the borders only
            Wt, Ht = plan.target_wh
            strips = ((slice(0, dy0), slice(0, Wt)), (slice(dy1, Ht), slice(0, Wt)),
                      (slice(dy0, dy1), slice(0, dx0)), (slice(dy0, dy1), slice(dx1, Wt)))  # fmt: skip
            for rows, cols in strips:
                if nchw:
                    out[:, rows, cols] = self._pad_input[:, None, None]
                else:
                    out[rows, cols, :] = self._pad_input
        planes = cv2.split(crop)  # contiguous channel planes (SIMD de-interleave)
        raw = self.card.input.dtype is InputDtype.UINT8
        for c, src_c in enumerate(self._channel_order):
            region = (out[c] if nchw else out[:, :, c])[dy0:dy1, dx0:dx1]
            if raw:
                region[...] = planes[src_c]
            else:
                np.multiply(planes[src_c], self._gain[c], out=region, dtype=np.float32)
                region += self._bias[c]

    def _interpolation(self, shrink_x: float, shrink_y: float) -> int:
        """cv2 flag for a resize that shrinks by ``shrink_x``, ``shrink_y`` (> 1 = smaller)."""
        mode = self.card.input.interpolation
        if mode is Interpolation.AUTO:
            return cv2.INTER_AREA if min(shrink_x, shrink_y) >= 2.0 else cv2.INTER_LINEAR
        return _CV_INTERPOLATION[mode]

    # --- inference ----------------------------------------------------------------------------------
    def _infer(self, blob: np.ndarray) -> np.ndarray:
        """Run the session on ``blob``, in chunks when the model's batch axis is fixed (or is dynamic in name only:
        a model that fails on a batch but runs one image is then fed one image per call)."""
        n = blob.shape[0]
        step = self.batch_size or n
        outs = []
        for start in range(0, n, step):
            chunk = blob[start : start + step]
            if chunk.shape[0] < step:  # fixed batch axis: pad the last chunk with copies
                chunk = np.concatenate([chunk, np.repeat(chunk[-1:], step - chunk.shape[0], axis=0)])
            try:
                out = self._run_session(chunk)
            except ModelError:
                if self.batch_size is not None or chunk.shape[0] == 1:
                    raise
                self._run_session(chunk[:1])  # one image fails too: that error
                log.warning("%s fails on a batch of %d images but runs one image: fed one image per call from now on",
                            self.where, chunk.shape[0])  # fmt: skip
                self.batch_size = 1
                self.batch_why = (f"it failed on a batch of {chunk.shape[0]} images (a batch axis dynamic in name "
                                  "only) but runs one image")  # fmt: skip
                return self._infer(blob)
            if out.ndim == 0 or out.shape[0] != chunk.shape[0]:
                raise ModelError(
                    f"{self.where}: output '{self.output_spec.name}' has shape {list(out.shape)} for a batch of "
                    f"{chunk.shape[0]} image(s); its first axis must hold one result per image: export the model "
                    "with the same batch axis on its input and output"
                )
            outs.append(out)
        out = outs[0] if len(outs) == 1 else np.concatenate(outs)
        self.last_output_shape = tuple(out.shape)
        return out[:n]

    def _run_session(self, chunk: np.ndarray) -> np.ndarray:
        """The output of one session call on ``chunk`` (with a batch axis added to an (H, W) output).

        Raises:
            ModelError: onnxruntime failed (its message in one line, with what to check in the card).
        """
        self.last_input_shape = tuple(chunk.shape)
        try:
            (out,) = self.session.run([self.output_spec.name], {self.input_spec.name: chunk})
        except Exception as exc:  # onnxruntime's own exception classes
            raise ModelError(
                f"{self.where} failed on an input of shape {list(chunk.shape)} ({_explain_run_error(str(exc))}): "
                "check input.size / input.multiple_of / input.layout in the card"
            ) from None
        out = np.asarray(out)
        return out[None] if not self._output_batched and out.ndim == 2 else out

    def _run(self, images: Sequence[Any]) -> tuple[np.ndarray, list[ResizePlan], float, float]:
        """Validate, preprocess and infer; returns raw output, plans, preprocess and inference ms."""
        if len(images) == 0:
            raise DataError(f"{self.where}: predict_batch needs at least one image")
        t0 = time.perf_counter()
        checked = [check_image(im, f"image {i}") for i, im in enumerate(images)]
        blob, plans = self._preprocess(checked)
        t1 = time.perf_counter()
        out = self._infer(blob)
        t2 = time.perf_counter()
        return out, plans, (t1 - t0) * 1e3, (t2 - t1) * 1e3


def measure_overhead(
    model: OnnxModel, image_rgb: np.ndarray, repeats: int = 10, **kwargs: Any
) -> dict[str, float]:
    """Median per-frame timings of ``model.predict(image_rgb)`` over ``repeats`` runs (after one warm-up).

    Per-step medians are robust to scheduler hiccups on a shared CPU; ``overhead_ms`` (what the adapter
    adds to the model: preprocessing + postprocessing) and ``total_ms`` are sums of those medians.

    Returns:
        dict with ``preprocess_ms``, ``inference_ms``, ``postprocess_ms``, ``overhead_ms``, ``total_ms``
        and ``repeats``.
    """
    model.predict(image_rgb, **kwargs)  # type: ignore[attr-defined]
    rows = []
    for _ in range(max(1, repeats)):
        model.predict(image_rgb, **kwargs)  # type: ignore[attr-defined]
        t = model.last_timings
        rows.append((t.preprocess_ms, t.inference_ms, t.postprocess_ms))
    pre, inf, post = (float(v) for v in np.median(np.asarray(rows), axis=0))
    return {
        "preprocess_ms": pre,
        "inference_ms": inf,
        "postprocess_ms": post,
        "overhead_ms": pre + post,
        "total_ms": pre + inf + post,
        "repeats": float(len(rows)),
    }
