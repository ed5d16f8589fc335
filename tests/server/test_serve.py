"""The live view of a map server: what it sends to the viewer."""

from __future__ import annotations

import pytest

from shgm_slam.backend.confirmation import describe
from shgm_slam.errors import DataError
from shgm_slam.evaluation import evaluate_results
from shgm_slam.io.export import INCOMPLETE_FILE
from shgm_slam.server import serve as serve_module
from shgm_slam.server.node import ServerNode
from shgm_slam.server.serve import ServerView
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport


class RecordingViz:
    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple]] = []

    def __getattr__(self, name):
        return lambda *args, **kwargs: self.calls.append((name, args))


def test_view_streams_graphs_trajectories_and_states(uninterrupted) -> None:
    viz = RecordingViz()
    view = ServerView(viz, every_s=0.0)
    view.update(uninterrupted, uninterrupted.map.matches)
    kinds = [c[0] for c in viz.calls]
    assert kinds.count("log_graph") == 2 and kinds.count("log_trajectories") == 2
    assert any(k == "log_matches" for k in kinds)
    traj = [c[1] for c in viz.calls if c[0] == "log_trajectories"]
    assert all(fused is not None and len(fused) for _, _, fused in traj)  # both robots placed
    texts = [c[1][0] for c in viz.calls if c[0] == "log_text"]
    placement = uninterrupted.map.placement(uninterrupted.map.agents[1])
    assert sum(describe(uninterrupted.map.agents[1], placement) == t for t in texts) == 1  # placed: said once
    view.update(uninterrupted, uninterrupted.map.matches)
    view.update(uninterrupted, [])
    assert [c[0] for c in viz.calls].count("log_text") == len(texts)  # states are logged once, not every update


def test_the_view_draws_the_fused_map_and_every_match_where_the_maps_are(uninterrupted) -> None:
    """``shgm-slam server``'s recording drew each graph moved by the latest correction as one rigid body (not the
    fused map of ``shared_graph_<agent>.json``), and drew a match only when both robots were placed."""
    import numpy as np

    viz = RecordingViz()
    server = uninterrupted.map
    ServerView(viz, every_s=0.0).update(uninterrupted, server.matches)
    for robot, graph in [c[1] for c in viz.calls if c[0] == "log_graph"]:
        expected = server.shared_graph(robot)
        assert expected is not None and np.abs(graph.positions_xyz - expected.positions_xyz).max() < 1e-9, robot
    drawn = [c[1] for c in viz.calls if c[0] == "log_matches"]
    assert len(drawn) == sum(m.success for m in server.matches)
    maps = {r: server.shared_graph(r).positions_xyz for r in server.agents}
    for a, b, pa, pb, *_ in drawn:  # each end of a line on a node of that robot's map
        for agent, ends in ((a, pa), (b, pb)):
            assert np.linalg.norm(ends[:, None] - maps[agent][None], axis=2).min(axis=1).max() < 1e-6
    reference = server.agents[0]
    odometry = next(c[1][1] for c in viz.calls if c[0] == "log_trajectories" and c[1][0] == reference)
    np.testing.assert_allclose(odometry, server.keyframe_poses(reference)[:, :3, 3], atol=1e-5)  # its own frame


def test_a_server_that_stops_with_an_error_marks_its_folder_and_a_resumed_one_clears_it(cfg, tmp_path, monkeypatch):
    """An unexpected error in the server loop leaves ``incomplete.txt`` (``eval`` refuses the folder); a server
    restarted on the folder (it resumes from the journal) removes the mark once it finishes."""
    monkeypatch.setattr(serve_module, "make_transport", lambda role, listen: InProcessTransport(InProcessBus()))

    def broken_poll(self, timeout_s: float = 0.0):
        raise RuntimeError("disk controller on fire")

    with monkeypatch.context() as m:
        m.setattr(ServerNode, "poll", broken_poll)
        with pytest.raises(RuntimeError):
            serve_module.serve(cfg, tmp_path)
    marker = tmp_path / INCOMPLETE_FILE
    assert "disk controller on fire" in marker.read_text() and "resumes from its journal" in marker.read_text()
    with pytest.raises(DataError, match="ended with an error"):
        evaluate_results(tmp_path)
    resumed = ServerNode(cfg, InProcessTransport(InProcessBus()), tmp_path, reference="car1")
    resumed.finish()
    assert not marker.exists()
