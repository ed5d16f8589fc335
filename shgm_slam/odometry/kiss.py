"""KISS-ICP adapter tuned for dense pseudo-LiDAR clouds from depth images (REFERENCE.md §1).

The KISS-ICP config is built explicitly, field by field: ``kiss_icp.config.KISSConfig`` is a
pydantic-settings class, so ``kiss_icp_*`` environment variables would otherwise silently change it.
Frames whose cloud is too small for ICP are not registered: the pose follows the constant-velocity
prediction and the frame is reported as degenerate.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np

from shgm_slam.errors import ConfigError

log = logging.getLogger(__name__)

MIN_POINTS = 300
"""Clouds with fewer points (after range filtering) are not registered."""

MIN_SOURCE_VOXELS = 50
"""Clouds that fill fewer of KISS-ICP's source voxels (``SOURCE_VOXEL_FACTOR`` x its voxel, one point each:
what ICP registers) are not registered either, however many points they hold: a camera that sees one surface
up close leaves ICP free to slide and tilt. A UAV flying 1-3 m over a roof (airsim-like tuning world 17 at
30-40 m) filled 12-14 voxels with 30k points for two seconds, and KISS-ICP's steps turned up to 8 degrees off
there, undetected (the bend that put that UAV 6 m off; the UAV of world 16 likewise, 26 voxels). Every other
frame of the tuning and report robots' drives fills 150 or more (a car in a narrow street; UAVs at 44-95 m 890
or more): the limit changes nothing else."""

SOURCE_VOXEL_FACTOR = 1.5
"""KISS-ICP registers the frame downsampled to this many of its voxels (``KissICP.voxelize``)."""


class OdometryStatus(str, Enum):
    """Outcome of registering one frame."""

    OK = "ok"
    DEGENERATE_CLOUD = "degenerate-cloud"  # too few points or voxels: constant-velocity prediction used
    ICP_FAILED = "icp-failed"  # ICP returned a non-finite pose: constant-velocity prediction used


@dataclass(frozen=True)
class Relocation:
    """A kept step that also corrects the pose from outside ICP (``KissOdometry.register``'s ``fuse_step``
    may return one instead of a step), e.g. by the motion of the last second measured from the images.

    The local map restarts from this frame: it holds the frames ICP placed along the path it slid, which
    would pull the next registrations back onto that path (UAVs at 85-95 m, tuning seeds 15-19, odometry
    alone: ICP's motion over a second was 8-36 % off, median per UAV, with the map kept, 5-13 % with it
    restarted; ATE summed over the five 26.6 against 19.4 m).
    The constant-velocity model continues with ``velocity``: the step holds the correction, not one frame's
    motion; for the same reason the step is not counted in the adaptive threshold's model error.

    Attributes:
        step: (4, 4) the pose of this frame in the previous camera frame.
        velocity: (4, 4) the motion model's next frame-to-frame motion.
    """

    step: np.ndarray
    velocity: np.ndarray


@dataclass(frozen=True)
class Registration:
    """Result of ``KissOdometry.register``.

    Attributes:
        T_odom_cam: (4, 4) pose of the camera in the odometry frame (the first camera frame).
        status: whether ICP ran and succeeded.
        num_points: points of the input cloud inside the range limits.
        source_voxels: KISS-ICP source voxels those points fill, where that made the cloud degenerate
            (``MIN_SOURCE_VOXELS``); None otherwise (not counted in full).
        map_misfit: how badly the cloud fits the local map under the step kept (``map_misfits``), where a
            ``fuse_step`` measured the map's fit in this frame (a search ran); None otherwise (not measured:
            measuring costs 10-20 ms).
    """

    T_odom_cam: np.ndarray
    status: OdometryStatus
    num_points: int
    source_voxels: int | None = None
    map_misfit: float | None = None

    def describe(self) -> str:
        """``status (N points in range[, V source voxels])``, for logs."""
        voxels = "" if self.source_voxels is None else f", {self.source_voxels} source voxels"
        return f"{self.status.value} ({self.num_points} points in range{voxels})"

    @property
    def ok(self) -> bool:
        return self.status is OdometryStatus.OK


def _kiss_config(
    *,
    voxel_size_m: float,
    max_points_per_voxel: int,
    min_range_m: float,
    max_range_m: float,
    max_icp_iterations: int,
    convergence_criterion: float,
    max_threads: int,
    fixed_threshold_m: float | None,
    initial_threshold_m: float,
    min_motion_m: float,
):  # -> kiss_icp.config.KISSConfig
    """Every KISS-ICP field set from arguments; ``kiss_icp_*`` environment variables are ignored."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import AdaptiveThresholdConfig, DataConfig, MappingConfig, RegistrationConfig

    stray = sorted(k for k in os.environ if k.lower().startswith("kiss_icp_"))
    if stray:
        log.warning("ignoring environment variables %s: shgm_slam sets the KISS-ICP config explicitly", stray)
    # model_construct skips pydantic-settings' environment source; every field is given, so nothing
    # is left at None (the reason kiss_icp.config.load_config exists).
    return KISSConfig.model_construct(
        out_dir="results",
        data=DataConfig(max_range=max_range_m, min_range=min_range_m, deskew=False),
        mapping=MappingConfig(voxel_size=voxel_size_m, max_points_per_voxel=max_points_per_voxel),
        registration=RegistrationConfig(
            max_num_iterations=max_icp_iterations,
            convergence_criterion=convergence_criterion,
            max_num_threads=max_threads,
        ),
        adaptive_threshold=AdaptiveThresholdConfig(
            fixed_threshold=fixed_threshold_m,
            initial_threshold=initial_threshold_m,
            min_motion_th=min_motion_m,
        ),
    )


