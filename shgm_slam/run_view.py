"""What ``run`` sends the viewer: each frame and match as it comes, and at each keyframe only the stretches of the
map that changed.

``log_frame`` sends a processed frame (pose, image; depth and cloud at keyframes only; for a robot placed in the
shared frame whose sequence has ground truth, the drawn camera's distance from it, ``RunView.truth``) and, through
``log_matches``, the matches its server poll tried; ``last_healthy_position`` is where the viewer marks an odometry
failure.

Trajectories are drawn in stretches of ``TRAJECTORY_CHUNK_FRAMES`` frames and graphs in parts of the
nodes anchored to ``GRAPH_CHUNK_KEYFRAMES`` consecutive keyframes (``Viz.log_trajectories`` /
``log_graph`` with a chunk index). At a keyframe only the trajectory stretches since the previous
keyframe and the graph parts its nodes touched (with their neighbours) are re-sent, so the cost per
keyframe does not grow with the distance driven. Fused positions and graph nodes ride on their keyframe's
correction (graph nodes as in ``shared_graph_<robot>.json``); the grey odometry line starts at the fused pose
of the segment's first keyframe (for the reference robot: its odometry file) and shows the drift from there.
When the pose graph changes in a way that can move old keyframes (a closure enters or leaves, a robot is
placed or loses its place: ``MapServer.corrections``), or the robot starts a new trajectory segment,
everything of that robot is sent once more (cleared first when it lost its place or segment). Between such
changes the parts already sent are not moved with the small updates every new keyframe brings (centimetres to
decimetres).
At the end of the run (``finish``), after the final matching and convergence, every robot's whole
trajectory and graph are sent once more: the viewer ends on the results written to disk.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from shgm_slam.arrays import thinning_stride
from shgm_slam.geometry import se3
from shgm_slam.robot.frontend import FrameResult, RobotFrontend
from shgm_slam.server.map_server import MapServer
from shgm_slam.shared_frame import SharedTruth
from shgm_slam.types import GraphArrays
from shgm_slam.viz.map_positions import anchored_positions, node_positions, odometry_start
from shgm_slam.viz.rerun_logger import Viz

TRAJECTORY_CHUNK_FRAMES = 200
"""Frames per trajectory stretch (a few hundred: small enough to re-send at every keyframe)."""
GRAPH_CHUNK_KEYFRAMES = 50
"""Keyframes whose nodes form one graph part."""


@dataclass
class _RobotState:
    agent: str = ""
    corrections: int = -1
    next_frame: int = 0  # frames before this one are in stretches already sent
    placed: bool = False


def fused_positions(front: RobotFrontend, server: MapServer, frames: np.ndarray) -> np.ndarray:
    """(F, 3) fused camera positions (shared frame) of ``front``'s frames ``frames``: each frame rides on
    its last keyframe's correction (the server's latest keyframe of the segment for keyframes still on their
    way to it, or waiting their turn there); NaN rows for frames of unplaced segments or before a first
    keyframe."""
    out = np.full((frames.size, 3), np.nan)
    seg_of, kf_of = front.frame_segment[frames], front.frame_kf[frames]
    for seg in front.segments:
        held = min(seg.num_keyframes, server.received(seg.agent))
        rows = np.flatnonzero((seg_of == seg.index) & (kf_of >= 0) & (kf_of < seg.num_keyframes))
        if not rows.size or not held:
            continue
        kfs, inverse = np.unique(np.minimum(kf_of[rows], held - 1), return_inverse=True)
        T_shared_kf = server.T_shared_kf_at(seg.agent, kfs)
        if T_shared_kf is None:
            continue
        T_odom_kf = np.stack([seg.kf_poses[k] for k in kfs.tolist()])
        correction = (T_shared_kf @ se3.inverse(T_odom_kf))[inverse]
        out[rows] = np.einsum("nij,nj->ni", correction[:, :3, :3], front.T_odom_cam[frames[rows], :3, 3])
        out[rows] += correction[:, :3, 3]
    return out


class RunView:
    """Sends each robot's trajectory and graph to a viewer in changed chunks (module docstring).

    Args:
        viz: the viewer.
        truth: the run's ground truth in the shared frame (``log_frame`` draws each placed robot's distance from
            it), or None.
    """

    def __init__(self, viz: Viz, truth: SharedTruth | None = None) -> None:
        self.viz = viz
        self.truth = truth
        self._robots: dict[str, _RobotState] = {}
        self.points_sent = 0  # trajectory positions and graph nodes sent so far (for tests and benchmarks)

    def keyframe(self, server: MapServer, front: RobotFrontend, res: FrameResult) -> None:
        """Send what changed of ``res.robot``'s trajectory and graph at its keyframe ``res``."""
        r, agent = res.robot, res.agent or res.robot
        st = self._robots.setdefault(r, _RobotState())
        placed = server.is_placed(agent)
        if st.agent != agent or (st.placed and not placed):  # a new segment, or the fused line is wrong now
            self.viz.clear_map(r)
        full = st.agent != agent or st.corrections != server.corrections or st.placed != placed
        st.agent, st.corrections, st.placed = agent, server.corrections, placed
        f = res.frame.index
        self._trajectory(server, front, 0 if full else st.next_frame, f)
        st.next_frame = f
        update = None if full or res.message is None else res.message.graph_update
        self._graph(server, r, agent, update)

    def finish(self, server: MapServer, fronts: Iterable[RobotFrontend]) -> None:
        """Send each robot's whole trajectory (up to its last frame with a pose) and graph once more, at its
        last frame's time: after the final matching and convergence, the state the results files hold (the error
        series stays the live estimate's: a last value at the end of the timeline drew a straight line across the
        other robots' frames)."""
        for front in fronts:
            st = self._robots.get(front.name)
            if st is None:
                continue
            if st.agent != front.segment.agent or (st.placed and not server.is_placed(front.segment.agent)):
                self.viz.clear_map(front.name)  # lost its place at the end: no fused line of a former estimate
            posed = np.flatnonzero(front.frame_segment == front.segment.index)
            if not posed.size:
                continue
            last = int(posed[-1])
            self.viz.set_time(front.name, last, float(front.sequence.timestamps_s[last]))
            self._trajectory(server, front, 0, last)
            self._graph(server, front.name, front.segment.agent, None)

    def _trajectory(self, server: MapServer, front: RobotFrontend, since: int, upto: int) -> None:
        seg = front.segment
        T_shared_start = odometry_start(server, seg.agent, seg.kf_poses[0]) if seg.num_keyframes else None
        for c in range(since // TRAJECTORY_CHUNK_FRAMES, upto // TRAJECTORY_CHUNK_FRAMES + 1):
            lo = c * TRAJECTORY_CHUNK_FRAMES
            frames = np.arange(lo, min(lo + TRAJECTORY_CHUNK_FRAMES + 1, upto + 1))  # +1: stretches join up
            mine = frames[front.frame_segment[frames] == front.segment.index]
            odo_xyz = front.T_odom_cam[mine, :3, 3]
            if T_shared_start is not None:
                odo_xyz = se3.transform_points(T_shared_start, odo_xyz)
            fused = fused_positions(front, server, frames)
            fused = fused[np.isfinite(fused).all(axis=1)]
            self.viz.log_trajectories(front.name, odo_xyz, fused if len(fused) else None, chunk=c)
            self.points_sent += len(odo_xyz) + len(fused)

    def _graph(self, server: MapServer, robot: str, agent: str, update) -> None:
        graph = server.graph(agent)
        if not len(graph):
            return
        anchors = server.graph_anchors(agent)
        chunk_of = anchors // GRAPH_CHUNK_KEYFRAMES
        if update is None:
            dirty = np.unique(chunk_of)
        else:
            touched = np.isin(graph.node_ids, update.observed_node_ids)
            e = graph.edges
            near = touched.copy()
            near[e[touched[e[:, 0]], 1]] = True
            near[e[touched[e[:, 1]], 0]] = True
            dirty = np.unique(chunk_of[near])
        edge_chunk = np.maximum(chunk_of[graph.edges[:, 0]], chunk_of[graph.edges[:, 1]])  # drawn by the later part
        for c in dirty.tolist():
            edges = graph.edges[edge_chunk == c]
            rows = np.union1d(np.flatnonzero(chunk_of == c), edges.reshape(-1))
            xyz = anchored_positions(server, agent, anchors[rows], graph.positions_xyz[rows])
            part = GraphArrays(graph.node_ids[rows], graph.label_ids[rows], xyz, graph.sizes[rows],
                               np.searchsorted(rows, edges))  # fmt: skip
            self.viz.log_graph(robot, part, chunk=c, drawn=chunk_of[rows] == c)
            self.points_sent += len(rows)


def log_frame(viz: Viz, view: RunView, server: MapServer, front: RobotFrontend, res: FrameResult, records) -> None:
    """Send robot ``res.robot``'s processed frame ``res`` to the viewer (at a keyframe also what changed of its
    trajectory and graph, ``RunView.keyframe``), then the matches ``records`` its server poll tried."""
    r, agent = res.robot, res.agent or res.robot
    if not viz.enabled:  # nothing shown: skip the poses, clouds, trajectories and graphs only the viewer needs
        log_matches(viz, server, records)
        return
    viz.set_time(r, res.frame.index, res.frame.timestamp_s)
    if not np.isfinite(res.T_odom_cam).all():  # between a divergence and the next measured frame
        log_matches(viz, server, records)
        return
    T_shared_odom = server.T_shared_odom(agent)
    T_view = res.T_odom_cam if T_shared_odom is None else T_shared_odom @ res.T_odom_cam
    # the heavy parts (depth image, point cloud) only at keyframes: keeps recordings ~100 KB per frame
    key = res.message is not None
    pts = labels = None
    if key:  # thinned as the viewer would before it is moved into the shared frame
        step = thinning_stride(len(res.points_cam), viz.max_cloud_points)
        pts = se3.transform_points(T_view, res.points_cam[::step])
        labels = None if res.point_labels is None else res.point_labels[::step]
    viz.log_frame(r, T_view, res.frame.image_rgb, res.depth_m if key else None, res.label_ids, pts, labels)
    truth = None if T_shared_odom is None or view.truth is None else view.truth.position(r, res.frame.index)
    if truth is not None:  # placed: how far the camera drawn in the shared frame is from where it was
        viz.log_error(r, float(np.linalg.norm(T_view[:3, 3] - truth)))
    viz.log_timings(r, res.timings_ms)
    if res.message is not None:
        view.keyframe(server, front, res)  # only the trajectory stretches and graph parts that changed
    log_matches(viz, server, records)


def log_matches(viz: Viz, server: MapServer, records) -> None:
    """Each successful match of ``records`` (``MatchRecord``s): lines between its inlier nodes where the viewer
    draws each robot's graph (``node_positions``: the shared frame when placed, else the robot's own odometry
    frame, so the matches of robots not placed yet show too), and a line in the viewer's log panel (INFO accepted
    or already known, WARN rejected)."""
    for m in records:
        if not m.success:
            continue
        pairs = np.asarray(m.inliers, dtype=np.int64).reshape(-1, 2)  # node ids of robot_a, robot_b
        pa = node_positions(server, m.robot_a, pairs[:, 0], m.inlier_positions_a)
        pb = node_positions(server, m.robot_b, pairs[:, 1], m.inlier_positions_b)
        viz.log_matches(m.robot_a, m.robot_b, pa, pb, m.accepted, len(m.inliers))
        level = "INFO" if m.accepted or m.duplicate else "WARN"
        verdict = "accepted" if m.accepted else "already known" if m.duplicate else "rejected"
        sigma = m.evidence.centroid_sigma_m if m.evidence is not None else float("nan")
        precision = f" (±{sigma:.1f} m predicted at the centre of {m.robot_b}'s nodes)" if np.isfinite(sigma) else ""
        viz.log_text(f"{m.robot_a}<->{m.robot_b} ({m.query}): {len(m.inliers)} inliers{precision}, {verdict}: "
                     f"{m.reason}", level)  # fmt: skip


def last_healthy_position(front: RobotFrontend, server: MapServer) -> np.ndarray | None:
    """(3,) shared-frame position of the last frame of the segment that just failed, if that is placed."""
    seg = front.segments[-1] if front.stopped else front.segments[-2]
    frames = np.flatnonzero(front.frame_segment == seg.index)
    if not len(frames) or server.T_shared_kf(seg.agent) is None:
        return None
    return (server.T_shared_odom(seg.agent) @ front.T_odom_cam[frames[-1]])[:3, 3]
