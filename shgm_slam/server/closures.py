"""Closure cutting: one graph match becomes several keyframe-to-keyframe closures, each refitted locally.

A whole-graph transform averages over both robots' drift and is exact only near its inliers, so the
inliers are cut into stretches along robot a's graph and each stretch gets its own Eq. 2 refit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shgm_slam.geometry import se3
from shgm_slam.geometry.ground import rotation_to_z
from shgm_slam.labels import FLAT_GROUND_LABELS, Label
from shgm_slam.matching.pose import spread_m

COMPACT_LABELS = (
    Label.POLE,
    Label.TRAFFIC_LIGHT,
    Label.TRAFFIC_SIGN,
    Label.VEGETATION,
    Label.CAR,
    Label.TRUCK,
    Label.BUS,
)
"""Classes of compact objects: their centroid depends far less on the viewpoint than a building's or a
road patch's."""

THIN_LABELS = (Label.POLE, Label.TRAFFIC_LIGHT, Label.TRAFFIC_SIGN)
"""Compact classes thin enough that the centroid of their visible surface is their centre from any side.
The others (trees, vehicles) are solid: the pixels seen are the near side, so the centroid lies ~1 m
(trees, cars) to ~3 m (trucks, buses) short of the centre along the viewing ray (measured on simulated
worlds against the true object centres); two robots seeing them from opposite directions disagree by
twice that."""

MIN_THIN = 3
"""Fewest thin inliers that carry a local refit on their own (a 4-DoF fit needs 2)."""

MAX_SURFACE_OFFSET_M = 3.0
"""Largest centre-behind-surface offset a refit may estimate for solid objects (half a bus's width)."""

OFFSET_PRIOR_WEIGHT = 1.0
"""Weight of the prior on the surface offset in a refit (m²-equivalent: a quarter of one pair seen from
opposite sides, whose two rays differ by ~2)."""


@dataclass
class SurfaceOffset:
    """How far solid objects' centres lie behind the surfaces cameras see, as the fleet's matches measured
    it: an information-weighted mean of the refits' estimates (``add``), 0 with no evidence yet.

    A refit alone can measure the offset only when thin objects (whose centroids are unbiased) fix the
    translation along the street; elsewhere the offset looks exactly like a translation, so the fleet's
    estimate is the prior every refit starts from.
    """

    mean: float = 0.0
    weight: float = OFFSET_PRIOR_WEIGHT
    _sum_info: float = 0.0
    _sum_info_delta: float = 0.0

    def state(self) -> tuple[float, float, float]:
        """(mean, accumulated information, information-weighted sum of estimates), for snapshots."""
        return (self.mean, self._sum_info, self._sum_info_delta)

    @classmethod
    def from_state(cls, state: tuple[float, float, float]) -> SurfaceOffset:
        """The estimate ``state()`` described (finite numbers, non-negative information).

        Raises:
            ValueError: non-finite numbers or negative information.
        """
        mean, info, info_delta = (float(v) for v in state)
        if not all(np.isfinite([mean, info, info_delta])) or info < 0:
            raise ValueError(f"surface offset state must be finite with non-negative information, got {state}")
        out = cls()
        out.mean, out._sum_info, out._sum_info_delta = mean, info, info_delta
        return out

    def add(self, delta_m: float, info: float) -> None:
        """Fold in one refit's estimate ``delta_m`` with the data's information ``info`` on it."""
        if info <= 0 or not np.isfinite(delta_m):
            return
        self._sum_info += info
        self._sum_info_delta += info * delta_m
        self.mean = self._sum_info_delta / self._sum_info

OFFSET_ITERATIONS = 4
"""Alternations of the refit between the transform and the surface offset."""