class KissOdometry:
    """Frame-to-map ICP odometry (KISS-ICP) over camera-frame point clouds.

    The odometry frame is the camera frame of the first registered frame. Defaults follow the tuning
    table in REFERENCE.md §1.2 for dense, short-range pseudo-LiDAR.

    Note: KISS-ICP's thread count is a process-wide setting fixed by the first instance built. With more
    than one thread its sums add in an order that depends on thread scheduling, so two runs differ by
    ~1e-14 m; the default (1) gives the same trajectory every run.
    """

    def __init__(
        self,
        voxel_size_m: float = 0.4,
        max_points_per_voxel: int = 10,
        min_range_m: float = 0.5,
        max_range_m: float = 30.0,
        max_icp_iterations: int = 100,
        *,
        convergence_criterion: float = 1e-4,
        max_threads: int = 1,
        fixed_threshold_m: float | None = None,
        initial_threshold_m: float = 2.0,
        min_motion_m: float = 0.1,
        min_points: int = MIN_POINTS,
        min_source_voxels: int = MIN_SOURCE_VOXELS,
        register_seen_only: bool = True,
    ) -> None:
        """``register_seen_only``: ICP registers only the points the previous camera saw too (``_registrable``);
        False: all of them (KISS-ICP's own; the source's choice on noisy depth, ``sources._kiss``)."""
        from kiss_icp.kiss_icp import KissICP

        if not 0.0 <= min_range_m < max_range_m:
            raise ConfigError(
                f"KISS-ICP needs 0 <= min_range_m < max_range_m, got {min_range_m} and {max_range_m}"
            )
        if voxel_size_m <= 0 or max_points_per_voxel < 1 or max_icp_iterations < 1:
            raise ConfigError(
                "KISS-ICP needs voxel_size_m > 0, max_points_per_voxel >= 1 and max_icp_iterations >= 1"
            )
        self.min_range_m = min_range_m
        self.max_range_m = max_range_m
        self.min_points = min_points
        self.min_source_voxels = min_source_voxels
        self.register_seen_only = register_seen_only
        self.voxel_size_m = voxel_size_m
        self.config = _kiss_config(
            voxel_size_m=voxel_size_m,
            max_points_per_voxel=max_points_per_voxel,
            min_range_m=min_range_m,
            max_range_m=max_range_m,
            max_icp_iterations=max_icp_iterations,
            convergence_criterion=convergence_criterion,
            max_threads=max_threads,
            fixed_threshold_m=fixed_threshold_m,
            initial_threshold_m=initial_threshold_m,
            min_motion_m=min_motion_m,
        )
        self._icp = KissICP(self.config)
        self._no_stamps = np.array([])  # KISS-ICP needs an array; empty = no deskew
        self.num_frames = 0
        self._seed_delta: np.ndarray | None = None  # ``reset``'s motion, taken once the first frame is in
        self._seeded_step = False  # the next registered step is predicted with ``reset``'s motion
        self._aligning: Callable[[np.ndarray], np.ndarray] | None = None  # ``realign`` during ``_register_fused``
        self._fitting: _MapFit | None = None  # ``map_misfits`` during ``_register_fused``

    def reset(self, motion: np.ndarray | None = None) -> None:
        """Start afresh: empty map; the next frame defines a new odometry frame.

        Args:
            motion: optional (4, 4) frame-to-frame motion (a frame's camera in the previous one) the
                constant-velocity model predicts the second frame with; None: zero velocity (KISS-ICP's start).
                Where the second frame's step lies beyond ICP's gate from it (``model_error_m`` over 3 x the
                threshold), that gap is not counted in KISS-ICP's adaptive threshold: it measures the seed (a motion
                remembered across a re-initialisation, from before a turn began), not the constant-velocity model's
                error, and as the threshold's only sample it would rule it alone (airsim-like tuning 26's car2,
                restarted in a 27 deg turn with the 0.5 deg step before it, registered the turn right and its
                threshold jumped to 34 m, which the health check took for two more failures).
        """
        from kiss_icp.kiss_icp import KissICP

        self._icp = KissICP(self.config)
        self.num_frames = 0
        self._seed_delta = None if motion is None else np.asarray(motion, dtype=np.float64).copy()
        self._seeded_step = False

    @property
    def threshold_m(self) -> float:
        """KISS-ICP's adaptive threshold σ, metres (correspondences are searched within 3σ)."""
        return float(self._icp.adaptive_threshold.get_threshold())

    def beyond_threshold(self, step_a: np.ndarray, step_b: np.ndarray) -> bool:
        """Whether two steps of the frame being registered ((4, 4) each: the camera in the previous one) move its
        source points apart by more than KISS-ICP's adaptive threshold σ (``threshold_m``; the median point's
        displacement, metres): within σ the two are one motion to ICP's kernel. Only inside a ``register`` call's
        ``fuse_step``."""
        if self._fitting is None:
            raise RuntimeError("KissOdometry.beyond_threshold is only valid inside register()'s fuse_step")
        return self._fitting.displacement_m(step_a, step_b) > self.threshold_m

    @property
    def predicted_delta(self) -> np.ndarray:
        """(4, 4) copy of the constant-velocity prediction of the next frame-to-frame motion."""
        return self._icp.last_delta.copy()

    @property
    def T_odom_cam(self) -> np.ndarray:
        """(4, 4) copy of the latest camera pose in the odometry frame."""
        return self._icp.last_pose.copy()

    def local_map_points(self) -> np.ndarray:
        """(M, 3) float64 points of KISS-ICP's local voxel map, odometry frame."""
        return np.asarray(self._icp.local_map.point_cloud(), dtype=np.float64)

    def register(
        self,
        points_cam: np.ndarray,
        delta_prior: np.ndarray | None = None,
        fuse_step: Callable[[np.ndarray], np.ndarray | Relocation] | None = None,
    ) -> Registration:
        """Register one cloud against the local map and return the new camera pose.

        Args:
            points_cam: (N, 3) points in the camera frame, metres (float32/float64; non-finite rows
                are dropped). N may be 0.
            delta_prior: (4, 4) predicted motion of this frame in the previous camera frame, replacing
                KISS-ICP's constant-velocity prediction as ICP's initial guess (e.g. with a rotation
                measured from the images).
            fuse_step: maps ICP's step (4, 4), the motion of this frame in the previous camera frame,
                to the step to keep (e.g. fused with another odometry's); the adaptive threshold, the
                local map and the pose are then updated with the kept step, as KISS-ICP does with its own
                (returning the very array it was given keeps exactly KISS-ICP's own update); or to a
                ``Relocation`` (the map restarts from this frame).

        Returns:
            ``Registration`` with a copy of ``T_odom_cam`` (4, 4). Clouds with fewer than
            ``min_points`` points in range, or filling fewer than ``min_source_voxels`` of KISS-ICP's
            source voxels, are not registered: the pose advances by the last motion (constant velocity)
            and the status is DEGENERATE_CLOUD.
        """
        pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        r = np.linalg.norm(pts, axis=1)
        in_range = (r >= self.min_range_m) & (r <= self.max_range_m)
        num_in_range = int(np.count_nonzero(in_range))
        self.num_frames += 1
        if delta_prior is not None:
            self._icp.last_delta = np.asarray(delta_prior, dtype=np.float64).copy()
        if num_in_range < self.min_points:
            return Registration(self._coast(), OdometryStatus.DEGENERATE_CLOUD, num_in_range)
        voxels = too_few_source_voxels(pts[in_range], self.voxel_size_m, self.min_source_voxels)
        if voxels is not None:
            return Registration(self._coast(), OdometryStatus.DEGENERATE_CLOUD, num_in_range, voxels)

        last_pose, last_delta = self._icp.last_pose.copy(), self._icp.last_delta.copy()
        misfit = self._register_fused(np.ascontiguousarray(pts), _own_step if fuse_step is None else fuse_step)
        if self._seed_delta is not None:  # the first frame is in (at the origin): predict on at the seeded motion
            self._icp.last_delta, self._seed_delta = self._seed_delta, None
            self._seeded_step = True
        if not np.isfinite(self._icp.last_pose).all():
            # the map may now hold points placed with a non-finite pose: restart it from the next frame
            self._icp.local_map.clear()
            self._icp.last_pose, self._icp.last_delta = last_pose, last_delta
            return Registration(self._coast(), OdometryStatus.ICP_FAILED, num_in_range)
        return Registration(self._icp.last_pose.copy(), OdometryStatus.OK, num_in_range, map_misfit=misfit)

    def _register_fused(
        self, pts: np.ndarray, fuse_step: Callable[[np.ndarray], np.ndarray | Relocation]
    ) -> float | None:
        """``KissICP.register_frame`` with ICP's step passed through ``fuse_step`` before the update of
        the threshold, the map and the pose (the same steps, in KISS-ICP's order; ``Relocation``: its
        docstring), and ICP run on the points the map can hold (``_registrable``). Returns the map misfit of the
        step kept where ``fuse_step`` measured the map's fit (``Registration.map_misfit``), else None."""
        icp = self._icp
        frame = icp.preprocessor.preprocess(pts, self._no_stamps, icp.last_delta)
        source, frame_downsample = icp.voxelize(frame)
        sigma = icp.adaptive_threshold.get_threshold()
        initial_guess = icp.last_pose @ icp.last_delta

        def align(guess_pose: np.ndarray) -> np.ndarray:  # the pose ICP reaches from ``guess_pose``
            points = source
            if self.register_seen_only:
                points = _registrable(source, np.linalg.inv(icp.last_pose) @ guess_pose, self.max_range_m,
                                      self.min_source_voxels)  # fmt: skip
            return icp.registration.align_points_to_map(
                points=points, voxel_map=icp.local_map, initial_guess=guess_pose,
                max_correspondance_distance=3 * sigma, kernel=sigma,
            )  # fmt: skip

        new_pose = align(initial_guess)
        icp_step = np.linalg.inv(icp.last_pose) @ new_pose
        self._aligning = lambda guess_step: np.linalg.inv(icp.last_pose) @ align(icp.last_pose @ guess_step)
        self._fitting = _MapFit(icp.local_map, source, icp.last_pose, 3 * sigma, self.max_range_m)
        try:
            step = fuse_step(icp_step)
            fitted = self._fitting.measured and not isinstance(step, Relocation)
            misfit = self._fitting([np.asarray(step, dtype=np.float64)])[0] if fitted else None
        finally:
            self._aligning = None
            self._fitting = None
        relocation = step if isinstance(step, Relocation) else None
        if relocation is not None:
            step = relocation.step
            icp.local_map.clear()
        if step is not icp_step:  # a step of its own: the pose follows it (ICP's own: exactly KISS-ICP's update)
            step = np.asarray(step, dtype=np.float64)
            new_pose = icp.last_pose @ step
        deviation = np.linalg.inv(initial_guess) @ new_pose
        seeded, self._seeded_step = self._seeded_step, False
        wrong_seed = seeded and model_error_m(deviation, self.max_range_m) > 3 * sigma  # ``reset``
        if relocation is None and not wrong_seed:  # a correction is not the motion model's error, nor a wrong seed's
            icp.adaptive_threshold.update_model_deviation(deviation)
        icp.local_map.update(frame_downsample, new_pose)
        icp.last_delta = step if relocation is None else np.asarray(relocation.velocity, dtype=np.float64)
        icp.last_pose = new_pose
        return misfit

    def map_misfits(self, *steps: np.ndarray) -> tuple[float, ...]:
        """How badly the frame being registered fits the local map if this frame's camera is each of ``steps``
        ((4, 4) each: the camera in the previous one): for each, the mean of min(d, g)^2 / g^2 over the frame's
        source points, d the distance to the plane through the nearest map points (point to plane: a step along a
        wall or the ground, which the map's samples cannot tell apart, costs nothing) and g ICP's correspondence
        gate (3 sigma); 0 when every point lies on the map, 1 when none lies within the gate. All steps are judged
        on the same points: those the previous camera saw too under every one of them (``_seen_before``). Only
        inside a ``register`` call's ``fuse_step``."""
        if self._fitting is None:
            raise RuntimeError("KissOdometry.map_misfits is only valid inside register()'s fuse_step")
        return self._fitting([np.asarray(s, dtype=np.float64) for s in steps])

    def map_judged(self, *steps: np.ndarray) -> int:
        """How many of the frame's source points ``map_misfits`` judges ``steps`` on (those the previous camera saw
        under every one of them): two steps far apart share few, and misfits on a few points say little. Only
        inside a ``register`` call's ``fuse_step``."""
        if self._fitting is None:
            raise RuntimeError("KissOdometry.map_judged is only valid inside register()'s fuse_step")
        return self._fitting.judged([np.asarray(s, dtype=np.float64) for s in steps])

    def realign(self, guess_step: np.ndarray) -> np.ndarray:
        """ICP of the frame being registered, again, from another initial step (``guess_step`` (4, 4): this frame's
        camera in the previous one), against the same local map with the same threshold; returns the step it
        reaches (4, 4). Only inside a ``register`` call's ``fuse_step`` (the map is not touched)."""
        if self._aligning is None:
            raise RuntimeError("KissOdometry.realign is only valid inside register()'s fuse_step")
        return self._aligning(np.asarray(guess_step, dtype=np.float64))

    def _coast(self) -> np.ndarray:
        """Advance the pose by the last frame-to-frame motion without touching the map."""
        self._icp.last_pose = self._icp.last_pose @ self._icp.last_delta
        return self._icp.last_pose.copy()


