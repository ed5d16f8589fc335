"""Build a node's transport from its role and an endpoint spec (what the CLI passes through).

- ``bus`` given: an in-process transport on that bus (``shgm-slam run``).
- Server, peer mode: listens on the endpoint(s) (default ``tcp/127.0.0.1:7447``).
- Robot, or any node in client mode: connects to the endpoint(s) (same default).
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import Enum

from shgm_slam.transport.base import Transport
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.zenoh_transport import (
    DEFAULT_ENDPOINT,
    TransportMode,
    ZenohTransport,
    parse_endpoints,
)


class NodeRole(Enum):
    """Which side of the protocol a node plays."""

    SERVER = "server"
    ROBOT = "robot"


def make_transport(
    role: NodeRole,
    endpoint: str | Sequence[str] | None = None,
    *,
    mode: TransportMode = TransportMode.PEER,
    bus: InProcessBus | None = None,
) -> Transport:
    """The transport of one node; ``endpoint`` is one or more comma-separated Zenoh endpoints."""
    if bus is not None:
        return InProcessTransport(bus)
    endpoints = parse_endpoints(endpoint) or [DEFAULT_ENDPOINT]
    if role is NodeRole.SERVER and mode is TransportMode.PEER:
        return ZenohTransport(mode, listen=endpoints)
    return ZenohTransport(mode, connect=endpoints)
