"""What ``shgm-slam server`` says of its robots (``ServerView``'s state lines), whatever the batching of messages."""

from __future__ import annotations

from shgm_slam.robot.node import RobotNode
from shgm_slam.runner import make_frontend
from shgm_slam.server.node import ServerNode
from shgm_slam.server.serve import ServerView
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.viz.rerun_logger import NullLogger
from tests.server.conftest import FakeClock


def test_a_robot_whose_hello_and_done_arrive_in_one_poll_is_said_to_have_connected(robots, cfg, tmp_path) -> None:
    """A loaded server polled once while a short robot connected, sent its keyframes and its done: the robot was
    never seen active, and the server said only "car1: sent its last keyframe", never that it had connected."""
    clock, bus = FakeClock(), InProcessBus()
    server = ServerNode(cfg, InProcessTransport(bus), tmp_path, reference="car1", expect=3, clock=clock)
    said: list[str] = []
    view = ServerView(NullLogger(), say=said.append)
    robot = RobotNode(make_frontend("car1", robots["car1"], cfg), InProcessTransport(bus), clock=clock)
    robot.hello()
    for i in range(4):
        robot.step(i)
    robot.done()
    view.update(server, server.poll())  # hello, keyframes and done in one batch
    assert said == ["car1: connected (1 of 3 robots expected)", "car1: sent its last keyframe"]
    view.update(server, server.poll())
    assert len(said) == 2  # each said once
