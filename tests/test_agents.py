"""Agent names: a robot and its later trajectory segments."""

from __future__ import annotations

from shgm_slam.agents import SEGMENT_SEPARATOR, agent_robot, segment_agent


def test_segment_names_round_trip_and_the_first_segment_is_the_robot() -> None:
    assert segment_agent("car1", 0) == "car1" and agent_robot("car1") == ("car1", 0)
    for robot in ("car1", "uav", "kitti08a", "r-2_x"):
        for seg in (0, 1, 2, 17):
            name = segment_agent(robot, seg)
            assert agent_robot(name) == (robot, seg)
            assert (SEGMENT_SEPARATOR in name) == (seg > 0)
