"""Resize geometry between an image and a model input: stretch, letterbox pad, centre crop, and back.

``plan_resize`` decides which image region goes where in the model input; ``paste_back`` inverts
it for a model output (any output resolution), so depth and labels land on the image's own pixels
and pixels the model never saw (cropped borders) come back as invalid.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from shgm_slam.perception.card import ResizeMode


@dataclass(frozen=True)
class ResizePlan:
    """Where an image goes in the model input and back.

    ``src_box`` (x0, y0, x1, y1) is the image region that is fed (all of it unless cropped);
    ``dst_box`` is where it lands in the model input of size ``target_wh`` (all of it unless padded).
    """

    image_wh: tuple[int, int]
    target_wh: tuple[int, int]
    src_box: tuple[int, int, int, int]
    dst_box: tuple[int, int, int, int]

    @property
    def scale_x(self) -> float:
        """Model-input pixels per image pixel along x."""
        return (self.dst_box[2] - self.dst_box[0]) / (self.src_box[2] - self.src_box[0])

    def output_box(self, out_wh: tuple[int, int]) -> tuple[int, int, int, int]:
        """``dst_box`` in the pixels of a model output of size ``out_wh`` (outputs may be smaller)."""
        rx, ry = out_wh[0] / self.target_wh[0], out_wh[1] / self.target_wh[1]
        x0, y0, x1, y1 = self.dst_box
        bx0, by0 = round(x0 * rx), round(y0 * ry)
        return bx0, by0, max(bx0 + 1, round(x1 * rx)), max(by0 + 1, round(y1 * ry))


def plan_resize(
    image_wh: tuple[int, int], target_wh: tuple[int, int], mode: ResizeMode, *, fixed_size: bool = True
) -> ResizePlan:
    """Plan how an image of ``image_wh`` becomes a model input of ``target_wh`` (both W, H pixels).

    ``fixed_size=False`` (any-size models) pads or crops to the target without rescaling when the
    image allows it.
    """
    W, H = image_wh
    Wt, Ht = target_wh
    full_src, full_dst = (0, 0, W, H), (0, 0, Wt, Ht)
    if mode is ResizeMode.STRETCH:
        return ResizePlan(image_wh, target_wh, full_src, full_dst)
    if mode is ResizeMode.KEEP_ASPECT_PAD:
        s = min(Wt / W, Ht / H) if fixed_size else min(1.0, Wt / W, Ht / H)
        rw, rh = min(Wt, max(1, round(W * s))), min(Ht, max(1, round(H * s)))
        ox, oy = (Wt - rw) // 2, (Ht - rh) // 2
        return ResizePlan(image_wh, target_wh, full_src, (ox, oy, ox + rw, oy + rh))
    s = max(Wt / W, Ht / H) if fixed_size else max(1.0, Wt / W, Ht / H)
    cw, ch = min(W, max(1, round(Wt / s))), min(H, max(1, round(Ht / s)))
    x0, y0 = (W - cw) // 2, (H - ch) // 2
    return ResizePlan(image_wh, target_wh, (x0, y0, x0 + cw, y0 + ch), full_dst)


def any_size_target(image_wh: tuple[int, int], multiple_of: int, mode: ResizeMode) -> tuple[int, int]:
    """Model input size for an any-size model: the image size rounded to ``multiple_of``
    (up when padding, down when cropping, to the nearest when stretching)."""
    m = multiple_of
    rnd = {ResizeMode.KEEP_ASPECT_PAD: np.ceil, ResizeMode.KEEP_ASPECT_CROP: np.floor}.get(mode, np.round)
    return tuple(max(m, int(rnd(v / m)) * m) for v in image_wh)  # type: ignore[return-value]


def paste_back(
    values: np.ndarray, plan: ResizePlan, fill: float, interpolation: int, valid: np.ndarray | None = None
) -> np.ndarray:
    """Resize a model-output region back onto the image grid (the inverse of the resize plan).

    Args:
        values: (h, w) output values of the plan's ``dst_box`` region (already cut out).
        plan: the plan the input was made with.
        fill: value of image pixels the model did not see (cropped borders).
        interpolation: cv2 flag (INTER_NEAREST for labels, INTER_LINEAR for depth).
        valid: optional (h, w) bool mask of valid values; with linear interpolation invalid values do
            not bleed into valid ones (normalized interpolation) and pixels mostly covered by
            invalid ones come out as ``fill``.

    Returns:
        (H, W) array of ``values.dtype`` on the image grid.
    """
    W, H = plan.image_wh
    x0, y0, x1, y1 = plan.src_box
    size = (x1 - x0, y1 - y0)
    if valid is not None and not valid.all():
        weight = cv2.resize(valid.astype(np.float32), size, interpolation=interpolation)
        summed = cv2.resize(np.where(valid, values, 0).astype(np.float32), size, interpolation=interpolation)
        with np.errstate(invalid="ignore", divide="ignore"):
            region = np.where(weight >= 0.5, summed / np.maximum(weight, 1e-6), fill).astype(values.dtype)
    elif size != (values.shape[1], values.shape[0]):
        region = cv2.resize(values, size, interpolation=interpolation)
    else:
        region = values
    if (x0, y0, x1, y1) == (0, 0, W, H):
        return np.ascontiguousarray(region)
    full = np.full((H, W), fill, dtype=values.dtype)
    full[y0:y1, x0:x1] = region
    return full