def local_closures(
    pos_a: np.ndarray,
    pos_b: np.ndarray,
    labels: np.ndarray,
    anchors_a: np.ndarray,
    anchors_b: np.ndarray,
    T_a_b: np.ndarray,
    *,
    segment_m: float,
    min_inliers: int,
    max_rmse_m: float,
    up_a: np.ndarray | None,
    up_b: np.ndarray | None,
    rays_a: np.ndarray | None = None,
    rays_b: np.ndarray | None = None,
    offset: SurfaceOffset | None = None,
) -> list[tuple[int, int, np.ndarray, int, np.ndarray]]:
    """Cut one graph match into local closures ``(kf_a, kf_b, T_a_b_local, inliers, rows)``.

    Args:
        pos_a, pos_b: (M, 3) inlier node positions in robot a's / robot b's graph frame (metres).
        labels: (M,) inlier label ids.
        anchors_a, anchors_b: (M,) keyframe each inlier node is anchored to, in a's / b's graph.
        T_a_b: (4, 4) the whole match's transform (b's graph frame -> a's graph frame).
        segment_m: stretch length along a's graph (``backend.local_closure_m``).
        min_inliers: fewest inliers in a stretch that gives its own closure.
        max_rmse_m: a stretch whose refit leaves a larger RMS residual gives none.
        up_a, up_b: (3,) "up" in a's / b's graph frame when known (then refits are 4-DoF).
        rays_a, rays_b: (M, 3) unit viewing rays in a's / b's graph frame (from the camera of the keyframe
            that first saw each inlier's object towards it) or None: ``refit`` then also estimates how
            far solid objects' centres lie behind their seen surfaces.
        offset: the fleet's estimate of that offset (``SurfaceOffset``): each refit starts from it and adds
            what its own data says.

    Returns:
        Closures between the keyframes anchoring each stretch's central inlier, ``T_a_b_local`` in the
        graph frames (b -> a), with the (n,) indices into the M inliers that support it; without any
        good stretch, one closure at the centre with ``T_a_b``, supported by all inliers.
    """
    order = np.argsort(anchors_a, kind="stable")
    groups: list[np.ndarray] = []
    start = 0
    for i in range(1, len(order) + 1):
        if i == len(order) or np.linalg.norm(pos_a[order[i]] - pos_a[order[start]]) > segment_m:
            groups.append(order[start:i])
            start = i
    out = []
    for g in groups:
        if len(g) < min_inliers or spread_m(pos_a[g]) < 0.25 * segment_m:
            continue
        rays = (None, None) if rays_a is None or rays_b is None else (rays_a[g], rays_b[g])
        T_local = refit(pos_a[g], pos_b[g], labels[g], up_a, up_b, *rays, offset=offset)
        resid = np.linalg.norm(se3.transform_points(T_local, pos_b[g]) - pos_a[g], axis=1)
        if np.sqrt(np.mean(resid**2)) > max_rmse_m:
            continue
        c = g[int(np.argmin(np.linalg.norm(pos_a[g] - pos_a[g].mean(axis=0), axis=1)))]
        out.append((int(anchors_a[c]), int(anchors_b[c]), T_local, len(g), np.sort(g)))
    if not out:
        c = int(np.argmin(np.linalg.norm(pos_a - pos_a.mean(axis=0), axis=1)))
        out.append((int(anchors_a[c]), int(anchors_b[c]), T_a_b, len(pos_a), np.arange(len(pos_a))))
    return out


def refit(
    pos_a: np.ndarray,
    pos_b: np.ndarray,
    labels: np.ndarray,
    up_a: np.ndarray | None,
    up_b: np.ndarray | None,
    rays_a: np.ndarray | None = None,
    rays_b: np.ndarray | None = None,
    offset: SurfaceOffset | None = None,
) -> np.ndarray:
    """Eq. 2 refit of ``T_a_b`` (4, 4; b's graph frame -> a's) to matched positions (M, 3) each.

    A node's position is the centroid of what the camera saw of its object: the object's centre only
    for thin objects (poles, lights, signs; ``THIN_LABELS``). Of a solid one (trees, vehicles) the camera
    sees the near side, so its centroid lies short of the centre along the viewing ray (~1 m for cars and
    trees on our simulated worlds), and two robots that saw it from opposite sides disagree by twice that,
    along the street both drove: a bias no averaging removes, and one that looks exactly like a shift.

    With the viewing rays (``rays_a``, ``rays_b``: unit vectors from the camera that first saw each object
    towards it, in each graph frame) the fit moves every solid object's centroid back along its ray by one
    offset ``delta`` estimated together with the transform (``_refit_with_offset``): thin objects fix the
    translation and the solid ones' residuals then measure ``delta``; without thin objects ``delta`` stays
    at the fleet's estimate ``offset`` (``SurfaceOffset``, which this refit also updates with what its data
    says). Seen from the same side the two rays cancel, and so does the bias. Thin and solid objects carry
    the fit together when there are at least 4. Without rays, thin objects alone carry it when there are at
    least ``MIN_THIN``, else the compact ones. Else all. With both robots' "up" known the fit is 4-DoF, and
    its height then comes from the flat ground classes when it matched any (``_level_on_ground``).
    """
    thin = np.isin(labels, THIN_LABELS)
    compact = np.isin(labels, COMPACT_LABELS)
    if rays_a is not None and rays_b is not None and compact.sum() >= 4:
        prior = offset if offset is not None else SurfaceOffset()
        T, delta, info = _refit_with_offset(
            pos_a[compact], pos_b[compact], ~thin[compact], rays_a[compact], rays_b[compact], up_a, up_b, prior
        )
        if offset is not None:
            offset.add(delta, info)
    elif thin.sum() >= MIN_THIN:
        T = _fit(pos_a[thin], pos_b[thin], up_a, up_b)
    elif compact.sum() >= 4:
        T = _fit(pos_a[compact], pos_b[compact], up_a, up_b)
    else:
        T = _fit(pos_a, pos_b, up_a, up_b)
    return _level_on_ground(T, pos_a, pos_b, labels, up_a, up_b)


