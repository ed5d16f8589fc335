"""What the server knows of one robot, read for its results: its fused per-frame and per-keyframe trajectories in
the shared frame, why its place is provisional, and its line in ``server.json``. Pure reads of the ``MapServer``
and the robot's ``RobotSession``; ``ServerNode`` writes them."""

from __future__ import annotations

import numpy as np

from shgm_slam.agents import agent_robot
from shgm_slam.fusion import fuse_segments
from shgm_slam.server.map_server import MapServer
from shgm_slam.server.sessions import RobotSession


def _agents_of(server: MapServer, robot: str) -> list[str]:
    """The agents (odometry segments) of ``robot`` the server holds, in its order."""
    return [a for a in server.agents if agent_robot(a)[0] == robot]


def fused_trajectory(server: MapServer, session: RobotSession) -> tuple[np.ndarray, np.ndarray | None]:
    """``(timestamps_s (N,), T_shared_cam (N, 4, 4) or None)``: every frame of the robot's trajectory (its
    ``DoneMessage``, which must have arrived) carried into the shared frame by its segments' fused keyframes
    (``fusion.fuse_segments``; None where no segment is placed)."""
    traj = session.done.trajectory
    seg = {agent_robot(a)[1]: a for a in _agents_of(server, session.name)}
    fused = fuse_segments(
        traj.T_odom_cam, traj.frame_segment,
        {k: np.asarray(session.kf_frames.get(a, []), dtype=np.int64) for k, a in seg.items()},
        {k: server.keyframe_poses(a) for k, a in seg.items()},
        {k: server.T_shared_kf(a) for k, a in seg.items()},
    )  # fmt: skip
    return traj.timestamps_s, fused


def keyframe_trajectory(server: MapServer, session: RobotSession) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(timestamps_s (K,), T_odom_kf (K, 4, 4), T_shared_kf (K, 4, 4) or None)`` of all the robot's keyframes
    in time order (odometry in each segment's own frame; fused NaN for unplaced segments, None when none is
    placed): what is known of a robot before its trajectory arrives."""
    times, odo, fused = [], [], []
    for a in _agents_of(server, session.name):
        if not server.received(a):
            continue
        T_odom = server.keyframe_poses(a)
        T_shared = server.T_shared_kf(a)
        times += session.kf_timestamps.get(a, [])[: len(T_odom)]
        odo.append(T_odom)
        fused.append(T_shared if T_shared is not None else np.full_like(T_odom, np.nan))
    if not odo:
        return np.zeros(0), np.zeros((0, 4, 4)), None
    order = np.argsort(times, kind="stable")
    T_fused = np.concatenate(fused)[order]
    placed = np.isfinite(T_fused).all(axis=(1, 2)).any()
    return np.asarray(times)[order], np.concatenate(odo)[order], T_fused if placed else None


def provisional_note(server: MapServer, robot: str) -> str | None:
    """Why ``robot``'s place in the shared frame is provisional (one line per such agent), or None when every
    placed agent of it is confirmed (``backend.confirmation``)."""
    notes = [server.placement_note(a) or "" for a in _agents_of(server, robot) if server.placement(a).provisional]
    return "; ".join(notes) or None


def robot_summary(server: MapServer | None, session: RobotSession, dropped: dict[str, str]) -> dict:
    """The robot's entry in ``server.json``: its state, agents, which are placed, provisional or waiting, the
    heading drift its loop closures measured (deg per 100 m), keyframes held, and ``dropped`` segments (agent ->
    why its keyframes are dropped; other robots' agents are left out)."""
    mine = _agents_of(server, session.name) if server is not None else []
    return {
        "state": session.state.value,
        "agents": mine,
        "placed": [a for a in mine if server.is_placed(a)],
        "provisional": [a for a in mine if server.placement(a).provisional],
        "waiting": [note for a in mine if (note := server.waiting_note(a)) is not None],
        # odometry heading drift its loop closures measured beyond the prior, deg per 100 m, per agent
        "measured_drift_deg_per_100m": {
            a: round(float(np.degrees(d)) * 100.0, 2) for a in mine if (d := server.measured_drift(a)) is not None
        },
        # the longest stretch of each placed agent's path resting on its own odometry, metres
        # (``MapServer.path_from_closures_m``)
        "path_from_closures_m": {
            a: round(m, 1) for a in mine if (m := server.path_from_closures_m(a)) is not None
        },
        "keyframes": sum(server.received(a) for a in mine) if server else 0,
        "done": session.done is not None,
        "went_stale": session.went_stale,
        "dropped_segments": {a: why for a, why in dropped.items() if agent_robot(a)[0] == session.name},
    }
