"""Repeated queries between two robots: a match counts as a piece of evidence of its own only beyond the threshold
plus the log of the matches the pair has tried (``MapServer._marginal``); the marginal ones of a pair together
are one piece."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from shgm_slam.backend.pose_graph import MultiRobotPoseGraph
from shgm_slam.config import ShgmConfig
from shgm_slam.geometry.se3 import make_pose, rot_y
from shgm_slam.matching import MatchResult
from shgm_slam.server.map_server import MARGINAL_OBJECT, MapServer


def _accepted(llr: float, threshold: float) -> MatchResult:
    """An accepted match with this log likelihood ratio and chance threshold, nats."""
    return MatchResult(True, np.eye(4), np.zeros((0, 2), np.int64), 0, llr=llr, llr_threshold=threshold)


def _tried(server: MapServer, pairs: list[tuple[str, str]]) -> None:
    server._matches += [SimpleNamespace(robot_a=a, robot_b=b) for a, b in pairs]


def test_the_bar_rises_with_the_matches_the_pair_tried() -> None:
    server = MapServer(["car1", "car2", "uav"], ShgmConfig())
    clear = _accepted(12.5, 9.0)  # 3.5 nats beyond the threshold
    assert not server._marginal("car1", "car2", clear)  # the first try: the threshold alone
    _tried(server, [("car1", "car2")] * 20 + [("car2", "car1")] * 10)  # either robot's queries count
    assert math.log(31) < 3.5 + 0.01 and not server._marginal("car1", "car2", clear)
    _tried(server, [("car2", "car1")] * 5)
    assert server._marginal("car1", "car2", clear)  # 36 tries: log 36 = 3.58 > 3.5
    _tried(server, [("car1", "uav")] * 100)  # other pairs' tries do not count
    assert not server._marginal("car2", "uav", clear)
    assert not server._marginal("car1", "car2", _accepted(30.0, 9.0))


def test_marginal_matches_of_a_pair_are_one_piece_strong_ones_two() -> None:
    """Two matches on disjoint objects are two pieces of evidence (the robot enters the shared frame); with the
    pair's marginal pseudo-object on both they are one (it waits)."""
    poses = [make_pose(rot_y(0.03 * k), [0.0, 0.0, 2.0 * k]) for k in range(30)]
    marginal = {("a", f"{MARGINAL_OBJECT}:b"), ("b", f"{MARGINAL_OBJECT}:a")}
    for extra, pieces in ((set(), 2), (marginal, 1)):
        pg = MultiRobotPoseGraph(["a", "b"], min_closures_to_anchor=2)
        for r in ("a", "b"):
            for k, T in enumerate(poses):
                pg.add_keyframe(r, k, T)
        for match_id, kf, nodes in ((1, 5, (1, 2, 3)), (2, 20, (7, 8, 9))):
            objects = frozenset({("a", n) for n in nodes} | {("b", n + 100) for n in nodes} | extra)
            pg.add_inter_robot_closure("a", kf, "b", kf, np.eye(4), num_inliers=8, match_id=match_id, support=objects)
        assert pg.evidence_between("a", "b") == pieces
        assert pg.is_anchored("b") == (pieces == 2)


def test_a_decisive_match_clears_the_bar_of_two_pieces() -> None:
    """One match places a robot alone when its log likelihood ratio is twice the bar a piece clears (threshold
    plus log of the pair's tries): as unlikely under chance as two pieces together."""
    server = MapServer(["car1", "car2", "uav"], ShgmConfig())
    assert not server._decisive("car1", "car2", _accepted(17.9, 9.0))  # first try: 2 x 9
    assert server._decisive("car1", "car2", _accepted(18.0, 9.0))
    _tried(server, [("car1", "car2")] * 19)  # 20 tries: the bar is 2 x (9 + log 20) = 23.99
    assert not server._decisive("car1", "car2", _accepted(23.9, 9.0))
    assert server._decisive("car1", "car2", _accepted(24.0, 9.0))
    assert server._decisive("car1", "uav", _accepted(18.0, 9.0))  # another pair's count
    strong = _accepted(99.0, 9.0)
    for change in ({"decisive_match": False}, {"min_closures_to_anchor": 1}):  # off, or one match places anyway
        cfg = ShgmConfig().model_copy(update={"backend": ShgmConfig().backend.model_copy(update=change)})
        assert not MapServer(["car1", "car2"], cfg)._decisive("car1", "car2", strong)
