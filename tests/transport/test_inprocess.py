"""In-process transport: key matching, routing, order, inbox semantics, key helpers."""

from __future__ import annotations

import threading

import pytest

from shgm_slam.errors import ConfigError
from shgm_slam.transport import InProcessBus, InProcessTransport, NodeRole, Transport, TransportError, make_transport
from shgm_slam.transport.base import Inbox
from shgm_slam.transport.keys import (
    ALL_KEYFRAMES,
    STATUS_KEY,
    correction_key,
    done_key,
    hello_key,
    key_matches,
    keyframe_key,
    robot_of,
    validate_key_expr,
    validate_robot_name,
)


@pytest.mark.parametrize(
    ("key_expr", "key", "expected"),
    [
        ("shgm/*/keyframe", "shgm/a/keyframe", True),
        ("shgm/*/keyframe", "shgm/a/b/keyframe", False),
        ("shgm/*/keyframe", "shgm/a/done", False),
        ("shgm/*", "shgm", False),
        ("shgm/**", "shgm", True),
        ("shgm/**", "shgm/a/keyframe", True),
        ("**/keyframe", "shgm/a/keyframe", True),
        ("**", "x", True),
        ("shgm/**/done", "shgm/done", True),
        ("shgm/**/done", "shgm/a/b/done", True),
        ("shgm/**/done", "shgm/a/b/keyframe", False),
        ("shgm/a/keyframe", "shgm/a/keyframe", True),
        ("shgm/a/keyframe", "shgm/ab/keyframe", False),
        ("*/*", "shgm/a", True),
    ],
)
def test_key_matching_follows_zenoh(key_expr: str, key: str, expected: bool) -> None:
    assert key_matches(key_expr, key) is expected


def test_key_helpers_and_robot_names() -> None:
    assert keyframe_key("robot_a") == "shgm/robot_a/keyframe"
    assert hello_key("r1") == "shgm/r1/hello"
    assert done_key("r1") == "shgm/r1/done"
    assert correction_key("r-2") == "shgm/r-2/correction"
    assert STATUS_KEY == "shgm/server/status"
    assert robot_of(keyframe_key("uav")) == "uav"
    assert validate_robot_name("A" * 32) == "A" * 32
    for bad in ["", "1robot", "a/b", "a*", "a$b", "a b", "A" * 33, "server", "ü"]:
        with pytest.raises(ConfigError):
            keyframe_key(bad)
    for bad in ["", "/shgm", "shgm/", "shgm//a", "shgm/a*b", "shgm/$*", "shgm/a?x"]:
        with pytest.raises(ConfigError):
            validate_key_expr(bad)
    with pytest.raises(ConfigError, match="wildcards"):
        validate_key_expr(ALL_KEYFRAMES, concrete=True)


def test_bus_routes_by_key_expression_in_order() -> None:
    bus = InProcessBus()
    with InProcessTransport(bus) as server, InProcessTransport(bus) as robot_a, InProcessTransport(bus) as robot_b:
        assert isinstance(server, Transport)
        inbox = server.subscribe(ALL_KEYFRAMES)
        assert not robot_a.wait_for_subscribers(done_key("a"), 1.0)
        server.subscribe("shgm/*/done", inbox)
        assert robot_a.wait_for_subscribers(done_key("a"), 1.0)
        corrections_a = robot_a.subscribe(correction_key("a"))
        status_b = robot_b.subscribe(STATUS_KEY)

        robot_a.publish(keyframe_key("a"), b"a0")
        robot_b.publish(keyframe_key("b"), b"b0")
        robot_a.publish(keyframe_key("a"), b"a1")
        robot_b.publish(done_key("b"), b"")
        server.publish(correction_key("a"), b"corr")
        server.publish(correction_key("b"), b"nobody")
        server.publish(STATUS_KEY, b"ok")

        assert inbox.drain() == [
            ("shgm/a/keyframe", b"a0"),
            ("shgm/b/keyframe", b"b0"),
            ("shgm/a/keyframe", b"a1"),
            ("shgm/b/done", b""),
        ]
        assert corrections_a.drain() == [("shgm/a/correction", b"corr")]
        assert status_b.get() == ("shgm/server/status", b"ok")
        assert status_b.get(timeout_s=0.0) is None
        assert bus.messages_published == 7
        assert bus.bytes_published == 2 * 3 + 4 + 6 + 2


def test_own_publications_double_subscriptions_and_close() -> None:
    bus = InProcessBus()
    node = InProcessTransport(bus)
    other = InProcessTransport(bus)
    inbox = node.subscribe("shgm/**")
    node.subscribe(ALL_KEYFRAMES, inbox)
    node.publish(keyframe_key("a"), b"x")
    assert inbox.drain() == [("shgm/a/keyframe", b"x")] * 2  # one per matching subscription, like Zenoh
    node.close()
    node.close()
    other.publish(keyframe_key("a"), b"y")
    assert len(inbox) == 0
    with pytest.raises(TransportError):
        node.publish(keyframe_key("a"), b"z")
    with pytest.raises(ConfigError):
        other.publish(ALL_KEYFRAMES, b"z")
    assert isinstance(make_transport(NodeRole.ROBOT, bus=bus), InProcessTransport)


def test_inbox_get_waits_for_a_producer_thread() -> None:
    inbox = Inbox()
    assert inbox.get(timeout_s=0.05) is None
    timer = threading.Timer(0.05, inbox.put, args=("k", b"v"))
    timer.start()
    assert inbox.get(timeout_s=5.0) == ("k", b"v")
    timer.join()
    for i in range(5):
        inbox.put("k", bytes([i]))
    assert inbox.get() == ("k", b"\x00")
    assert [payload for _, payload in inbox.drain()] == [bytes([i]) for i in range(1, 5)]
    assert inbox.drain() == []