def _level_on_ground(
    T_a_b: np.ndarray, pos_a: np.ndarray, pos_b: np.ndarray, labels: np.ndarray,
    up_a: np.ndarray | None, up_b: np.ndarray | None,
) -> np.ndarray:  # fmt: skip
    """``T_a_b`` (4, 4) moved along a's "up" so that the matched flat-ground nodes (``FLAT_GROUND_LABELS``) lie at
    their heights in a: the median of their height residuals. A 4-DoF fit's height is decoupled from its
    yaw and horizontal shift, and the compact objects that fix those disagree in height between a car and
    a UAV (a side versus a top). Unchanged without both "up"s (a 6-DoF fit) or without flat nodes."""
    flat = np.isin(labels, FLAT_GROUND_LABELS)
    if up_a is None or up_b is None or not flat.any():
        return T_a_b
    up = up_a / np.linalg.norm(up_a)
    dz = (pos_a[flat] - se3.transform_points(T_a_b, pos_b[flat])) @ up
    out = T_a_b.copy()
    out[:3, 3] += float(np.median(dz)) * up
    return out


def _fit(pos_a: np.ndarray, pos_b: np.ndarray, up_a: np.ndarray | None, up_b: np.ndarray | None) -> np.ndarray:
    """Rigid ``T_a_b`` fit (4-DoF about the shared vertical when both "up"s are known, else 6-DoF)."""
    if up_a is None or up_b is None:
        return se3.kabsch(pos_b, pos_a)
    R_a, R_b = rotation_to_z(up_a), rotation_to_z(up_b)
    T_g = se3.kabsch_yaw(pos_b @ R_b.T, pos_a @ R_a.T)
    return se3.make_pose(R_a.T, np.zeros(3)) @ T_g @ se3.make_pose(R_b, np.zeros(3))


def _refit_with_offset(
    pos_a: np.ndarray, pos_b: np.ndarray, solid: np.ndarray, rays_a: np.ndarray, rays_b: np.ndarray,
    up_a: np.ndarray | None, up_b: np.ndarray | None, prior: SurfaceOffset,
) -> tuple[np.ndarray, float, float]:  # fmt: skip
    """``refit`` with one surface-to-centre offset ``delta`` of the solid (``solid``, (M,) bool) objects:
    minimizes sum |(p_a + delta s u_a) - R (p_b + delta s u_b) - t|² + prior.weight (delta - prior.mean)²
    over T = (R, t) and delta (s = solid). Alternates a joint linear least-squares step in (t, delta) with R
    fixed and a rigid fit of R, t to the corrected points.

    Returns:
        ``T_a_b``, the offset the data alone gives (without the prior; for the fleet's estimate) and the
        data's information on it (1 / variance per unit residual variance: the Schur complement of the
        (t, delta) normal equations, ~0 when the data cannot tell it from a translation, e.g. without thin
        objects).
    """
    s = solid[:, None].astype(np.float64)
    delta, info = prior.mean, 0.0
    T = _fit(pos_a + delta * s * rays_a, pos_b + delta * s * rays_b, up_a, up_b)
    m = len(pos_a)
    for _ in range(OFFSET_ITERATIONS):
        R = T[:3, :3]
        e0 = pos_a - pos_b @ R.T  # = t - delta w at the optimum
        w = s * (rays_a - rays_b @ R.T)
        # normal equations of sum |e0 - t + delta w|^2 in x = (t, delta)
        N = np.zeros((4, 4))
        N[:3, :3] = m * np.eye(3)
        N[:3, 3] = N[3, :3] = -w.sum(axis=0)
        N[3, 3] = float((w * w).sum())
        rhs = np.concatenate([e0.sum(axis=0), [-float((e0 * w).sum())]])
        info = float(N[3, 3] - N[3, :3] @ N[:3, 3] / m)  # Schur complement: what the data alone says on delta
        data_delta = float(rhs[3] - N[3, :3] @ rhs[:3] / m) / info if info > 1e-9 else prior.mean
        N[3, 3] += prior.weight
        rhs[3] += prior.weight * prior.mean
        delta = float(np.clip(np.linalg.solve(N, rhs)[3], 0.0, MAX_SURFACE_OFFSET_M))
        T = _fit(pos_a + delta * s * rays_a, pos_b + delta * s * rays_b, up_a, up_b)
    return T, data_delta, info
