"""Depth that errs the way a monocular depth network errs, at a chosen AbsRel (the depth-quality study).

``corruption.corrupt_depth`` adds independent (or slightly smoothed) noise; a network's error is
structured instead, and the structure is what decides whether ICP on its pseudo-LiDAR works. Measured
on the demo depth model (airsim-like seed 10, car1; ``log(pred / true)`` per pixel): the error is
spatially correlated (0.56 at 5 px, 0.28 at 20 px, 0.06 at 80 px apart at 320x96), it changes from
frame to frame (pixelwise correlation 0.44 two frames apart), its whole-frame scale wanders by ~2 %
per frame, AbsRel grows with range (0.07 at 5-10 m, 0.14 at 30-80 m), and it is 3x larger at depth
edges, which networks blur toward the nearer surface. ``NetworkDepthErrors`` reproduces each part:

    log d' = log d + a * (d / range_ref_m) ** range_exponent * f_k(u, v),   then edge bleeding

* ``f_k`` is a smooth random field with unit variance: a whole-frame scale term (``global_share`` of
  the variance) plus a spatial term, white noise on a coarse grid (cell = ``cell_frac`` of the image
  width) interpolated bicubically: a low-frequency multiplicative scale field across the image;
* temporal flicker: between consecutive frames the field is an AR(1) process with correlation
  ``temporal_correlation`` (1 = frozen, 0 = independent per frame); frame ``k``'s field depends only on
  ``(seed, k)``, so frames can be read in any order;
* edge bleeding: every pixel within ``bleed_px`` of a nearer surface takes the blend of its
  neighbourhood where that is nearer (``min(d, box mean of d)``): background pixels at an occlusion
  edge come out too near, foreground pixels stay, like a network's smeared edges;
* ``a`` (``amplitude``) is solved by ``calibrate_amplitude`` so that the AbsRel over a sequence's
  frames hits a target (0.03, 0.05, ...).

Pure: arrays and seeds in, arrays out; no files.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from shgm_slam.errors import SimulationError


@dataclass(frozen=True)
class NetworkDepthErrors:
    """Parameters of a network-like depth error (see the module doc). ``amplitude`` 0 = true depth.

    Attributes:
        amplitude: std of ``log(d'/d)`` at ``range_ref_m`` before edge bleeding (``calibrate_amplitude``).
        range_ref_m: range at which the error's std is ``amplitude``, metres.
        range_exponent: the error's std grows as ``(d / range_ref_m) ** range_exponent``.
        global_share: share of the field's variance that is one scale for the whole frame.
        cell_frac: grid cell of the spatial field as a fraction of the image width (low frequency).
        temporal_correlation: correlation of the field between consecutive frames (flicker: 1 - this).
        bleed_px: width of edge bleeding at 320 pixels of image width (scaled with the width); 0 = none.
        seed: seed of the random fields.
    """

    amplitude: float = 0.0
    range_ref_m: float = 20.0
    range_exponent: float = 0.5
    global_share: float = 0.2
    cell_frac: float = 0.125
    temporal_correlation: float = 0.7
    bleed_px: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.amplitude < 0 or self.range_ref_m <= 0 or self.range_exponent < 0 or self.bleed_px < 0:
            raise SimulationError("depth errors need amplitude >= 0, range_ref_m > 0, range_exponent >= 0, bleed >= 0")
        if not 0.0 <= self.global_share <= 1.0 or not 0.0 <= self.temporal_correlation <= 1.0:
            raise SimulationError("depth errors: global_share and temporal_correlation are fractions in 0..1")
        if not 0.0 < self.cell_frac <= 1.0:
            raise SimulationError(f"depth errors: cell_frac must be in (0, 1], got {self.cell_frac}")

    def with_amplitude(self, amplitude: float) -> NetworkDepthErrors:
        """The same errors with another amplitude (same seed: the same fields, scaled)."""
        return NetworkDepthErrors(amplitude, self.range_ref_m, self.range_exponent, self.global_share,
                                  self.cell_frac, self.temporal_correlation, self.bleed_px, self.seed)  # fmt: skip


def bleed_edges(depth_m: np.ndarray, radius_px: int) -> np.ndarray:
    """Depth with occlusion edges smeared toward the nearer surface by ``radius_px`` pixels.

    Args:
        depth_m: (H, W) depth, metres; 0 or non-finite = invalid (stays invalid, never spreads).
        radius_px: half-width of the box over which depth is averaged (0 = unchanged).

    Returns:
        (H, W) float32 ``min(d, mean of the valid depths in the (2r+1)^2 box)``: a background pixel
        next to a nearer surface takes an in-between depth (a "flying pixel"), everything else stays.
    """
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0).astype(np.float32)
    if radius_px <= 0:
        return d
    valid = (d > 0).astype(np.float32)
    k = (2 * radius_px + 1, 2 * radius_px + 1)
    s = cv2.boxFilter(d, -1, k, normalize=False, borderType=cv2.BORDER_REFLECT)
    n = cv2.boxFilter(valid, -1, k, normalize=False, borderType=cv2.BORDER_REFLECT)
    mean = s / np.maximum(n, 1e-6)
    return np.where(d > 0, np.minimum(d, mean), 0.0).astype(np.float32)


@dataclass
class ErrorFieldSequence:
    """The unit-variance error fields ``f_k`` of one sequence (random access, cached AR(1) states).

    Args:
        shape_hw: (H, W) of the depth images.
        errors: the parameters (``cell_frac``, ``global_share``, ``temporal_correlation``, ``seed``).
    """

    shape_hw: tuple[int, int]
    errors: NetworkDepthErrors
    _states: list[np.ndarray] = field(default_factory=list, repr=False)

    @property
    def grid_hw(self) -> tuple[int, int]:
        """(rows, cols) of the coarse grid: at least 2 x 2 cells, square cells of ``cell_frac`` x W."""
        h, w = self.shape_hw
        cell = max(1.0, self.errors.cell_frac * w)
        return max(2, round(h / cell) + 1), max(2, round(w / cell) + 1)

    def _innovation(self, k: int) -> np.ndarray:
        gh, gw = self.grid_hw
        return np.random.default_rng([self.errors.seed, k]).standard_normal(gh * gw + 1)

    def _state(self, k: int) -> np.ndarray:
        """AR(1) state (grid values + the global term) of frame ``k``: rho * state(k-1) + sqrt(1-rho^2) * n_k."""
        rho = self.errors.temporal_correlation
        while len(self._states) <= k:
            j = len(self._states)
            n = self._innovation(j)
            self._states.append(n if j == 0 else rho * self._states[-1] + np.sqrt(1.0 - rho * rho) * n)
        return self._states[k]

    def field(self, k: int) -> np.ndarray:
        """(H, W) float32 unit-variance error field of frame ``k`` (>= 0)."""
        if k < 0:
            raise SimulationError(f"frame index must be >= 0, got {k}")
        h, w = self.shape_hw
        gh, gw = self.grid_hw
        state = self._state(k)
        grid = state[:-1].reshape(gh, gw).astype(np.float32)
        spatial = cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        spatial /= max(float(spatial.std()), 1e-6)
        g = self.errors.global_share
        return (np.sqrt(g) * state[-1] + np.sqrt(1.0 - g) * spatial).astype(np.float32)


def apply_network_errors(
    depth_m: np.ndarray, unit_field: np.ndarray, errors: NetworkDepthErrors
) -> np.ndarray:
    """Corrupt one depth image with a given unit field (``ErrorFieldSequence.field``).

    Args:
        depth_m: (H, W) true z-depth, metres; 0 or non-finite = invalid (kept invalid, as 0).
        unit_field: (H, W) unit-variance error field of this frame.
        errors: amplitude, range growth and bleeding.

    Returns:
        (H, W) float32 corrupted depth, metres, 0 where ``depth_m`` is invalid.
    """
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0).astype(np.float32)
    if d.shape != unit_field.shape:
        raise SimulationError(f"error field {unit_field.shape} and depth {d.shape} differ in size")
    with np.errstate(divide="ignore", invalid="ignore"):
        growth = np.power(np.maximum(d, 1e-3) / errors.range_ref_m, errors.range_exponent, dtype=np.float32)
    out = d * np.exp(errors.amplitude * growth * unit_field)
    radius = round(errors.bleed_px * d.shape[1] / 320.0)
    return bleed_edges(np.where(d > 0, out, 0.0), radius)


def abs_rel(depth_true_m: np.ndarray, depth_est_m: np.ndarray) -> float:
    """Mean of ``|est - true| / true`` over pixels valid in both (depth networks' AbsRel); NaN if none."""
    t = np.asarray(depth_true_m, dtype=np.float64)
    e = np.asarray(depth_est_m, dtype=np.float64)
    ok = np.isfinite(t) & np.isfinite(e) & (t > 0) & (e > 0)
    return float(np.mean(np.abs(e[ok] - t[ok]) / t[ok])) if ok.any() else float("nan")


def calibrate_amplitude(
    depths_m: Sequence[np.ndarray],
    frame_indices: Sequence[int],
    errors: NetworkDepthErrors,
    target_abs_rel: float,
    *,
    iterations: int = 30,
) -> float:
    """The amplitude at which ``errors`` gives a mean AbsRel of ``target_abs_rel`` on these frames.

    Args:
        depths_m: true (H, W) depth images of a sequence (a sample of its frames), metres.
        frame_indices: each image's frame index (selects its error field).
        errors: every parameter but the amplitude.
        target_abs_rel: the AbsRel to reach (e.g. 0.05).

    Returns:
        The amplitude (bisection; AbsRel grows monotonically with it for fixed fields).

    Raises:
        SimulationError: no frames, or edge bleeding alone already exceeds the target (lower ``bleed_px``).
    """
    if len(depths_m) == 0 or len(depths_m) != len(frame_indices):
        raise SimulationError("calibrating depth errors needs at least one depth image and one index per image")
    if not 0.0 < target_abs_rel < 1.0:
        raise SimulationError(f"target AbsRel must be in (0, 1), got {target_abs_rel}")
    fields = ErrorFieldSequence(np.shape(depths_m[0]), errors)
    units = [fields.field(k) for k in frame_indices]

    def mean_abs_rel(a: float) -> float:
        e = errors.with_amplitude(a)
        return float(np.nanmean([abs_rel(d, apply_network_errors(d, u, e))
                                 for d, u in zip(depths_m, units, strict=True)]))  # fmt: skip

    floor = mean_abs_rel(0.0)
    if floor >= target_abs_rel:
        raise SimulationError(
            f"edge bleeding alone gives AbsRel {floor:.3f} >= the target {target_abs_rel}; lower bleed_px"
        )
    lo, hi = 0.0, 0.1
    while mean_abs_rel(hi) < target_abs_rel:
        lo, hi = hi, 2.0 * hi
        if hi > 10.0:
            raise SimulationError(f"no amplitude up to 10 reaches AbsRel {target_abs_rel}")
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mean_abs_rel(mid) < target_abs_rel else (lo, mid)
    return 0.5 * (lo + hi)
