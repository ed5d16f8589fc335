"""Run the networks once: ONNX depth and segmentation over a sequence, written as a reusable sequence.

``perceive("KITTI/sequences/08:0-1500", depth_model, seg_model, out)`` writes a complete sequence in
our layout (ARCHITECTURE.md) that ``shgm-slam run --robot a=OUT`` reads with no models::

    OUT/ image_2/ or image_0/   links to the source images (or copies), renumbered from 000000.png
         depth/%06d.png          uint16, metres x 256, 0 = invalid     (from the depth model)
         semantic/%06d.png       uint8 Cityscapes train ids            (from the segmentation model)
         calib.txt               P0..P3 = [K | 0] of the source camera
         times.txt  poses.txt    the range's timestamps and ground truth (T_world_cam of this camera)
         perceive.json           what produced it: source, range, models (hashes), progress

Frame ``i`` of OUT is frame ``start + i`` of the source. Each PNG is written atomically (temp file +
rename), so an interrupted run never leaves a half file; running the same command again skips every
frame whose depth and label PNGs exist and decode with the right size and type, and redoes the rest.
A source image that cannot be read (missing or corrupt) is a logged skip, not the end of the job: its
frame gets placeholder outputs (no valid depth, every pixel ``ignore``) that ``run`` skips like the
unreadable image itself, the manifest lists it under ``unreadable``, and the next run of the same
command tries it again (re-export the file, run again).
Images are fed to the models in batches (one session call per batch, chunked by the adapters when a
model's batch axis is fixed); sessions use CUDA when onnxruntime-gpu is installed.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

from shgm_slam.data.base import open_sequence, parse_sequence_spec, sequence_root
from shgm_slam.data.kitti import IMAGE_SOURCES, frame_file
from shgm_slam.data.sequence import DEPTH_DIR, LABEL_DIR, PERCEIVE_MANIFEST, encode_depth, read_perceive_manifest
from shgm_slam.data.validate import check_sequence_start
from shgm_slam.errors import ConfigError, DataError, ModelError
from shgm_slam.io.export import LOCK_FILE
from shgm_slam.io.json_text import to_json_text
from shgm_slam.io.trajectories import format_kitti_pose
from shgm_slam.labels import IGNORE_ID, NUM_CLASSES
from shgm_slam.perception.card import card_to_yaml
from shgm_slam.perception.depth import DepthModel
from shgm_slam.perception.onnx_model import OnnxModel
from shgm_slam.perception.segmentation import SegmentationModel
from shgm_slam.types import DepthOrigin

MANIFEST = PERCEIVE_MANIFEST
MANIFEST_FORMAT = "shgm-perceive/1"
DEFAULT_BATCH = 8
_HASHES = ("sha256", "card_sha256")

log = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]
"""Called with (frames done, frames to compute) after every batch."""


class Provider(str, Enum):
    """Where the networks run."""

    AUTO = "auto"  # CUDA when onnxruntime-gpu has it, else CPU
    CPU = "cpu"
    CUDA = "cuda"


class ImageMode(str, Enum):
    """How the source images get into the output sequence."""

    LINK = "link"  # absolute symlinks (no copy; the source must stay where it is)
    COPY = "copy"


@dataclass(frozen=True)
class BatchUsed:
    """The images one session call of a model was fed, against the ``batch_size`` asked for.

    Attributes:
        size: images per session call (fewer in a sequence's last batch).
        why: why it differs from the batch size asked for (a model that failed on a batch and runs one image, a
            fixed batch axis, an output without a batch axis), or None when it is the one asked for.
    """

    size: int
    why: str | None = None

    def to_json_dict(self) -> dict:
        return {"size": self.size, "why": self.why}


def batch_used(model: OnnxModel, asked: int) -> BatchUsed:
    """What ``model`` was fed per session call when given batches of ``asked`` images (``OnnxModel.batch_size``,
    which a batch the model fails on but one image runs sets to 1)."""
    size = model.batch_size or asked
    return BatchUsed(size, None if size == asked else model.batch_why)


@dataclass
class PerceiveResult:
    """What ``perceive`` did. Frames are counted in the output sequence (0 = the range's first)."""

    out_dir: Path
    source: str
    frames: int
    computed: int
    reused: int
    providers: dict[str, list[str]]
    batch_size: int
    wall_s: float
    inference_ms_per_frame: dict[str, float] = field(default_factory=dict)
    interrupted: bool = False
    notes: list[str] = field(default_factory=list)
    unreadable: dict[int, str] = field(default_factory=dict)
    """Frames whose source image could not be read -> why (placeholder outputs were written)."""
    batch_used: dict[str, BatchUsed] = field(default_factory=dict)
    """Model (``depth``, ``segmentation``) -> the images it was fed per session call, and why where that is not
    ``batch_size`` (the ``last_run`` of ``perceive.json`` holds it; ``perceive``'s summary line says it)."""

    @property
    def complete(self) -> bool:
        return not self.interrupted and self.computed + self.reused == self.frames

    def to_json_dict(self) -> dict:
        return {
            "out_dir": str(self.out_dir), "source": self.source, "frames": self.frames, "computed": self.computed,
            "reused": self.reused, "providers": self.providers, "batch_size": self.batch_size,
            "wall_s": self.wall_s, "inference_ms_per_frame": self.inference_ms_per_frame,
            "interrupted": self.interrupted, "complete": self.complete, "notes": self.notes,
            "unreadable": {str(i): why for i, why in sorted(self.unreadable.items())},
            "batch_used": {k: b.to_json_dict() for k, b in self.batch_used.items()},
        }  # fmt: skip


def depth_model_of(sequence: object) -> dict | None:
    """The depth model that wrote ``sequence``'s depth files (``perceive``'s manifest), or None.

    ``sequence`` is any reader with a ``root`` folder, or a view with a ``base`` one; a folder without
    ``perceive.json``, or one whose manifest names no depth model (labels only), gives None. A manifest
    that cannot be read gives None too, with a warning: the depth is then treated as measured. A sequence
    that says where its depth comes from (``depth_origin``, ``data.memory.ArraySequence``) is taken at its
    word: predicted depth gives ``{"path": "predicted depth of <name>"}``, measured depth None.

    Returns:
        The manifest's model identity: ``path``, ``sha256``, ``card_sha256`` and (manifests written since
        it was added) ``input_wh``, the model's input size for this sequence's images.
    """
    while getattr(sequence, "base", None) is not None and getattr(sequence, "depth_origin", None) is None:
        sequence = sequence.base  # type: ignore[attr-defined]
    origin = getattr(sequence, "depth_origin", None)
    if origin is not None:
        predicted = DepthOrigin(origin) is DepthOrigin.PREDICTED
        return {"path": f"predicted depth of {getattr(sequence, 'name', 'the sequence')}"} if predicted else None
    root = sequence_root(sequence)
    if root is None or not (Path(root) / MANIFEST).is_file():
        return None
    try:
        manifest = json.loads((Path(root) / MANIFEST).read_text())
    except (OSError, ValueError) as exc:
        logging.getLogger(__name__).warning(
            "%s cannot be read (%s): its depth is treated as measured, not predicted; write it again with "
            "`shgm-slam perceive` (or delete it if no model wrote the depth)", Path(root) / MANIFEST, exc)
        return None
    if not isinstance(manifest, dict):
        logging.getLogger(__name__).warning("%s is not a perceive manifest: its depth is treated as measured",
                                            Path(root) / MANIFEST)
        return None
    model = manifest.get("depth_model")
    return model if isinstance(model, dict) else None


def session_providers(provider: Provider) -> list[str] | None:
    """ONNX Runtime providers for ``provider`` (None = the adapters' default, CUDA first when present).

    Raises:
        ModelError: CUDA asked for but this onnxruntime build has no CUDA provider.
    """
    if provider is Provider.CPU:
        return ["CPUExecutionProvider"]
    if provider is Provider.CUDA:
        if "CUDAExecutionProvider" not in ort.get_available_providers():
            raise ModelError(
                f"--provider cuda: onnxruntime {ort.__version__} has no CUDA provider; install onnxruntime-gpu "
                "(pip uninstall onnxruntime && pip install onnxruntime-gpu) or use --provider auto"
            )
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return None


def check_providers(provider: Provider, providers: dict[str, list[str]], available: list[str]) -> list[str]:
    """Notes on where the models really run; ModelError when CUDA was asked for but a session is on CPU.

    Args:
        provider: what was asked for.
        providers: model -> the providers its session reports (``session.get_providers()``).
        available: ``onnxruntime.get_available_providers()``.
    """
    on_cpu = [name for name, p in providers.items() if "CUDAExecutionProvider" not in p]
    if not on_cpu or "CUDAExecutionProvider" not in available or provider is Provider.CPU:
        return []
    why = (f"onnxruntime has a CUDA provider but the {' and '.join(on_cpu)} session(s) run on CPU: CUDA could "
           "not start (are the CUDA 12 / cuDNN 9 libraries onnxruntime-gpu needs installed?)")
    if provider is Provider.CUDA:
        raise ModelError(f"--provider cuda: {why}")
    return [why]


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _model_identity(model: OnnxModel | None, image_wh: tuple[int, int]) -> dict | None:
    if model is None:
        return None
    card = hashlib.sha256(card_to_yaml(model.card).encode()).hexdigest()
    return {
        "path": str(model.model_path.absolute()), "sha256": _file_sha256(model.model_path), "card_sha256": card,
        "input_wh": list(model.target_size(image_wh)),
    }  # fmt: skip


def write_png_atomic(path: Path, image: np.ndarray) -> None:
    """Encode ``image`` as PNG into a temp file beside ``path`` and rename it onto ``path``."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise DataError(f"cannot encode {path} as PNG (dtype {image.dtype}, shape {image.shape})")
    _write_bytes_atomic(path, data.tobytes())


def _write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` into a temp file beside ``path`` and rename it onto ``path``.

    Raises:
        DataError: the folder is not writable or the disk is full (the previous file is kept).
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except BaseException as exc:  # an error, or Ctrl-C mid-write: no partial temporary left behind
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise DataError(
                f"cannot write {path}: {exc.strerror or exc}; free space or choose another --out"
            ) from None
        raise


def _write_text_atomic(path: Path, text: str) -> None:
    _write_bytes_atomic(path, text.encode())


def png_is_valid(path: Path, dtype: type, size_wh: tuple[int, int], *, label_ids: bool = False) -> bool:
    """True when ``path`` decodes as a single-channel ``dtype`` PNG of ``size_wh`` (W, H); with ``label_ids``, also
    every value a train id (0 .. ``NUM_CLASSES`` - 1) or ``IGNORE_ID`` (a label file we would have written)."""
    if not path.is_file():
        return False
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 2 or image.dtype != dtype or (image.shape[1], image.shape[0]) != size_wh:
        return False
    return not label_ids or bool(((image < NUM_CLASSES) | (image == IGNORE_ID)).all())


def _unreadable_before(out: Path) -> set[int]:
    """Frames an earlier run of ``perceive`` into ``out`` could not read (its manifest's ``unreadable``)."""
    listed = (read_perceive_manifest(out) or {}).get("unreadable")
    return {i for i in listed if isinstance(i, int)} if isinstance(listed, list) else set()


def _check_out(out: Path, source_root: Path, manifest: dict, overwrite: bool) -> None:
    """Refuse to write into the source, or into a folder that holds something else."""
    if out.exists() and not out.is_dir():
        raise DataError(f"--out {out} is a file; choose a folder")
    if out.resolve() == source_root.resolve():
        raise DataError(f"--out {out} is the source sequence itself; choose a new folder (the source is not changed)")
    if not out.is_dir() or not any(p.name != LOCK_FILE for p in out.iterdir()):  # (the lock: this process's)
        return
    previous_path = out / MANIFEST
    if not previous_path.is_file():
        if overwrite:
            for name in (DEPTH_DIR, LABEL_DIR):
                shutil.rmtree(out / name, ignore_errors=True)
            return
        raise DataError(f"--out {out} is not empty and was not written by perceive; choose a new folder")
    try:
        previous = json.loads(previous_path.read_text())
    except (OSError, ValueError, RecursionError):
        previous = None
    if not isinstance(previous, dict):  # damaged, or not a manifest: nothing in the folder can be trusted
        if not overwrite:
            raise DataError(
                f"{previous_path} is unreadable (not a perceive manifest): the outputs in --out {out} cannot be "
                "checked; choose a new folder or pass --overwrite to redo them"
            )
        previous = {}
    changed = [k for k in ("format", "source", "start", "end") if previous.get(k) != manifest[k]]
    for k in ("depth_model", "seg_model"):  # the same model may sit elsewhere now: compare contents only
        old, new = previous.get(k) or {}, manifest[k] or {}
        if {h: old.get(h) for h in _HASHES} != {h: new.get(h) for h in _HASHES}:
            changed.append(k)
    if changed and not overwrite:
        raise DataError(
            f"--out {out} holds perceive outputs of another source, range or model ({', '.join(changed)} "
            "changed); choose a new folder or pass --overwrite to redo them"
        )
    same_frames = not set(changed) - {"depth_model", "seg_model"} and not overwrite
    for name, key in ((DEPTH_DIR, "depth_model"), (LABEL_DIR, "seg_model")):
        if not same_frames or key in changed:
            shutil.rmtree(out / name, ignore_errors=True)


def _write_static(out: Path, sequence, source_images: Path, image_folder: str, start: int, mode: ImageMode) -> None:
    """Images (linked or copied), calib.txt ([K|0]), times.txt and poses.txt of the output sequence."""
    images = out / image_folder
    images.mkdir(parents=True, exist_ok=True)
    for other in {s.folder for s in IMAGE_SOURCES} - {image_folder}:
        if (out / other).is_dir():  # a previous run with another source camera
            shutil.rmtree(out / other)
    for i in range(len(sequence)):
        src, dst = frame_file(source_images, start + i).absolute(), frame_file(images, i)
        if mode is ImageMode.LINK:
            if dst.is_symlink() and os.readlink(dst) == str(src):
                continue
            tmp = dst.with_name(f".{dst.name}.{os.getpid()}.part")
            tmp.unlink(missing_ok=True)
            os.symlink(src, tmp)
            os.replace(tmp, dst)
        elif dst.is_symlink() or not dst.is_file() or dst.stat().st_size != src.stat().st_size:
            tmp = dst.with_name(f".{dst.name}.{os.getpid()}.part")
            shutil.copyfile(src, tmp)
            os.replace(tmp, dst)
    K = sequence.intrinsics.K
    line = " ".join(f"{v:.12e}" for v in np.hstack([K, np.zeros((3, 1))]).ravel())
    _write_text_atomic(out / "calib.txt", "".join(f"P{k}: {line}\n" for k in range(4)))
    _write_text_atomic(out / "times.txt", "".join(f"{t:.9f}\n" for t in np.asarray(sequence.timestamps_s)))
    gt = sequence.gt_poses
    if gt is not None:  # already on the read camera: with P = [K|0] the reader applies no offset again
        _write_text_atomic(out / "poses.txt", "".join(format_kitti_pose(T) + "\n" for T in gt))
    else:
        (out / "poses.txt").unlink(missing_ok=True)


def _open_models(
    depth_model: Path | None, seg_model: Path | None, threads: int, providers: list[str] | None
) -> tuple[DepthModel | None, SegmentationModel | None]:
    if depth_model is None and seg_model is None:
        raise ConfigError("perceive needs --depth-model and/or --seg-model (an .onnx file with its card beside it)")
    for what, path in (("depth", depth_model), ("segmentation", seg_model)):
        if path is not None and not Path(path).is_file():
            raise ModelError(f"{what} model {path} does not exist; pass the path of an .onnx file")
    depth = DepthModel(depth_model, threads=threads, providers=providers) if depth_model is not None else None
    seg = SegmentationModel(seg_model, threads=threads, providers=providers) if seg_model is not None else None
    return depth, seg


def _placeholder_depth(height: int, width: int) -> np.ndarray:
    """(H, W) float32 depth in metres, 5-10 m varying along x, that passes ``check_sequence_start``'s depth checks:
    what it probes when there is no depth model (the labels alone are checked; one value everywhere, as before, was
    refused as a sensor's saturated depth files and ended every ``perceive --seg-model`` alone)."""
    return np.broadcast_to(np.linspace(5.0, 10.0, width, dtype=np.float32), (height, width))


def _check_outputs(sequence, depth: DepthModel | None, seg: SegmentationModel | None) -> None:
    """The models' outputs on a few frames spread over the sequence, checked as ``run`` checks them (some valid
    depth, not constant) before the whole sequence is computed: a useless model is refused, not written out.

    Raises:
        ModelError: no valid output, or the same value everywhere, on every probed frame.
        DataError: no probed frame can be read.
    """

    def predict(frame):
        h, w = frame.image_rgb.shape[:2]
        d = depth.predict(frame.image_rgb, sequence.intrinsics) if depth else _placeholder_depth(h, w)
        return d, seg.predict(frame.image_rgb) if seg else None

    check_sequence_start(sequence.name, sequence, predict, depth_model=depth.model_path if depth else None,
                         seg_model=seg.model_path if seg else None)  # fmt: skip


def perceive(
    spec: str | Path,
    out: Path | str,
    *,
    depth_model: Path | str | None = None,
    seg_model: Path | str | None = None,
    batch_size: int = DEFAULT_BATCH,
    threads: int = 0,
    provider: Provider = Provider.AUTO,
    images: ImageMode = ImageMode.LINK,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
) -> PerceiveResult:
    """Run the depth and/or segmentation network over ``spec`` and write the sequence ``out``.

    Args:
        spec: ``path[:start-end]`` (start inclusive, end exclusive) of a KITTI or shgm sequence.
        out: output folder (created; resumed when it holds this job's earlier, interrupted outputs).
        depth_model, seg_model: .onnx files with their cards beside them; at least one.
        batch_size: frames per session call.
        threads: onnxruntime intra-op threads (0 = all cores).
        provider: CUDA when available (auto), or force CPU / CUDA.
        images: symlink the source images (default) or copy them.
        overwrite: redo every frame of a folder that holds other outputs.
        progress: called with (frames done, frames to compute).

    Returns:
        a ``PerceiveResult``; on Ctrl-C the frames done so far are kept and ``interrupted`` is True.

    Raises:
        ConfigError: no model, or a batch size below 1.
        ModelError: a model or its card is missing or does not fit, or its output on the first frames is
            useless (no valid value, or constant); CUDA asked for but absent.
        DataError: the sequence cannot be read, or ``out`` is the source or holds other data, or another
            shgm-slam process is writing it (two jobs on one folder, one with ``overwrite``, removed each other's
            files or left PNGs of two models under one manifest).
    """
    from shgm_slam.io.export import release_results_dir

    out = Path(out)
    created = _hold_out(out)
    try:
        return _perceive(spec, out, depth_model=depth_model, seg_model=seg_model, batch_size=batch_size,
                         threads=threads, provider=provider, images=images, overwrite=overwrite,
                         progress=progress)  # fmt: skip
    finally:
        release_results_dir(out)
        if created:  # refused before writing anything (a model, the sequence): no empty folder left behind
            with contextlib.suppress(OSError):
                out.rmdir()


def _hold_out(out: Path) -> bool:
    """Create ``out`` if needed and lock it for this process (``io.export.LOCK_FILE``, as a run locks its results
    folder): a second ``perceive`` on it is refused while this one writes. Returns whether ``out`` was created.

    Raises:
        DataError: ``out`` is a file or cannot be created, or another shgm-slam process holds it (naming its pid).
    """
    from shgm_slam.io.export import _lock_results_dir

    if out.exists() and not out.is_dir():
        raise DataError(f"--out {out} is a file; choose a folder")
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot write {out}: {exc.strerror or exc}; choose a writable --out with free space") from None
    try:
        _lock_results_dir(out)
    except DataError:
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    return created


def _perceive(
    spec: str | Path,
    out: Path,
    *,
    depth_model: Path | str | None,
    seg_model: Path | str | None,
    batch_size: int,
    threads: int,
    provider: Provider,
    images: ImageMode,
    overwrite: bool,
    progress: ProgressFn | None,
) -> PerceiveResult:
    """``perceive`` into ``out``, which this process holds."""
    t_start = time.perf_counter()
    if batch_size < 1:
        raise ConfigError(f"--batch-size {batch_size}: use 1 or more")
    root, start, _ = parse_sequence_spec(spec)
    sequence = open_sequence(spec)
    n = len(sequence)
    end = start + n
    source = next((s for s in IMAGE_SOURCES if (root / s.folder).is_dir()), None)
    if source is None:  # open_sequence checked this already
        raise DataError(f"{root} has neither image_2/ nor image_0/")
    depth, seg = _open_models(
        Path(depth_model) if depth_model else None, Path(seg_model) if seg_model else None,
        threads, session_providers(provider),
    )  # fmt: skip
    _check_outputs(sequence, depth, seg)
    providers = {name: m.providers for name, m in (("depth", depth), ("segmentation", seg)) if m is not None}
    notes = check_providers(provider, providers, ort.get_available_providers())
    image_wh = (sequence.intrinsics.width, sequence.intrinsics.height)
    manifest = {
        "format": MANIFEST_FORMAT, "source": str(root.absolute()), "start": start, "end": end, "frames": n,
        "depth_model": _model_identity(depth, image_wh), "seg_model": _model_identity(seg, image_wh),
        "complete": False,
    }  # fmt: skip
    outputs: list[tuple[str, type]] = [(DEPTH_DIR, np.uint16)] * (depth is not None) + [(LABEL_DIR, np.uint8)] * (
        seg is not None
    )
    retry = _unreadable_before(out)  # frames the last run could not read: tried again
    try:  # the output folder's skeleton: a read-only or full folder is one clear error
        _check_out(out, root, manifest, overwrite)
        out.mkdir(parents=True, exist_ok=True)
        _write_text_atomic(out / MANIFEST, to_json_text(manifest) + "\n")
        _write_static(out, sequence, root / source.folder, source.folder, start, images)
        for folder, _ in outputs:
            (out / folder).mkdir(exist_ok=True)
            for stale in (out / folder).glob(".*.part"):
                stale.unlink(missing_ok=True)
    except OSError as exc:
        where, why = exc.filename or out, exc.strerror or exc
        raise DataError(f"cannot write {where}: {why}; choose a writable --out with free space") from None
    size = sequence.intrinsics.size_wh
    todo = [
        i for i in range(n) if i in retry
        or not all(png_is_valid(frame_file(out / f, i), t, size, label_ids=f == LABEL_DIR) for f, t in outputs)
    ]  # fmt: skip
    result = PerceiveResult(out, str(spec), n, 0, n - len(todo), providers, batch_size, 0.0, notes=notes)
    inference_ms = {"depth": 0.0, "segmentation": 0.0}
    batches = [todo[k : k + batch_size] for k in range(0, len(todo), batch_size)]

    def load(batch: list[int]) -> list[np.ndarray | None]:
        """The batch's images; None (and a logged skip) for one that cannot be read."""
        images: list[np.ndarray | None] = []
        for i in batch:
            try:
                images.append(sequence[i].image_rgb)  # type: ignore[misc]
            except DataError as exc:
                result.unreadable[i] = str(exc)
                log.warning("frame %d skipped: %s", i, exc)
                images.append(None)
        return images

    blank_wh = (sequence.intrinsics.height, sequence.intrinsics.width)

    def write(batch: list[int], depths: list[np.ndarray] | None, labels: list[np.ndarray] | None) -> int:
        for i, d in zip(batch, depths or [], strict=False):
            write_png_atomic(frame_file(out / DEPTH_DIR, i), encode_depth(d))
        for i, lab in zip(batch, labels or [], strict=False):
            write_png_atomic(frame_file(out / LABEL_DIR, i), lab.astype(np.uint8))
        return len(batch)

    def write_placeholders(batch: list[int]) -> None:
        """Outputs of unreadable frames: no valid depth, every pixel ``ignore`` (``run`` skips them)."""
        write(batch, [np.zeros(blank_wh, np.float32)] * len(batch) if depth is not None else None,
              [np.full(blank_wh, IGNORE_ID, np.uint8)] * len(batch) if seg is not None else None)  # fmt: skip

    written: deque[Future[int]] = deque()

    def collect(keep: int) -> None:
        """Wait until at most ``keep`` batches are still being written; count and report the rest."""
        while len(written) > keep:
            result.computed += written.popleft().result()
            if progress:
                progress(result.computed, len(todo))

    # three stages overlap: loading the next batch, the models, PNG encoding of the previous batch
    with ThreadPoolExecutor(max_workers=1) as loader, ThreadPoolExecutor(max_workers=1) as writer:
        pending = loader.submit(load, batches[0]) if batches else None
        try:
            if progress:
                progress(0, len(todo))
            for k, batch in enumerate(batches):
                assert pending is not None
                loaded = pending.result()
                pending = loader.submit(load, batches[k + 1]) if k + 1 < len(batches) else None
                write_placeholders([i for i, im in zip(batch, loaded, strict=True) if im is None])
                batch = [i for i, im in zip(batch, loaded, strict=True) if im is not None]
                rgb = [im for im in loaded if im is not None]
                result.computed += len(loaded) - len(rgb)
                if not rgb:
                    continue
                depths = labels = None
                if depth is not None:
                    depths = depth.predict_batch(rgb, sequence.intrinsics)
                    inference_ms["depth"] += depth.last_timings.total_ms
                if seg is not None:
                    labels = seg.predict_batch(rgb)
                    inference_ms["segmentation"] += seg.last_timings.total_ms
                written.append(writer.submit(write, batch, depths, labels))
                collect(keep=1)
            collect(keep=0)
        except KeyboardInterrupt:
            result.interrupted = True
            if pending is not None:
                pending.cancel()
            while written:  # batches already handed to the writer finish (each file is atomic anyway)
                result.computed += written.popleft().result()
    inferred = result.computed - len(result.unreadable)
    result.inference_ms_per_frame = {k: v / inferred for k, v in inference_ms.items() if inferred and k in providers}
    result.wall_s = time.perf_counter() - t_start
    models = (("depth", depth), ("segmentation", seg))
    result.batch_used = {k: batch_used(m, batch_size) for k, m in models if m is not None}
    if result.unreadable:
        manifest["unreadable"] = sorted(result.unreadable)
    if result.complete:
        manifest["complete"] = True
    if result.complete or result.unreadable:
        _write_text_atomic(out / MANIFEST, to_json_text({**manifest, "last_run": result.to_json_dict()}) + "\n")
    return result
