"""``MapServer.shared_positions``: where the viewer draws nodes, per chunk and keyframe."""

from __future__ import annotations

import numpy as np
import pytest

from shgm_slam.server.node import ServerNode


class _IndexedOnly(list):
    """A robot's received keyframe poses that may be read one by one, not all at once."""

    def __iter__(self):
        raise AssertionError("every keyframe's pose was read")


def test_shared_positions_read_only_the_keyframes_their_points_are_anchored_to(
    uninterrupted: ServerNode, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The viewer moves each chunk of a graph with ``shared_positions`` at every keyframe: it stacked all K received
    keyframe poses each call (``keyframe_poses``), a cost per keyframe that grew with the distance driven."""
    server = uninterrupted.map
    agent = next(a for a in server.agents if server.is_placed(a) and server.received(a) > 2 and len(server.graph(a)))
    expected = server.shared_graph(agent).positions_xyz
    graph, anchors = server.graph(agent), server.graph_anchors(agent)
    monkeypatch.setitem(server._T_odom_kf, agent, _IndexedOnly(server._T_odom_kf[agent]))
    rows = np.flatnonzero(anchors == anchors.max())  # one chunk's nodes: those of the latest keyframe
    got = server.shared_positions(agent, anchors[rows], graph.positions_xyz[rows])
    np.testing.assert_allclose(got, expected[rows], atol=1e-12)
