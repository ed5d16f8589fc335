"""Robot keys: one letter per robot, round trips, clear errors."""

from __future__ import annotations

import gtsam
import pytest

from shgm_slam.backend.keys import MAX_AGENTS, ROBOT_LETTERS, RobotKeys, decode, key, robot_letter, segments_per_robot
from shgm_slam.errors import BackendError


def test_letters_are_deterministic_and_keys_round_trip():
    assert [robot_letter(i) for i in range(3)] == ["a", "b", "c"]
    keys = RobotKeys(["alpha", "beta", "gamma"])
    assert keys.key("beta", 7) == gtsam.symbol("b", 7)
    assert gtsam.Symbol(keys.key("gamma", 12)).string() == "c12"
    for name in keys.names:
        for kf in (0, 1, 999_999):
            assert keys.decode(keys.key(name, kf)) == (name, kf)
    all_keys = {key(i, k) for i in range(len(ROBOT_LETTERS)) for k in range(3)}
    assert len(all_keys) == 3 * len(ROBOT_LETTERS)  # no collisions across robots
    assert decode(key(30, 5)) == (30, 5)


def test_errors_name_the_problem():
    with pytest.raises(BackendError, match="unknown robot 'delta'"):
        RobotKeys(["a", "b"]).index("delta")
    with pytest.raises(BackendError, match="unique"):
        RobotKeys(["a", "a"])
    with pytest.raises(BackendError, match="at most 52 robots"):
        RobotKeys([f"r{i}" for i in range(53)])
    with pytest.raises(BackendError, match="not a robot keyframe key"):
        decode(gtsam.symbol("#", 3))
    with pytest.raises(BackendError, match="belongs to no robot"):
        RobotKeys(["a", "b"]).decode(key(5, 0))


def test_agents_are_added_at_run_time_up_to_52():
    keys = RobotKeys(["car1", "car2"])
    assert keys.add("car1#1") == 2
    assert keys.key("car1#1", 4) == gtsam.symbol("c", 4)
    assert keys.decode(gtsam.symbol("c", 4)) == ("car1#1", 4)
    with pytest.raises(BackendError, match="already"):
        keys.add("car1#1")
    for i in range(2, 51):
        keys.add(f"car1#{i}")
    assert len(keys) == 52
    with pytest.raises(BackendError, match="at most 52 agents"):
        keys.add("car1#51")


def test_each_robots_share_of_segments_fits_the_pose_graph():
    assert MAX_AGENTS == 52
    for robots in (1, 2, 3, 17, 26, 27, 52):
        share = segments_per_robot(robots)
        assert share >= 1 and robots * share <= MAX_AGENTS
    assert segments_per_robot(2) == 26 and segments_per_robot(52) == 1