def model_error_m(deviation: np.ndarray, max_range_m: float) -> float:
    """KISS-ICP's measure of a (4, 4) deviation from its prediction, metres (its adaptive threshold's sample): the
    translation's length plus how far the rotation moves a point at ``max_range_m`` (2 r sin(angle / 2))."""
    cos = np.clip((np.trace(deviation[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(deviation[:3, 3]) + 2.0 * max_range_m * np.sin(np.arccos(cos) / 2.0))


def _own_step(icp_step: np.ndarray) -> np.ndarray:
    """``register``'s ``fuse_step`` where none is given: ICP's very step (KISS-ICP's own update)."""
    return icp_step


def _registrable(source_xyz: np.ndarray, guess_step: np.ndarray, max_range_m: float, min_points: int) -> np.ndarray:
    """The (M, 3) rows of the frame's source points ((N, 3), its camera frame, metres; contiguous) ICP registers
    from ``guess_step`` ((4, 4): this camera in the previous one): those the previous camera saw too under it
    (``_seen_before``), where they are ``min_points`` or more; all of them otherwise.

    A point the map cannot hold yet pulls ICP towards the map's nearest edge: a camera looking back from a car
    sees a new strip of road and kerb right below it in every frame (the previous camera, a step behind it, had
    that strip behind itself), its points matched to the near edge of the road the map holds, a pull away from the
    camera along the ground below it, so a tilt. KISS-ICP's steps pitched 0.03 deg per frame on the synthia-like
    backward cameras at 3.3 frames/s (tuning seed 14: 9.9 deg over 310 frames, the trajectory 67 m below the road
    after 800 m, drift 2.5 %; registered on what the previous camera saw, 0.57 %). The same pull, weaker, at the
    far edge of a camera looking ahead and where a UAV's view slides on. KISS-ICP alone on the tuning worlds
    (10-25 at 3.3 frames/s, 10-13 at 10 Hz; 140 drives): backward cameras' median ATE 3.23 -> 0.79 m at 3.3
    frames/s (16 drives, 13 better) and 1.41 -> 0.72 m at 10 Hz, UAVs' 0.87 -> 0.55 and 0.69 -> 0.39 m, cars
    ahead alike or a little better; 3-15 % more CPU.

    Not on noisy depth (``KissOdometry.register_seen_only``, off where the measured depth noise is not 0): on the
    tuning worlds rendered with 2 % depth noise the UAVs of seeds 75-78 drifted to 3.8 / 5.1 / 5.8 / 3.4 m ATE
    registered on what the previous camera saw, against 2.0 / 3.6 / 1.5 / 2.3 m on everything (why is not known)."""
    seen = _seen_before(source_xyz, [guess_step], max_range_m)
    if int(np.count_nonzero(seen)) < max(min_points, 1) or seen.all():
        return source_xyz
    return np.ascontiguousarray(source_xyz[seen])


def _seen_before(points_cam: np.ndarray, steps: list[np.ndarray], max_range_m: float) -> np.ndarray:
    """(N,) bool: the points of this frame's cloud ((N, 3), its camera frame) that the previous camera saw too under
    every one of ``steps`` (each this camera in the previous one): in front of it, within the range and within the
    cloud's own span of bearings (its field of view). A right step into a turn or down the road sees an edge of
    the world the map does not hold yet; judged only on what every step puts where the map was made, it does
    not pay for that edge."""
    z = np.maximum(points_cam[:, 2], 1e-9)
    span_x, span_y = points_cam[:, 0] / z, points_cam[:, 1] / z
    keep = points_cam[:, 2] > 0
    if not keep.any():
        return keep
    lo_x, hi_x, lo_y, hi_y = span_x[keep].min(), span_x[keep].max(), span_y[keep].min(), span_y[keep].max()
    for step in steps:
        prev = points_cam @ step[:3, :3].T + step[:3, 3]
        zp = np.maximum(prev[:, 2], 1e-9)
        x, y = prev[:, 0] / zp, prev[:, 1] / zp
        keep &= (prev[:, 2] > 0) & (np.linalg.norm(prev, axis=1) < max_range_m)
        keep &= (x >= lo_x) & (x <= hi_x) & (y >= lo_y) & (y <= hi_y)
    return keep


PLANE_NEIGHBOURS = 6
"""Map points a point's local plane is fitted to (``KissOdometry.map_misfits``)."""


class _MapFit:
    """``KissOdometry.map_misfits`` of one frame: the local map's points in a KD-tree, built on the first call."""

    def __init__(
        self, local_map, source_xyz: np.ndarray, T_odom_prev: np.ndarray, gate_m: float, max_range_m: float
    ) -> None:
        self._map, self._source, self._T_prev = local_map, np.asarray(source_xyz), T_odom_prev
        self._gate, self._max_range = gate_m, max_range_m
        self._tree = None

    @property
    def measured(self) -> bool:
        """Whether the map's search tree was built (a misfit was asked for): another one then costs little."""
        return self._tree is not None

    def __call__(self, steps: list[np.ndarray]) -> tuple[float, ...]:
        from scipy.spatial import cKDTree

        source = self._source[_seen_before(self._source, steps, self._max_range)]
        if self._tree is None:
            points = self._map.point_cloud()
            self._tree = cKDTree(points) if len(points) else None
        if self._tree is None or len(source) == 0:
            return tuple(1.0 for _ in steps)
        return tuple(self._misfit(source @ (self._T_prev @ s)[:3, :3].T + (self._T_prev @ s)[:3, 3]) for s in steps)

    def displacement_m(self, step_a: np.ndarray, step_b: np.ndarray) -> float:
        """Median distance, metres, between where the two steps ((4, 4) each) put the frame's source points."""
        if len(self._source) == 0:
            return 0.0
        a, b = np.asarray(step_a, dtype=np.float64), np.asarray(step_b, dtype=np.float64)
        moved = self._source @ (a[:3, :3] - b[:3, :3]).T + (a[:3, 3] - b[:3, 3])
        return float(np.median(np.linalg.norm(moved, axis=1)))

    def judged(self, steps: list[np.ndarray]) -> int:
        """The source points ``__call__`` judges ``steps`` on."""
        return int(_seen_before(self._source, steps, self._max_range).sum())

    def _misfit(self, points_xyz: np.ndarray) -> float:
        """Mean of min(r, g)^2 / g^2 over (N, 3) points in the odometry frame, r the distance to the plane through
        the nearest map points (``PLANE_NEIGHBOURS`` within the gate g; a point with fewer is r = g): sliding
        along a wall or the ground, which the map's samples cannot tell apart, costs nothing."""
        d, idx = self._tree.query(points_xyz, k=PLANE_NEIGHBOURS, distance_upper_bound=self._gate)
        full = np.isfinite(d).all(axis=1)
        r = np.full(len(points_xyz), self._gate)
        if full.any():
            near = self._tree.data[idx[full]]  # (M, k, 3)
            centred = near - near.mean(axis=1, keepdims=True)
            normals = np.linalg.eigh(np.einsum("mki,mkj->mij", centred, centred))[1][:, :, 0]  # least spread
            r[full] = np.abs(np.einsum("mi,mi->m", points_xyz[full] - near.mean(axis=1), normals))
        return float(np.mean(np.minimum(r, self._gate) ** 2) / self._gate**2)


def too_few_source_voxels(points_xyz: np.ndarray, voxel_size_m: float, minimum: int) -> int | None:
    """The source voxels (``source_voxel_count``) the (N, 3) points fill when fewer than ``minimum``, else None.
    Every eighth point is counted first: a subset fills no more voxels than all, so only a cloud whose subset
    falls short is counted in full (~0.5 ms against ~4 ms for 30k points)."""
    if source_voxel_count(points_xyz[::8], voxel_size_m) >= minimum:
        return None
    count = source_voxel_count(points_xyz, voxel_size_m)
    return count if count < minimum else None


def source_voxel_count(points_xyz: np.ndarray, voxel_size_m: float) -> int:
    """How many of KISS-ICP's source voxels (``SOURCE_VOXEL_FACTOR`` x ``voxel_size_m``, one point each) the
    (N, 3) points fill (metres, any frame; KISS-ICP's own voxel grid)."""
    from kiss_icp.voxelization import voxel_down_sample

    if len(points_xyz) == 0:
        return 0
    points = np.ascontiguousarray(points_xyz, dtype=np.float64)
    return len(voxel_down_sample(points, SOURCE_VOXEL_FACTOR * voxel_size_m))
