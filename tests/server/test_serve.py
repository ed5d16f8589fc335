"""The live view of a map server: what it sends to the viewer."""

from __future__ import annotations

from shgm_slam.backend.confirmation import describe
from shgm_slam.server.serve import ServerView


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
