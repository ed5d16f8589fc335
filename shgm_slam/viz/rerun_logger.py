"""All Rerun logging: one method per data kind, a do-nothing logger when off, and the factory.

The pipeline calls these methods; they never decide anything. Every pose is ``T_shared_X`` (4, 4)
float64 in the SHARED world frame (robot 0's odometry frame, a camera RDF frame: x right, y down,
z forward, metres) and every point set is already expressed in that frame. The entity tree is
documented in ``viz/blueprint.py``.

Timelines: ``frame`` (the robot's frame index), ``step`` (a global counter incremented by every
``set_time`` call, monotonic even though robots are interleaved) and ``sensor_time`` (the frame's
timestamp as a duration in seconds). Rerun keeps the time per thread: call ``set_time`` on the thread
that logs.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading
import time
from enum import Enum
from pathlib import Path
from typing import Protocol

import numpy as np
import rerun as rr

from shgm_slam.arrays import thinning_stride
from shgm_slam.errors import ConfigError, DataError
from shgm_slam.labels import CITYSCAPES_CLASSES, CITYSCAPES_COLORS_RGB, IGNORE_ID
from shgm_slam.types import GraphArrays, Intrinsics
from shgm_slam.viz.blueprint import (
    LOG,
    METRICS,
    WORLD,
    camera_path,
    default_blueprint,
    error_path,
    matches_path,
    robot_path,
    timings_path,
)

DEFAULT_CONNECT_URL = "rerun+http://127.0.0.1:9876/proxy"
CONNECT_TIMEOUT_S = 2.0
"""How long ``--rerun connect`` waits for a viewer to answer before the run goes on without it."""
FLUSH_TIMEOUT_S = 10.0
"""How long closing waits for the sink to take the last data (a viewer that went away must not hang the run)."""

log = logging.getLogger(__name__)


def viewer_address(url: str) -> tuple[str, int]:
    """``(host, port)`` of a Rerun gRPC URL such as ``rerun+http://127.0.0.1:9876/proxy``.

    Raises:
        ConfigError: the URL is not of that form.
    """
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(url)
        host, port = parts.hostname, parts.port
    except ValueError as exc:
        raise ConfigError(f"--rerun-url {url!r} is not a URL ({exc}); e.g. {DEFAULT_CONNECT_URL}") from None
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not host or port is None:
        raise ConfigError(f"--rerun-url {url!r}: expected rerun+http://HOST:PORT/proxy, e.g. {DEFAULT_CONNECT_URL}")
    return host, port


_H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
"""The HTTP/2 client connection preface and an empty SETTINGS frame (RFC 9113, 3.4 and 6.5)."""


def viewer_reachable(host: str, port: int, timeout_s: float = CONNECT_TIMEOUT_S, *, tls: bool = False) -> bool:
    """True when a gRPC server (a Rerun viewer) answers at ``host:port`` within ``timeout_s``.

    A gRPC server answers the HTTP/2 connection preface with a SETTINGS frame. Anything else listening
    there (a web server, a socket that never replies) is not a viewer: streaming the recording to it would
    fail at the end of the run or block it. With ``tls`` (``rerun+https``) only the TCP connection is tried.
    """
    deadline = time.monotonic() + timeout_s
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            if tls:
                return True
            sock.sendall(_H2_PREFACE)
            head = b""
            while len(head) < 9:  # a frame header: length (3), type (1), flags (1), stream id (4)
                sock.settimeout(max(deadline - time.monotonic(), 0.01))
                chunk = sock.recv(9 - len(head))
                if not chunk:
                    return False
                head += chunk
            return head[3] == 0x04  # SETTINGS
    except OSError:  # refused, unreachable, reset, or no answer in time
        return False


ROBOT_COLORS_RGB = np.array(
    [(0, 150, 255), (255, 140, 0), (200, 60, 255), (0, 210, 200), (255, 215, 0), (255, 90, 170),
     (140, 90, 60), (150, 150, 255)],
    dtype=np.uint8,
)  # fmt: skip
"""Fixed per-robot palette (robot i gets colour i mod 8); no pure green/red (= match accepted/rejected)."""

STAGE_COLORS_RGB = np.array(
    [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
     (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)],
    dtype=np.uint8,
)  # fmt: skip
"""Palette of timing series, assigned to stages in order of first appearance; robots shade it."""

ROBOT_SHADES = (0.0, 0.45, -0.45, 0.7, -0.7)
"""Per robot (index mod 5): blend of a stage colour towards white (> 0) or black (< 0)."""


ODOMETRY_COLOR_RGB = (150, 150, 150)
MATCH_ACCEPTED_RGB = (0, 230, 64)
MATCH_REJECTED_RGB = (230, 30, 30)


def series_color(stage_rgb: np.ndarray, robot_index: int) -> np.ndarray:
    """(3,) uint8 colour of a timing series: the stage's colour shaded by the robot's index."""
    shade = ROBOT_SHADES[robot_index % len(ROBOT_SHADES)]
    target = 255.0 if shade > 0 else 0.0
    rgb = (1 - abs(shade)) * stage_rgb.astype(np.float64) + abs(shade) * target
    return np.round(rgb).astype(np.uint8)


class RerunMode(str, Enum):
    """Where the recording goes: a spawned viewer, an .rrd file, a running viewer/server, or nowhere."""

    SPAWN = "spawn"
    SAVE = "save"
    CONNECT = "connect"
    OFF = "off"


class LogLevel(str, Enum):
    """Severity of a text log line (shown and filterable in the viewer's log view)."""

    DEBUG = "DEBUG"
    INFO = "INFO"
    WARN = "WARN"
    ERROR = "ERROR"


def node_radius_m(sizes: np.ndarray) -> np.ndarray:
    """Display radius of graph nodes, metres: ``0.3 + 0.2 * log1p(size / 1000)`` for (N,) sizes >= 0.

    A 1 px object is 0.3 m, a 5000 px blob about 0.66 m, a 100 kpx building about 1.2 m.
    """
    return 0.3 + 0.2 * np.log1p(np.maximum(np.asarray(sizes, dtype=np.float64), 0.0) / 1000.0)


def depth_to_mm_u16(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) metres (0 or non-finite = invalid) to (H, W) uint16 millimetres, 0 = invalid or > 65.535 m."""
    mm = np.rint(np.asarray(depth_m, dtype=np.float32) * np.float32(1000.0))
    mm[~(mm <= 65535.0) | (mm < 0)] = 0  # also catches NaN
    return mm.astype(np.uint16)


class Viz(Protocol):
    """What the pipeline logs. Implementations: ``RerunLogger`` and ``NullLogger``.

    ``enabled`` is False when nothing is shown: callers skip computing what only the viewer needs
    (fused trajectories, graphs in the shared frame) instead of handing it to a no-op. ``max_cloud_points``:
    the most points of a frame's cloud it draws (``thinning_stride``; 0 when nothing is shown), so that
    callers thin a cloud before transforming or sending it.
    """

    enabled: bool
    max_cloud_points: int

    def setup(self, robots: dict[str, Intrinsics]) -> None: ...

    def set_time(self, robot: str, frame_index: int, timestamp_s: float) -> None: ...

    def log_frame(
        self,
        robot: str,
        T_shared_cam: np.ndarray,
        image_rgb: np.ndarray | None,
        depth_m: np.ndarray | None,
        label_ids: np.ndarray | None,
        points_shared: np.ndarray | None = None,
        point_labels: np.ndarray | None = None,
    ) -> None: ...

    def log_trajectories(
        self, robot: str, odometry_xyz: np.ndarray, fused_xyz: np.ndarray | None, chunk: int = 0
    ) -> None: ...

    def log_graph(
        self, robot: str, graph: GraphArrays, chunk: int = 0, drawn: np.ndarray | None = None
    ) -> None: ...

    def clear_map(self, robot: str) -> None: ...

    def log_matches(
        self,
        robot_a: str,
        robot_b: str,
        positions_a: np.ndarray,
        positions_b: np.ndarray,
        accepted: bool,
        num_inliers: int | None = None,
        score: float | None = None,
    ) -> None: ...

    def log_text(self, message: str, level: LogLevel | str = LogLevel.INFO) -> None: ...

    def log_odometry_failure(self, robot: str, message: str, position_shared: np.ndarray | None = None) -> None: ...

    def log_timings(self, robot: str, timings_ms: dict[str, float]) -> None: ...

    def log_scalar(self, path: str, value: float) -> None: ...

    def log_error(self, robot: str, error_m: float) -> None: ...

    def close(self) -> None: ...


class NullLogger:
    """A ``Viz`` that does nothing (``--rerun off``); every call is a cheap no-op."""

    enabled = False
    max_cloud_points = 0

    def setup(self, robots: dict[str, Intrinsics]) -> None:
        pass

    def set_time(self, robot: str, frame_index: int, timestamp_s: float) -> None:
        pass

    def log_frame(
        self,
        robot: str,
        T_shared_cam: np.ndarray,
        image_rgb: np.ndarray | None,
        depth_m: np.ndarray | None,
        label_ids: np.ndarray | None,
        points_shared: np.ndarray | None = None,
        point_labels: np.ndarray | None = None,
    ) -> None:
        pass

    def log_trajectories(
        self, robot: str, odometry_xyz: np.ndarray, fused_xyz: np.ndarray | None, chunk: int = 0
    ) -> None:
        pass

    def log_graph(
        self, robot: str, graph: GraphArrays, chunk: int = 0, drawn: np.ndarray | None = None
    ) -> None:
        pass

    def clear_map(self, robot: str) -> None:
        pass

    def log_matches(
        self,
        robot_a: str,
        robot_b: str,
        positions_a: np.ndarray,
        positions_b: np.ndarray,
        accepted: bool,
        num_inliers: int | None = None,
        score: float | None = None,
    ) -> None:
        pass

    def log_text(self, message: str, level: LogLevel | str = LogLevel.INFO) -> None:
        pass

    def log_odometry_failure(self, robot: str, message: str, position_shared: np.ndarray | None = None) -> None:
        pass

    def log_timings(self, robot: str, timings_ms: dict[str, float]) -> None:
        pass

    def log_scalar(self, path: str, value: float) -> None:
        pass

    def log_error(self, robot: str, error_m: float) -> None:
        pass

    def close(self) -> None:
        pass


def _xyz(name: str, points: np.ndarray) -> np.ndarray:
    """``points`` as (N, 3) float32, or a DataError naming the argument."""
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise DataError(f"viz: {name} must be an (N, 3) array of points, got shape {arr.shape}")
    return arr.astype(np.float32, copy=False)


def _pose(name: str, T: np.ndarray) -> np.ndarray:
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise DataError(f"viz: {name} must be a (4, 4) rigid transform, got shape {arr.shape}")
    return arr


class RerunLogger:
    """A ``Viz`` that writes to an explicit ``rr.RecordingStream`` (whose sink the caller attached).

    Args:
        rec: the recording stream (``make_viz`` creates it and attaches the sink).
        robots: robot names in display order; robot i gets ``ROBOT_COLORS_RGB[i % 8]``.
        max_cloud_points: clouds are subsampled with a fixed stride to at most this many points.
        jpeg_quality: RGB images are JPEG-compressed at this quality (0..100) to keep recordings small.
        image_plane_distance_m: depth of the camera frustum drawn in the 3D view, metres.
        remote_url: the viewer the sink streams to (``--rerun connect``), None for a file or a spawned viewer;
            ``close`` never waits long for it.
    """

    enabled = True

    def __init__(
        self,
        rec: rr.RecordingStream,
        robots: list[str],
        *,
        max_cloud_points: int = 20_000,
        jpeg_quality: int = 80,
        image_plane_distance_m: float = 2.0,
        remote_url: str | None = None,
    ) -> None:
        self.rec = rec
        self.remote_url = remote_url
        self.robots = list(robots)
        self.max_cloud_points = int(max_cloud_points)
        self.jpeg_quality = int(jpeg_quality)
        self.image_plane_distance_m = float(image_plane_distance_m)
        self._step = 0
        self._styled_series: set[str] = set()
        self._stage_colors: dict[str, np.ndarray] = {}

    def robot_color(self, robot: str) -> np.ndarray:
        """(3,) uint8 RGB display colour of ``robot`` (robots not given at construction are appended)."""
        if robot not in self.robots:
            self.robots.append(robot)
        return ROBOT_COLORS_RGB[self.robots.index(robot) % len(ROBOT_COLORS_RGB)]

    # --- static data ------------------------------------------------------------------------------

    def setup(self, robots: dict[str, Intrinsics]) -> None:
        """Static scene: RDF world axes, Cityscapes AnnotationContext, a pinhole per robot, the blueprint.

        ``robots`` maps robot name -> intrinsics of the images it will log (in display order).
        """
        for robot in robots:
            self.robot_color(robot)
        self.rec.log(WORLD, rr.ViewCoordinates.RDF, static=True)
        infos = [
            rr.AnnotationInfo(id=i, label=name, color=CITYSCAPES_COLORS_RGB[i])
            for i, name in enumerate(CITYSCAPES_CLASSES)
        ]
        infos.append(rr.AnnotationInfo(id=IGNORE_ID, label="ignore", color=(0, 0, 0, 0)))
        # Every entity under /world inherits it: clouds and graph nodes (3D) and the seg images (2D views).
        self.rec.log(WORLD, rr.AnnotationContext(infos), static=True)
        for robot, intr in robots.items():
            self.rec.log(
                camera_path(robot),
                rr.Pinhole(
                    image_from_camera=intr.K,
                    resolution=[intr.width, intr.height],
                    camera_xyz=rr.ViewCoordinates.RDF,
                    image_plane_distance=self.image_plane_distance_m,
                    color=self.robot_color(robot),
                ),
                static=True,
            )
        self.rec.send_blueprint(default_blueprint(self.robots))

    # --- time -------------------------------------------------------------------------------------

    def set_time(self, robot: str, frame_index: int, timestamp_s: float) -> None:
        """Set ``frame`` = frame_index, ``sensor_time`` = timestamp_s (duration, s) and advance ``step``."""
        self.rec.set_time("step", sequence=self._step)
        self._step += 1
        self.rec.set_time("frame", sequence=int(frame_index))
        self.rec.set_time("sensor_time", duration=float(timestamp_s))

    # --- per frame --------------------------------------------------------------------------------

    def log_frame(
        self,
        robot: str,
        T_shared_cam: np.ndarray,
        image_rgb: np.ndarray | None,
        depth_m: np.ndarray | None,
        label_ids: np.ndarray | None,
        points_shared: np.ndarray | None = None,
        point_labels: np.ndarray | None = None,
    ) -> None:
        """One camera frame of ``robot``.

        Args:
            T_shared_cam: (4, 4) camera pose in the shared world frame.
            image_rgb: (H, W, 3) uint8 RGB or (H, W) uint8 gray, JPEG-compressed; None to skip.
            depth_m: (H, W) float32 metres, 0 or non-finite = invalid; None to skip. Stored as uint16
                millimetres (half the bytes of float32); depths beyond 65.5 m show as invalid.
            label_ids: (H, W) uint8 Cityscapes train ids (255 = ignore, drawn transparent); None to skip.
            points_shared: (N, 3) points in the shared frame, subsampled to ``max_cloud_points``.
            point_labels: (N,) train ids of ``points_shared`` (colours via the AnnotationContext).
        """
        T = _pose("T_shared_cam", T_shared_cam)
        cam = camera_path(robot)
        self.rec.log(cam, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        if image_rgb is not None:
            rgb = rr.Image(np.asarray(image_rgb)).compress(jpeg_quality=self.jpeg_quality)
            self.rec.log(f"{cam}/rgb", rgb)
        if depth_m is not None:
            depth_mm = depth_to_mm_u16(depth_m)
            self.rec.log(f"{cam}/depth", rr.DepthImage(depth_mm, meter=1000.0, colormap="turbo"))
        if label_ids is not None:
            self.rec.log(f"{cam}/seg", rr.SegmentationImage(np.asarray(label_ids, dtype=np.uint8)))
        if points_shared is not None:
            self._log_cloud(robot, _xyz("points_shared", points_shared), point_labels)

    def _log_cloud(self, robot: str, points: np.ndarray, labels: np.ndarray | None) -> None:
        stride = thinning_stride(points.shape[0], self.max_cloud_points)
        class_ids = None
        if labels is not None:
            labels = np.asarray(labels)
            if labels.shape != (points.shape[0],):
                raise DataError(f"viz: point_labels must have shape ({points.shape[0]},), got {labels.shape}")
            class_ids = labels[::stride].astype(np.uint16, copy=False)
        self.rec.log(
            f"{robot_path(robot)}/cloud",
            rr.Points3D(points[::stride], class_ids=class_ids, radii=rr.components.Radius.ui_points(1.5)),
        )

    def log_trajectories(
        self, robot: str, odometry_xyz: np.ndarray, fused_xyz: np.ndarray | None, chunk: int = 0
    ) -> None:
        """One stretch (``chunk``) of the robot's trajectory, both in the shared frame; the stretches
        together draw the whole trajectory, so a caller re-sends only the stretches that changed.

        ``odometry_xyz`` (N, 3) odometry-only camera positions: thin grey line. ``fused_xyz`` (M, 3)
        back-end (corrected) positions: thick line in the robot's colour; None to skip. Each call
        stores the stretch's polyline (12 bytes per point) at ``.../trajectory/{odometry,fused}/<chunk>``.
        """
        base = f"{robot_path(robot)}/trajectory"
        odom = _xyz("odometry_xyz", odometry_xyz)
        self.rec.log(
            f"{base}/odometry/{int(chunk)}",
            rr.LineStrips3D([odom], colors=ODOMETRY_COLOR_RGB, radii=rr.components.Radius.ui_points(1.0)),
        )
        if fused_xyz is not None:
            fused = _xyz("fused_xyz", fused_xyz)
            self.rec.log(
                f"{base}/fused/{int(chunk)}",
                rr.LineStrips3D(
                    [fused], colors=self.robot_color(robot), radii=rr.components.Radius.ui_points(3.0)
                ),
            )

    def clear_map(self, robot: str) -> None:
        """Remove the robot's trajectory and graph stretches (e.g. when a new trajectory segment starts)."""
        self.rec.log(f"{robot_path(robot)}/trajectory", rr.Clear(recursive=True))
        self.rec.log(f"{robot_path(robot)}/graph", rr.Clear(recursive=True))

    def log_graph(
        self, robot: str, graph: GraphArrays, chunk: int = 0, drawn: np.ndarray | None = None
    ) -> None:
        """One part (``chunk``) of the robot's semantic graph, positions in the shared frame
        (``graph.transformed(T_shared_world)``), at ``.../graph/{nodes,edges}/<chunk>``; the parts together
        draw the graph, so a caller re-sends only the parts that changed.

        Nodes: spheres coloured by class, radius ``node_radius_m(size)`` metres, node ids attached for
        hovering; only the rows ``drawn`` ((N,) bool; all when None), the others are there for edges to
        another part. Edges: thin lines in the robot's colour, one (2, 3) strip per edge of ``graph``.
        """
        base = f"{robot_path(robot)}/graph"
        positions = _xyz("graph.positions_xyz", graph.positions_xyz)
        rows = np.arange(len(graph)) if drawn is None else np.flatnonzero(np.asarray(drawn, dtype=bool))
        self.rec.log(
            f"{base}/nodes/{int(chunk)}",
            rr.Points3D(
                positions[rows],
                class_ids=np.asarray(graph.label_ids)[rows].astype(np.uint16),
                radii=node_radius_m(graph.sizes[rows]).astype(np.float32),
                show_labels=False,
            ),
            rr.AnyValues(node_id=np.asarray(graph.node_ids, dtype=np.int64)[rows]),
        )
        edges = np.asarray(graph.edges, dtype=np.int64).reshape(-1, 2)
        color = np.append(self.robot_color(robot), 140).astype(np.uint8)
        self.rec.log(
            f"{base}/edges/{int(chunk)}",
            rr.LineStrips3D(positions[edges], colors=color, radii=rr.components.Radius.ui_points(0.75)),
        )

    def log_matches(
        self,
        robot_a: str,
        robot_b: str,
        positions_a: np.ndarray,
        positions_b: np.ndarray,
        accepted: bool,
        num_inliers: int | None = None,
        score: float | None = None,
    ) -> None:
        """The latest match attempt between two robots: lines between matched node positions (shared frame).

        ``positions_a``/``positions_b`` are (K, 3) paired positions; ``num_inliers``/``score`` only
        annotate. A pair is one entity whichever robot's query matched (``matches_path`` of the two in display
        order): one label per pair, where both directions' labels stood on top of each other. Accepted attempts
        are drawn green at ``.../accepted`` and stay until the next accepted one; rejected attempts are drawn red
        at ``.../rejected`` and are cleared by the next accepted attempt of the pair. The matched nodes are also
        drawn as dots (``.../nodes``) so that matches stay visible when both ends coincide (after the robots are
        aligned).
        """
        pa, pb = _xyz("positions_a", positions_a), _xyz("positions_b", positions_b)
        if pa.shape != pb.shape:
            raise DataError(f"viz: positions_a {pa.shape} and positions_b {pb.shape} must pair up")
        for robot in (robot_a, robot_b):  # robots not given at construction join the display order
            self.robot_color(robot)
        if self.robots.index(robot_b) < self.robots.index(robot_a):
            robot_a, robot_b, pa, pb = robot_b, robot_a, pb, pa
        base = matches_path(robot_a, robot_b)
        parts = [f"{robot_a} ↔ {robot_b}", "accepted" if accepted else "rejected"]
        if num_inliers is not None:
            parts.append(f"{num_inliers} inliers")
        if score is not None:
            parts.append(f"score {score:.2f}")
        label = ", ".join(parts)
        kind = "accepted" if accepted else "rejected"
        if accepted:
            self.rec.log(f"{base}/rejected", rr.Clear(recursive=True))
        color = MATCH_ACCEPTED_RGB if accepted else MATCH_REJECTED_RGB
        self.rec.log(
            f"{base}/{kind}/nodes",
            rr.Points3D(np.concatenate([pa, pb]), colors=color, radii=rr.components.Radius.ui_points(4.0)),
        )
        self.rec.log(
            f"{base}/{kind}",
            rr.LineStrips3D(
                np.stack([pa, pb], axis=1),
                colors=color,
                radii=rr.components.Radius.ui_points(1.5),
                labels=label if pa.shape[0] else None,
            ),
            rr.AnyValues(  # an unknown count or score is left out (not -1 or NaN)
                accepted=bool(accepted),
                num_inliers=None if num_inliers is None else int(num_inliers),
                score=None if score is None else float(score),
            ),
        )

    # --- text and series --------------------------------------------------------------------------

    def log_text(self, message: str, level: LogLevel | str = LogLevel.INFO) -> None:
        """One line in the viewer's log view (``/log``)."""
        self.rec.log(LOG, rr.TextLog(message, level=LogLevel(level).value))

    def log_odometry_failure(self, robot: str, message: str, position_shared: np.ndarray | None = None) -> None:
        """A detected odometry divergence: a WARN line in ``/log`` and, when the last healthy position is
        known in the shared frame (``position_shared`` (3,), metres), a red marker ``<robot>/odometry_failure``."""
        self.log_text(message, LogLevel.WARN)
        if position_shared is not None:
            xyz = _xyz("position_shared", np.asarray(position_shared, dtype=np.float64).reshape(1, 3))
            self.rec.log(
                f"{robot_path(robot)}/odometry_failure",
                rr.Points3D(
                    xyz, colors=(230, 40, 40), radii=rr.components.Radius.ui_points(10.0), labels=["odometry failure"]
                ),
            )

    def log_timings(self, robot: str, timings_ms: dict[str, float]) -> None:
        """Per-stage durations (ms) of the current frame as series ``/timings/<robot>/<stage>``."""
        for stage, ms in timings_ms.items():
            path = timings_path(robot, stage)
            if path not in self._styled_series:
                stage_rgb = self._stage_colors.setdefault(
                    stage, STAGE_COLORS_RGB[len(self._stage_colors) % len(STAGE_COLORS_RGB)]
                )
                self.robot_color(robot)
                color = series_color(stage_rgb, self.robots.index(robot))
                self.rec.log(path, rr.SeriesLines(names=f"{robot}/{stage}", colors=color), static=True)
                self._styled_series.add(path)
            self.rec.log(path, rr.Scalars(float(ms)))

    def log_scalar(self, path: str, value: float) -> None:
        """A scalar series; a relative ``path`` goes under ``/metrics`` (``"ate_m"``: ``/metrics/ate_m``)."""
        full = path if path.startswith("/") else f"{METRICS}/{path}"
        self.rec.log(full, rr.Scalars(float(value)))

    def log_error(self, robot: str, error_m: float) -> None:
        """The distance (metres) of ``robot``'s drawn camera from its ground truth in the shared frame, as the
        series ``/metrics/error_m/<robot>`` in the robot's colour (``run_view.log_frame``: placed robots whose
        sequence has ground truth)."""
        path = error_path(robot)
        if path not in self._styled_series:
            self.rec.log(path, rr.SeriesLines(names=robot, colors=self.robot_color(robot), widths=2.0), static=True)
            self._styled_series.add(path)
        self.rec.log(path, rr.Scalars(float(error_m)))

    def close(self) -> None:
        """Flush everything to the sink and disconnect (the stream accepts no more data).

        A viewer (``remote_url``) that went away, refuses the stream or stops reading it costs the rest of
        the recording (a warning says so), never the run: closing waits at most ``FLUSH_TIMEOUT_S`` for it.
        """
        if self.remote_url is None:
            self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
            self.rec.disconnect()
            return
        failed: list[RuntimeError] = []

        def finish() -> None:
            try:
                self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
                self.rec.disconnect()
            except RuntimeError as exc:  # the SDK's error for a severed gRPC stream
                failed.append(exc)

        closer = threading.Thread(target=finish, name="rerun-close", daemon=True)
        closer.start()
        closer.join(FLUSH_TIMEOUT_S + 2.0)
        if closer.is_alive() or failed:
            # the sink no longer drains: dropping the stream (Rerun's __del__, its exit hook) would wait for ever
            rr.unregister_shutdown()
            _ABANDONED_RECORDINGS.append(self.rec.to_native())
            self.rec.__class__ = _AbandonedStream
        if closer.is_alive():
            log.warning("the Rerun viewer at %s did not take the end of the recording within %.0f s; what it "
                        "shows is incomplete (the results are written)", self.remote_url, FLUSH_TIMEOUT_S)
        elif failed:
            log.warning("the Rerun viewer at %s did not take the recording (%s); what it shows is incomplete "
                        "(the results are written)", self.remote_url, failed[0])


_ABANDONED_RECORDINGS: list[object] = []
"""Native handles of the streams whose viewer stopped taking data, held for the life of the process: a handle
nothing refers to is *orphaned*, and every later stream's drop (any recording of the process, a file's too)
sweeps the orphans and flushes them first, which would wait for ever on that viewer."""


class _AbandonedStream(rr.RecordingStream):
    """A recording stream whose viewer stopped taking data: dropping it must not wait for that viewer."""

    def __del__(self) -> None:
        pass


def _has_display() -> bool:
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def make_viz(
    mode: RerunMode,
    *,
    robots: list[str],
    app_id: str = "shgm_slam",
    recording_id: str | None = None,
    save_path: Path | str | None = None,
    connect_url: str | None = None,
    max_cloud_points: int = 20_000,
) -> Viz:
    """The ``Viz`` for ``mode``: a ``RerunLogger`` on a fresh stream with its sink, or a ``NullLogger``.

    Processes that log the same run (one per robot, say) must share ``app_id`` and ``recording_id``.
    ``save_path`` is required for SAVE (parent folders are created); ``connect_url`` defaults to a
    viewer on this machine (``rerun+http://127.0.0.1:9876/proxy``) for CONNECT. When no viewer answers
    there within ``CONNECT_TIMEOUT_S`` the run says so (a warning) and saves the recording to ``save_path``
    instead (or logs nothing when there is none): a missing viewer never blocks a run. ``max_cloud_points``
    bounds each logged cloud (a 20k-point cloud is ~0.27 MB of the ~0.4 MB a frame costs in an .rrd).
    """
    mode = RerunMode(mode)
    if mode is RerunMode.OFF:
        return NullLogger()
    rec = rr.RecordingStream(app_id, recording_id=recording_id)
    blueprint = default_blueprint(list(robots))
    if mode is RerunMode.CONNECT:
        url = connect_url or DEFAULT_CONNECT_URL
        if not viewer_reachable(*viewer_address(url), tls=url.startswith("rerun+https")):
            where = f"saving the recording to {save_path} instead" if save_path is not None else "logging nothing"
            log.warning("no Rerun viewer answers at %s within %.0f s: %s", url, CONNECT_TIMEOUT_S, where)
            if save_path is None:
                return NullLogger()
            mode = RerunMode.SAVE
        else:
            rec.connect_grpc(url, default_blueprint=blueprint)
            return RerunLogger(rec, robots, max_cloud_points=max_cloud_points, remote_url=url)
    if mode is RerunMode.SAVE:
        if save_path is None:
            raise ConfigError("--rerun save needs an output file: pass --rerun-file run.rrd")
        path = Path(save_path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            if not os.access(path.parent, os.W_OK):
                raise PermissionError(f"{path.parent} is not writable")
            rec.save(path, default_blueprint=blueprint)
        except (OSError, RuntimeError) as exc:
            raise ConfigError(
                f"cannot write the recording {path} ({exc}): choose a writable --out folder or --rerun off"
            ) from None
    elif mode is RerunMode.SPAWN:
        if not _has_display():
            raise ConfigError(
                "--rerun spawn needs a display (DISPLAY/WAYLAND_DISPLAY are unset): use --rerun save "
                "and open the .rrd with `rerun run.rrd` on a machine with a screen"
            )
        try:
            rec.spawn(default_blueprint=blueprint)
        except (OSError, RuntimeError) as exc:
            raise ConfigError(f"could not spawn the Rerun viewer ({exc}): use --rerun save instead") from exc
    return RerunLogger(rec, robots, max_cloud_points=max_cloud_points)
