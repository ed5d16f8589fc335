"""The transport seam between robots and the map server: in-process bus or Eclipse Zenoh."""

from shgm_slam.errors import TransportError
from shgm_slam.transport.base import Inbox, Message, Transport
from shgm_slam.transport.factory import NodeRole, make_transport
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport
from shgm_slam.transport.zenoh_transport import DEFAULT_ENDPOINT, TransportMode, ZenohTransport

__all__ = [
    "DEFAULT_ENDPOINT",
    "InProcessBus",
    "InProcessTransport",
    "Inbox",
    "Message",
    "NodeRole",
    "Transport",
    "TransportError",
    "TransportMode",
    "ZenohTransport",
    "make_transport",
]
