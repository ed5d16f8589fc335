"""One robot's front end: perception -> pseudo-LiDAR -> odometry -> keyframes -> semantic graph."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from shgm_slam.agents import segment_agent
from shgm_slam.config import ShgmConfig
from shgm_slam.geometry.ground import ground_normal
from shgm_slam.geometry.se3 import inverse
from shgm_slam.graph.extraction import extract_objects
from shgm_slam.graph.semantic_graph import SemanticGraph
from shgm_slam.messages import KeyframeMessage
from shgm_slam.odometry.clouds import depth_to_cloud
from shgm_slam.odometry.estimate import OdometryEstimate, OdometrySource
from shgm_slam.odometry.health import HealthLimits, OdometryFailure, OdometryHealthMonitor
from shgm_slam.odometry.sources import OdometryChoice
from shgm_slam.perception import PerceptionSource
from shgm_slam.robot.keyframes import KeyframeSelector
from shgm_slam.robot.segments import TrajectorySegment
from shgm_slam.types import Frame, Sequence

log = logging.getLogger(__name__)


SEGMENT_GRACE_S = 1.0
"""After a re-initialisation, predicted poses are not checked against the image motion for this long."""

MOTION_MEMORY_S = 1.0
"""A re-initialised odometry predicts its first step with the robot's last trusted frame-to-frame motion (the
step into the frame before the divergence's onset) when the new segment's first frame comes at most this long
after it: a vehicle's velocity does not restart with its odometry, and a segment that begins inside a sharp
turn, predicted at rest, reads its first steps as standing still wherever PnP fails and the images give no
sure turn (airsim-like, a car's visual odometry: 21 deg of a turn lost in two frames). Older motion says
little about the present one: the first step is then predicted at rest."""


@dataclass
class FrameResult:
    """Everything one front-end step produced (for the orchestrator, the viewer and the summary).

    ``agent`` is the trajectory segment the frame belongs to (``segment_agent``); ``failure`` the
    odometry divergence this frame revealed (then the frame starts a new segment), else None.
    ``T_odom_cam`` is NaN for frames that belong to no segment (after a divergence, before the
    odometry measures again).
    """

    robot: str
    frame: Frame
    T_odom_cam: np.ndarray
    depth_m: np.ndarray | None
    label_ids: np.ndarray | None
    points_cam: np.ndarray
    point_labels: np.ndarray | None
    odometry_ok: bool
    message: KeyframeMessage | None
    timings_ms: dict[str, float]
    agent: str = ""
    failure: OdometryFailure | None = None


class RobotFrontend:
    """One robot's front end: perception -> pseudo-LiDAR -> odometry -> keyframes -> semantic graph.

    Each trajectory segment's graph lives in its own odometry frame; nodes are anchored to keyframes.
    With ``cfg.odometry.health_check`` every pose is checked (``odometry.health``); on a divergence the
    segment is cut at its onset (frames from the onset on get NaN poses and segment -1), the odometry
    is re-initialised, and the next measured frame starts a new segment with a fresh graph, sent to
    the map server as a new agent (``segment_agent``). A robot allowed ``max_segments`` segments (its share
    of the pose graph's agents) whose last one diverges too stops there: its later frames are dropped
    (``stopped``), and the run goes on without it.
    """

    def __init__(
        self,
        name: str,
        sequence: Sequence,
        cfg: ShgmConfig,
        perception: PerceptionSource,
        odometry: OdometrySource,
        odometry_choice: OdometryChoice | None = None,
        *,
        depth_predicted: bool | None = None,
        max_segments: int | None = None,
        settings_digest: str = "",
    ) -> None:
        self.name = name
        # ``ShgmConfig.front_end_digest`` of the fleet config it was built from ("" = unknown): the map server
        # compares it with its own
        self.settings_digest = settings_digest
        self.max_segments = max_segments  # trajectory segments it may start (None: no limit)
        # depth from a network (a configured model, or files a model wrote), not measured
        self.depth_predicted = cfg.perception.depth_model is not None if depth_predicted is None else depth_predicted
        self.sequence = sequence
        self.cfg = cfg
        self.perception = perception
        self.odometry = odometry
        self.odometry_choice = odometry_choice  # which odometry and why (reported in the summary)
        self.measured_frames = 0  # frames the odometry measured (not predicted)
        self.planar_turns = 0  # of them, frames whose turn came from planar motion (visual odometry)
        self.road_steps = 0  # of them, frames whose step came from the road's image motion (visual odometry)
        self.image_steps = 0  # of them, frames where KISS-ICP slipped and the image tracks' step was kept
        self.image_windows = 0  # of them, frames where KISS-ICP slid over the last second, corrected from image tracks
        self.references = 0  # frames that became the visual odometry's tracking reference
        self.levelled_references = 0  # of them, references whose tilt was turned towards level (ground attitude)
        # predicted depth scaled to the camera's height above the road (``perception.ground_scale``): whether
        # it is on for this robot, and the factor of each processed frame it scaled
        self.ground_scale_on = getattr(perception, "ground_scale", None) is not None
        self.depth_scales: list[float] = []
        self.health = (
            OdometryHealthMonitor(HealthLimits.from_config(cfg.odometry)) if cfg.odometry.health_check else None
        )
        # per-frame rows (``T_odom_cam``, ``frame_kf``, ``frame_segment``), room for more than the sequence holds
        # when its frames arrive one by one (``data.stream``)
        self._T_odom_cam = np.full((0, 4, 4), np.nan)
        self._frame_kf = np.full(0, -1, dtype=np.int64)
        self._frame_segment = np.full(0, -1, dtype=np.int64)
        self._fit_rows()
        self.segments: list[TrajectorySegment] = []
        self.failures: list[OdometryFailure] = []
        # the last trusted frame-to-frame motion before the last divergence (4, 4) and its frame's time, seconds
        self._last_motion: tuple[np.ndarray, float] | None = None
        self._steady = True  # the current segment has measured a step (a restarted one: not yet; ``process``)
        self.first_changed_row = 0  # the first row of the per-frame arrays the last ``process`` call changed
        self._new_segment(0)

    @property
    def T_odom_cam(self) -> np.ndarray:
        """(N, 4, 4) each frame of the sequence in its own segment's odometry frame (NaN: in no segment)."""
        return self._T_odom_cam[: len(self.sequence)]

    @property
    def frame_kf(self) -> np.ndarray:
        """(N,) int64 the last keyframe (of its segment) at or before each frame (-1: none)."""
        return self._frame_kf[: len(self.sequence)]

    @property
    def frame_segment(self) -> np.ndarray:
        """(N,) int64 the segment of each frame (-1: none)."""
        return self._frame_segment[: len(self.sequence)]

    def _fit_rows(self) -> None:
        """Room in the per-frame rows for every frame the sequence holds now (it grows when frames arrive one by
        one: doubled, so that N frames cost O(N) copies)."""
        n, held = len(self.sequence), self._T_odom_cam.shape[0]
        if n <= held:
            return
        grow = max(n, 2 * held) - held
        self._T_odom_cam = np.concatenate([self._T_odom_cam, np.full((grow, 4, 4), np.nan)])
        self._frame_kf = np.concatenate([self._frame_kf, np.full(grow, -1, dtype=np.int64)])
        self._frame_segment = np.concatenate([self._frame_segment, np.full(grow, -1, dtype=np.int64)])

    def release(self) -> None:
        """Free the models and the odometry once another process runs this robot (``robot.remote``): the
        state stays readable, but ``process`` can no longer be called."""
        self.perception = None  # type: ignore[assignment]
        self.odometry = None  # type: ignore[assignment]

    # --- segments ------------------------------------------------------------------------------

    @property
    def segment(self) -> TrajectorySegment:
        """The current trajectory segment."""
        return self.segments[-1]

    @property
    def graph(self) -> SemanticGraph:
        """The current segment's semantic graph."""
        return self.segment.graph

    @property
    def num_keyframes(self) -> int:
        """Keyframes over all segments."""
        return sum(s.num_keyframes for s in self.segments)

    def _new_segment(self, first_frame: int) -> None:
        k = len(self.segments)
        self.segments.append(
            TrajectorySegment(
                k, segment_agent(self.name, k), first_frame,
                SemanticGraph(self.cfg.graph.merge_radius_m, self.cfg.graph.connectivity_m),
                KeyframeSelector(self.cfg.keyframes.distance_m, self.cfg.keyframes.angle_deg),
            )
        )  # fmt: skip

    @property
    def stopped(self) -> bool:
        """Its last allowed segment diverged (``max_segments``): it processes no more frames."""
        return self.segment.end_failure is not None

    def _fail(self, failure: OdometryFailure) -> None:
        """Cut the current segment at the failure's onset and re-initialise the odometry (or, when it has had
        its ``max_segments``, stop)."""
        last = self.max_segments is not None and len(self.segments) >= self.max_segments
        then = "its later frames are dropped (last allowed trajectory segment)" if last else (
            "restarting as a new trajectory segment")  # fmt: skip
        log.warning("%s: odometry diverged (%s); %s", self.name, failure.describe(), then)
        self.failures.append(failure)
        seg = self.segment
        seg.end_failure = failure
        self._last_motion = self._motion_before(failure.onset_frame)
        self._leave_segment(np.arange(self.T_odom_cam.shape[0]) >= failure.onset_frame)
        if last:
            return
        self._restart(failure.detected_frame)
        # a new segment starts at the next measured frame (the one after a re-initialisation)
        self._new_segment(-1)
        self._steady = False

    def _leave_segment(self, rows: np.ndarray) -> None:
        """The current segment's frames among ``rows`` ((N,) bool over all frames) belong to no segment now."""
        rows = rows & (self.frame_segment == self.segment.index)
        self.T_odom_cam[rows] = np.nan
        self.frame_segment[rows] = -1
        self.frame_kf[rows] = -1
        if rows.any():
            self.first_changed_row = min(self.first_changed_row, int(np.argmax(rows)))

    def _restart(self, first_index: int) -> None:
        """Re-initialise the odometry (``_restart_motion``) and the health check for a segment whose first frame
        is ``first_index``."""
        self.odometry.reset(self._restart_motion(first_index))
        self.health.reset()

    def _motion_before(self, onset: int) -> tuple[np.ndarray, float] | None:
        """The current segment's last step before frame ``onset`` (4, 4: frame onset-1's camera in frame onset-2's)
        and frame onset-1's time, seconds; None when those two frames are not both in the segment."""
        a, b = onset - 2, onset - 1
        seg = self.segment.index
        if a < 0 or self.frame_segment[a] != seg or self.frame_segment[b] != seg:
            return None
        motion = inverse(self.T_odom_cam[a]) @ self.T_odom_cam[b]
        return (motion, float(self.sequence.timestamps_s[b])) if np.isfinite(motion).all() else None

    def _restart_motion(self, index: int) -> np.ndarray | None:
        """(4, 4) the motion a re-initialised odometry whose first frame is ``index`` predicts its first step with
        (``MOTION_MEMORY_S``), or None (at rest)."""
        if self._last_motion is None or index >= len(self.sequence):
            return None
        motion, t_s = self._last_motion
        return motion if self.sequence.timestamps_s[index] - t_s <= MOTION_MEMORY_S else None

    # --- one frame -------------------------------------------------------------------------------

    def process(self, index: int) -> FrameResult:
        """Run frame ``index`` through the front end.

        Raises:
            DataError: the frame cannot be loaded or has no usable depth (the caller logs and skips it).
        """
        t0 = time.perf_counter()
        self.first_changed_row = index
        self._fit_rows()
        frame = self.sequence[index]
        t_load = time.perf_counter()
        if self.stopped:
            return self._dropped(frame, {"load": (t_load - t0) * 1e3})
        perceived = self.perception.process(frame)
        if perceived.depth_scale is not None:
            self.depth_scales.append(perceived.depth_scale)
        t_perc = time.perf_counter()
        o = self.cfg.odometry
        points_cam, point_labels = depth_to_cloud(
            perceived.depth_m,
            frame.intrinsics,
            stride=o.cloud_stride,
            min_range_m=o.min_range_m,
            max_range_m=o.max_range_m,
            label_ids=perceived.label_ids,
        )
        t_cloud = time.perf_counter()
        est = self.odometry.update(frame, points_cam, perceived.depth_m, perceived.label_ids)
        failure = None
        if self.health is not None:
            failure = self._check(index, frame.timestamp_s, est)
            if failure is not None:
                self._fail(failure)
                if self.stopped:
                    return self._dropped(frame, {"load": (t_load - t0) * 1e3}, failure)
                est = self.odometry.update(frame, points_cam, perceived.depth_m, perceived.label_ids)
                self.health.check(index, frame.timestamp_s, est.T_odom_cam, measured=est.ok)
        seg = self.segment
        if seg.first_frame < 0:  # after a re-initialisation: wait for a measured pose
            if est.ok:
                seg.first_frame = index
                if failure is None:  # (a frame that just failed was checked again above)
                    self.health.check(index, frame.timestamp_s, est.T_odom_cam)
            else:
                self._restart(index + 1)
        elif not self._steady and not est.ok:  # a restarted segment whose first step was not measured either
            est = self._move_origin(index, frame, points_cam, perceived.depth_m, perceived.label_ids)
        self._steady = self._steady or (est.ok and index > seg.first_frame >= 0)
        self.measured_frames += bool(est.ok)
        self.planar_turns += bool(est.planar_turn)
        self.road_steps += bool(est.road_step)
        self.image_steps += bool(est.image_step)
        self.image_windows += bool(est.image_window)
        self.references += bool(est.new_reference)
        self.levelled_references += bool(est.levelled)
        T_odom_cam = est.T_odom_cam if seg.first_frame >= 0 else np.full((4, 4), np.nan)
        t_odo = time.perf_counter()
        message = None
        timings = {
            "load": (t_load - t0) * 1e3,
            **{f"perception_{k}": v for k, v in perceived.timings_ms.items()},
            "cloud": (t_cloud - t_perc) * 1e3,
            "odometry": (t_odo - t_cloud) * 1e3,
        }
        if seg.first_frame >= 0:
            self.T_odom_cam[index] = T_odom_cam
            self.frame_segment[index] = seg.index
            # keyframes only from measured poses: a prediction may be cut away by a later failure
            # (and in a restarted segment only once it has measured a step: its origin may still move)
            if est.ok and self._steady and seg.keyframes.is_keyframe(T_odom_cam) and perceived.label_ids is not None:
                message = self._keyframe(seg, index, frame, perceived, T_odom_cam, points_cam, point_labels, timings)
            self.frame_kf[index] = seg.num_keyframes - 1
        return FrameResult(
            self.name, frame, T_odom_cam, perceived.depth_m, perceived.label_ids, points_cam, point_labels,
            est.ok, message, timings, seg.agent, failure,
        )  # fmt: skip

    def _move_origin(
        self, index: int, frame: Frame, points_cam: np.ndarray, depth_m: np.ndarray, label_ids: np.ndarray | None
    ) -> OdometryEstimate:
        """Restart the current segment's odometry at frame ``index``: a segment restarted after a divergence
        whose steps so far were predicted, not measured (PnP failed, a blank frame), would carry that guess as
        its motion (a new segment that begins inside a sharp turn: its first steps predicted at the last trusted
        motion or at rest, 15-21 deg of the turn lost); its frames so far (no keyframe yet) leave it, and this
        frame becomes its origin. Returns this frame's estimate (the new origin)."""
        seg = self.segment
        self._leave_segment(np.arange(self.T_odom_cam.shape[0]) < index)
        seg.first_frame = index
        self._restart(index)
        est = self.odometry.update(frame, points_cam, depth_m, label_ids)
        if not est.ok:  # no origin here either (a blank frame): wait for a measured pose, as after a divergence
            seg.first_frame = -1
            self._restart(index + 1)
        else:
            self.health.check(index, frame.timestamp_s, est.T_odom_cam)
        return est

    def _dropped(self, frame: Frame, timings: dict[str, float], failure: OdometryFailure | None = None) -> FrameResult:
        """The result of a frame after the robot ``stopped``: in no segment, nothing sent."""
        return FrameResult(self.name, frame, np.full((4, 4), np.nan), None, None, np.zeros((0, 3), np.float32), None,
                           False, None, timings, self.segment.agent, failure)  # fmt: skip

    def _check(self, index: int, timestamp_s: float, est: OdometryEstimate) -> OdometryFailure | None:
        seg = self.segment
        if seg.first_frame < 0:
            return None
        disagreement = est.rotation_disagreement_deg
        if not est.ok and timestamp_s - self.sequence.timestamps_s[seg.first_frame] < SEGMENT_GRACE_S:
            # a fresh segment's prediction has no motion to continue yet: a turn it misses is not a
            # divergence (coasting still ends it after ``max_coast_s``); without this a sharp turn right
            # after a re-initialisation cuts one new segment per frame
            disagreement = None
        return self.health.check(
            index, timestamp_s, est.T_odom_cam, measured=est.ok,
            registration_threshold_m=est.threshold_m, rotation_disagreement_deg=disagreement,
            rebased=est.image_window, map_misfit=est.map_misfit,
        )  # fmt: skip

    def _keyframe(self, seg, index, frame, perceived, T_odom_cam, points_cam, point_labels, timings) -> KeyframeMessage:
        t0 = time.perf_counter()
        ex = self.cfg.extraction
        objects = extract_objects(
            perceived.depth_m,
            perceived.label_ids,
            frame.intrinsics,
            T_odom_cam,
            labels=ex.labels,
            max_depth_m=ex.max_depth_m,
            min_depth_m=ex.min_depth_m,
            depth_step_m=ex.depth_step_m,
            min_blob_fraction=ex.min_blob_fraction,
            depth_percentiles=ex.depth_percentiles(self.depth_predicted),
        )
        t_ex = time.perf_counter()
        kf = seg.num_keyframes
        update = seg.graph.add_keyframe(kf, T_odom_cam, objects)
        t_graph = time.perf_counter()
        seg.kf_frames.append(index)
        seg.kf_poses.append(T_odom_cam.copy())
        n_cam = ground_normal(points_cam, point_labels)
        up = None if n_cam is None else T_odom_cam[:3, :3] @ n_cam  # this keyframe's ground normal, odometry frame
        timings["extraction"] = (t_ex - t0) * 1e3
        timings["graph"] = (t_graph - t_ex) * 1e3
        return KeyframeMessage(seg.agent, kf, index, frame.timestamp_s, T_odom_cam.copy(), update, up)
