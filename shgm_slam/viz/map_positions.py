"""Where the viewer draws a robot's map: in the shared frame as the results files hold it while the robot is placed
(each node with its keyframe's correction, ``MapServer.shared_positions``), else in the robot's own odometry frame.
Shared by ``run``'s view (``run_view``) and the map server's (``server.serve``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from shgm_slam.geometry import se3

if TYPE_CHECKING:
    from shgm_slam.server.map_server import MapServer


def anchored_positions(server: MapServer, agent: str, anchors: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(N, 3) positions of ``agent``'s nodes, given in its odometry frame (``positions`` (N, 3), metres) with the
    keyframe each is anchored to (``anchors`` (N,)), where the viewer draws them: in the shared frame, each moved
    with its keyframe's correction (the fused map of ``shared_graph_<robot>.json``: closures that bent the
    trajectory bend the map alike), or unchanged, in the agent's own odometry frame, while it is not placed."""
    shared = server.shared_positions(agent, anchors, positions)
    return np.asarray(positions, dtype=np.float64).reshape(-1, 3) if shared is None else shared


def node_positions(server: MapServer, agent: str, node_ids: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Where the viewer draws ``agent``'s nodes ``node_ids`` ((N,)), given at ``positions`` ((N, 3), its odometry
    frame, e.g. when a match found them): each node the server's graph holds where its map draws it now
    (``anchored_positions`` of its current position: a match's line ends on the node, however its centroid moved
    since), any other at ``positions`` moved with the agent's latest keyframe."""
    graph = server.graph(agent)
    positions = np.array(positions, dtype=np.float64).reshape(-1, 3)
    anchors = np.full(len(node_ids), max(server.received(agent) - 1, 0), dtype=np.int64)
    if len(graph):
        order = np.argsort(graph.node_ids)
        at = order[np.minimum(np.searchsorted(graph.node_ids, node_ids, sorter=order), len(order) - 1)]
        found = graph.node_ids[at] == node_ids
        anchors[found] = server.graph_anchors(agent)[at[found]]
        positions[found] = graph.positions_xyz[at[found]]
    return anchored_positions(server, agent, anchors, positions)


def odometry_start(server: MapServer, agent: str, T_odom_kf0: np.ndarray) -> np.ndarray | None:
    """(4, 4) where the viewer draws ``agent``'s odometry frame: its odometry line starts at the fused pose of its
    first keyframe (``T_odom_kf0`` (4, 4), that keyframe's odometry pose; for the reference robot the result is its
    odometry frame, the shared frame: the line is ``<robot>_odometry_tum.txt``) and drifts from the fused line from
    there on; None while it is not placed (or the server has none of its keyframes)."""
    if not server.received(agent):
        return None
    T_shared_kf0 = server.T_shared_kf_at(agent, np.zeros(1, dtype=np.int64))
    return None if T_shared_kf0 is None else T_shared_kf0[0] @ se3.inverse(T_odom_kf0)
