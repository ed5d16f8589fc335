"""Zenoh transport on loopback: two sessions in this process, ephemeral ports, bounded waits.

Multicast scouting is off, so these sessions only meet through the explicit endpoints and never
see another run or test on the machine.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable

import pytest

from shgm_slam.errors import ConfigError
from shgm_slam.transport import Inbox, NodeRole, TransportError, TransportMode, ZenohTransport, make_transport
from shgm_slam.transport.keys import ALL_DONE, ALL_KEYFRAMES, STATUS_KEY, correction_key, done_key, keyframe_key
from shgm_slam.transport.zenoh_transport import parse_endpoints

WAIT_S = 8.0


def free_endpoint() -> str:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{sock.getsockname()[1]}"


def wait_until(predicate: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def receive(inbox: Inbox, count: int, timeout_s: float = WAIT_S) -> list[tuple[str, bytes]]:
    deadline = time.monotonic() + timeout_s
    received: list[tuple[str, bytes]] = []
    while len(received) < count:
        message = inbox.get(timeout_s=max(0.0, deadline - time.monotonic()))
        if message is None:
            break
        received.append(message)
    return received


def server_at(endpoint: str) -> ZenohTransport:
    return ZenohTransport(TransportMode.PEER, listen=[endpoint])


def robot_to(endpoint: str) -> ZenohTransport:
    return ZenohTransport(TransportMode.PEER, connect=[endpoint], retry_init_s=0.1, retry_max_s=0.5)


def test_both_ways_with_wildcards() -> None:
    endpoint = free_endpoint()
    with server_at(endpoint) as server, robot_to(endpoint) as robot:
        from_robots = server.subscribe(ALL_KEYFRAMES)
        server.subscribe(ALL_DONE, from_robots)
        to_robot = robot.subscribe("**/correction")
        robot.subscribe("shgm/server/*", to_robot)
        assert robot.wait_for_subscribers(keyframe_key("a"), WAIT_S)
        assert robot.wait_for_subscribers(done_key("a"), WAIT_S)
        assert server.wait_for_subscribers(correction_key("a"), WAIT_S)
        assert server.wait_for_subscribers(STATUS_KEY, WAIT_S)
        assert robot.connected_nodes() == 1

        robot.publish(keyframe_key("a"), b"kf0")
        robot.publish(done_key("a"), b"")
        server.publish(correction_key("a"), b"corr")
        server.publish(correction_key("b"), b"for b")
        server.publish(STATUS_KEY, b"status")
        server.publish("shgm/server/other/status", b"deeper: no match")

        assert receive(from_robots, 2) == [("shgm/a/keyframe", b"kf0"), ("shgm/a/done", b"")]
        assert receive(to_robot, 3) == [
            ("shgm/a/correction", b"corr"),
            ("shgm/b/correction", b"for b"),
            ("shgm/server/status", b"status"),
        ]
        assert to_robot.get(timeout_s=0.2) is None


def test_200_messages_of_5kb_arrive_complete_and_in_order() -> None:
    endpoint = free_endpoint()
    with server_at(endpoint) as server, robot_to(endpoint) as robot:
        inbox = server.subscribe(ALL_KEYFRAMES)
        assert robot.wait_for_subscribers(keyframe_key("a"), WAIT_S)
        payloads = [i.to_bytes(4, "little") + bytes([i % 251]) * 5116 for i in range(200)]
        for payload in payloads:
            robot.publish(keyframe_key("a"), payload)
        received = receive(inbox, len(payloads))
        assert [payload for _, payload in received] == payloads


def test_order_across_keys_sharing_one_inbox() -> None:
    endpoint = free_endpoint()
    with server_at(endpoint) as server, robot_to(endpoint) as robot:
        inbox = server.subscribe(ALL_KEYFRAMES)
        server.subscribe(ALL_DONE, inbox)
        assert robot.wait_for_subscribers(keyframe_key("a"), WAIT_S)
        assert robot.wait_for_subscribers(done_key("a"), WAIT_S)
        sent = [(keyframe_key("a") if i % 3 else done_key("a"), bytes([i])) for i in range(60)]
        for key, payload in sent:
            robot.publish(key, payload)
        assert receive(inbox, len(sent)) == sent


def test_subscriber_first_then_publisher_connects() -> None:
    endpoint = free_endpoint()
    with server_at(endpoint) as server:
        inbox = server.subscribe(ALL_KEYFRAMES)
        with make_transport(NodeRole.ROBOT, endpoint) as robot:
            assert isinstance(robot, ZenohTransport)
            assert robot.wait_for_subscribers(keyframe_key("r1"), WAIT_S)
            robot.publish(keyframe_key("r1"), b"hello")
            assert receive(inbox, 1) == [("shgm/r1/keyframe", b"hello")]


def test_robot_starts_before_the_server_and_survives_a_server_restart() -> None:
    endpoint = free_endpoint()
    with robot_to(endpoint) as robot:  # nothing listens yet: opening must not fail
        assert robot.connected_nodes() == 0
        corrections = robot.subscribe(correction_key("a"))
        key = keyframe_key("a")
        for generation in range(2):  # server start, then server restart on the same port
            with server_at(endpoint) as server:
                inbox = server.subscribe(ALL_KEYFRAMES)
                assert robot.wait_for_subscribers(key, WAIT_S), f"no reconnect (generation {generation})"
                robot.publish(key, f"gen{generation}".encode())
                assert receive(inbox, 1) == [(key, f"gen{generation}".encode())]
                # the robot's subscription is declared again to the new server
                assert server.wait_for_subscribers(correction_key("a"), WAIT_S)
                server.publish(correction_key("a"), bytes([generation]))
                assert receive(corrections, 1) == [(correction_key("a"), bytes([generation]))]
            assert wait_until(lambda: robot.connected_nodes() == 0)
            robot.publish(key, b"lost while the server is down")  # no subscriber: dropped, no error


ROBOT_PROCESS = textwrap.dedent(
    """
    import sys
    from shgm_slam.transport import NodeRole, make_transport
    from shgm_slam.transport.keys import correction_key, done_key, keyframe_key

    with make_transport(NodeRole.ROBOT, sys.argv[1]) as robot:
        corrections = robot.subscribe(correction_key("p"))
        if not robot.wait_for_subscribers(keyframe_key("p"), 10.0):
            sys.exit("no server")
        for i in range(50):
            robot.publish(keyframe_key("p"), i.to_bytes(2, "little") * 2500)
        robot.publish(done_key("p"), b"")
        message = corrections.get(timeout_s=10.0)
        sys.exit(0 if message == (correction_key("p"), b"ack") else f"got {message!r}")
    """
)


def test_robot_process_started_before_the_server() -> None:
    endpoint = free_endpoint()
    robot = subprocess.Popen([sys.executable, "-c", ROBOT_PROCESS, endpoint], stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(0.3)
        with make_transport(NodeRole.SERVER, endpoint) as server:
            inbox = server.subscribe(ALL_KEYFRAMES)
            server.subscribe(ALL_DONE, inbox)
            received = receive(inbox, 51, timeout_s=15.0)
            assert [payload for _, payload in received[:50]] == [i.to_bytes(2, "little") * 2500 for i in range(50)]
            assert received[50:] == [(done_key("p"), b"")]
            assert server.wait_for_subscribers(correction_key("p"), WAIT_S)
            server.publish(correction_key("p"), b"ack")
            _, stderr = robot.communicate(timeout=15.0)
            assert robot.returncode == 0, stderr
    finally:
        if robot.poll() is None:
            robot.kill()
            robot.wait()


def test_robot_closed_and_reopened_reaches_the_same_server() -> None:
    endpoint = free_endpoint()
    with server_at(endpoint) as server:
        inbox = server.subscribe(ALL_KEYFRAMES)
        for run in range(2):
            with robot_to(endpoint) as robot:
                assert robot.wait_for_subscribers(keyframe_key("a"), WAIT_S)
                robot.publish(keyframe_key("a"), bytes([run]))
                assert receive(inbox, 1) == [("shgm/a/keyframe", bytes([run]))]
        assert wait_until(lambda: server.connected_nodes() == 0)


@pytest.mark.parametrize(
    "endpoint", ["127.0.0.1:7447", "tcp/127.0.0.1", "tcp/127.0.0.1:99999", "tcp:/x:1", "tcp/ 1.2.3.4:5", "TCP/a:1"]
)
def test_malformed_endpoint_is_a_config_error(endpoint: str) -> None:
    with pytest.raises(ConfigError, match="endpoint"):
        ZenohTransport(TransportMode.PEER, listen=[endpoint])


def test_unknown_protocol_is_a_config_error_from_zenoh() -> None:
    with pytest.raises(ConfigError, match="foo"):
        ZenohTransport(TransportMode.PEER, listen=["foo/127.0.0.1:1"])


def test_port_in_use_is_a_clear_transport_error() -> None:
    endpoint = free_endpoint()
    with server_at(endpoint), pytest.raises(TransportError, match="already in use") as info:
        server_at(endpoint)
    assert ".rs:" not in str(info.value)


def test_client_mode_waits_for_the_server_then_fails_clearly() -> None:
    endpoint = free_endpoint()
    started = time.monotonic()
    with pytest.raises(TransportError, match="cannot reach"):
        ZenohTransport(TransportMode.CLIENT, connect=[endpoint], open_timeout_s=0.3)
    assert time.monotonic() - started < 5.0
    with pytest.raises(ConfigError):
        ZenohTransport(TransportMode.CLIENT, listen=[endpoint], connect=[endpoint])


def test_client_robot_to_peer_server() -> None:
    endpoint = free_endpoint()
    with make_transport(NodeRole.SERVER, endpoint) as server:
        inbox = server.subscribe("shgm/**")
        with make_transport(NodeRole.ROBOT, endpoint, mode=TransportMode.CLIENT) as robot:
            assert isinstance(robot, ZenohTransport)
            assert robot.wait_for_subscribers(keyframe_key("c"), WAIT_S)
            robot.publish(keyframe_key("c"), b"from a client")
            assert receive(inbox, 1) == [("shgm/c/keyframe", b"from a client")]


def test_parse_endpoints_and_closed_transport() -> None:
    assert parse_endpoints("tcp/127.0.0.1:1, tcp/[::1]:2") == ["tcp/127.0.0.1:1", "tcp/[::1]:2"]
    assert parse_endpoints(None) == []
    transport = ZenohTransport(TransportMode.PEER)
    transport.close()
    transport.close()
    with pytest.raises(TransportError, match="closed"):
        transport.publish(keyframe_key("a"), b"x")


def test_three_robots_one_server() -> None:
    endpoint = free_endpoint()
    names = ["r0", "r1", "r2"]
    with server_at(endpoint) as server:
        inbox = server.subscribe(ALL_KEYFRAMES)
        robots = [robot_to(endpoint) for _ in names]
        try:
            corrections = [robot.subscribe(correction_key(name)) for robot, name in zip(robots, names, strict=True)]
            for robot, name in zip(robots, names, strict=True):
                assert robot.wait_for_subscribers(keyframe_key(name), WAIT_S)
                assert server.wait_for_subscribers(correction_key(name), WAIT_S)
            for i in range(10):
                for robot, name in zip(robots, names, strict=True):
                    robot.publish(keyframe_key(name), bytes([i]))
            received = receive(inbox, 30)
            for name in names:
                assert [payload for key, payload in received if key == keyframe_key(name)] == [
                    bytes([i]) for i in range(10)
                ]
            server.publish(correction_key("r1"), b"only r1")
            assert receive(corrections[1], 1) == [(correction_key("r1"), b"only r1")]
            assert corrections[0].get(timeout_s=0.2) is None and corrections[2].get() is None
        finally:
            for robot in robots:
                robot.close()
