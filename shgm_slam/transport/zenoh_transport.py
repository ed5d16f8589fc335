"""Eclipse Zenoh transport: robots and the map server as separate processes or machines.

One :class:`ZenohTransport` opens one Zenoh session (``eclipse-zenoh`` 1.x). Topology by default:
peer mode on loopback; the server *listens* on ``tcp/127.0.0.1:7447`` and every robot *connects*
to it. Endpoints use Zenoh's syntax ``<protocol>/<address>`` (``tcp/127.0.0.1:7447``,
``tcp/[::1]:7447``, ``tcp/robot-base.local:7447``); give a LAN address (or ``tcp/0.0.0.0:7447``)
to the server to reach robots on other machines.

Zenoh configuration this module sets (see the Zenoh ``DEFAULT_CONFIG.json5``):

- ``mode``: ``"peer"`` (default) or ``"client"`` (:class:`TransportMode`).
- ``scouting/multicast/enabled = false``: no multicast discovery, so two runs (or tests) on one
  machine or LAN never join each other; nodes meet only through the explicit endpoints.
- ``listen/endpoints``: exactly the given list (a robot listens on nothing by default), and
  ``listen/exit_on_failure = true``, so a port already in use fails at open with
  :class:`TransportError` instead of a silent node.
- ``connect/endpoints``: the given list. In peer mode ``connect/timeout_ms = -1`` with
  ``connect/exit_on_failure = false``: opening returns in milliseconds when the server is up and
  after about 0.5 s when it is not, and Zenoh keeps retrying in the background until it appears; a lost link (the
  server stopped and restarted) is retried the same way, so robots reconnect by themselves.
  Note: ``connect/timeout_ms = 0`` would try once and never retry (measured with zenoh 1.10).
- ``connect/retry``: ``period_init_ms`` / ``period_max_ms`` / ``period_increase_factor``, the
  back-off between connection attempts (here 200 ms growing to 2 s, instead of 1 s to 4 s).
- In client mode a session cannot open without a reachable peer or router:
  ``connect/timeout_ms`` is ``open_timeout_s`` and ``connect/exit_on_failure = true``, so opening
  blocks until the server is reachable and raises :class:`TransportError` after that time.

Publications use a declared publisher per key with ``Reliability.RELIABLE`` and
``CongestionControl.BLOCK``: while a link is up, a full send queue makes ``publish`` wait
instead of dropping a keyframe. Zenoh stores nothing: a message published while no subscriber
is connected (server down, not yet connected, or subscriptions not yet propagated after a
reconnect) is gone. The protocol above the transport handles that (hello/acknowledge, re-send of
unacknowledged keyframes); :meth:`ZenohTransport.wait_for_subscribers` tells whether a key
currently has a subscriber.

Subscriber callbacks only enqueue ``(key, payload)`` into an
:class:`~shgm_slam.transport.base.Inbox`; the node drains it from its own loop. They are declared
with ``zenoh.handlers.Callback(..., indirect=False)`` so they run directly on Zenoh's receiving
thread: with zenoh-python's default (``indirect=True``) every subscriber gets its own Python
thread, and two subscriptions sharing one inbox (``shgm/*/keyframe`` and ``shgm/*/done``) then
see messages out of their publication order (a robot's ``done`` before its last keyframe).

Zenoh's own (Rust) log is off unless :func:`enable_zenoh_logging` is called (from the CLI, once);
``RUST_LOG`` overrides the level.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Sequence
from enum import Enum
from types import TracebackType

import zenoh

from shgm_slam.errors import ConfigError, TransportError
from shgm_slam.transport.base import Inbox
from shgm_slam.transport.keys import DEFAULT_ENDPOINT, validate_key_expr

_ENDPOINT = re.compile(r"[a-z][a-z0-9-]*/[^\s,]+")
_HOST_PORT = re.compile(r"(?:\[[0-9A-Fa-f:.]+\]|[^:\[\]/?#]+):(\d+)(?:[?#].*)?")
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


class TransportMode(Enum):
    """Zenoh node mode: ``PEER`` (listens and/or connects) or ``CLIENT`` (connects only)."""

    PEER = "peer"
    CLIENT = "client"


def parse_endpoints(spec: str | Sequence[str] | None) -> list[str]:
    """Endpoints from ``"tcp/h:p"``, ``"tcp/h:p,tcp/h2:p2"`` or a list ([] for None or an empty list); ConfigError
    if malformed, or for a string that names none (``""`` is not the default endpoint, which None stands for)."""
    if spec is None:
        return []
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    endpoints = []
    for item in items:
        endpoint = str(item).strip()
        if not endpoint:
            continue
        if _ENDPOINT.fullmatch(endpoint) is None:
            raise ConfigError(
                f"endpoint {endpoint!r} is not in Zenoh syntax <protocol>/<address>, for example {DEFAULT_ENDPOINT!r}"
            )
        protocol, address = endpoint.split("/", 1)
        if protocol in _IP_PROTOCOLS:
            match = _HOST_PORT.fullmatch(address)
            if match is None or not 0 <= int(match.group(1)) <= 65535:
                raise ConfigError(
                    f"endpoint {endpoint!r} needs <host>:<port> with a port in 0-65535, "
                    f"for example {DEFAULT_ENDPOINT!r}"
                )
        endpoints.append(endpoint)
    if not endpoints and isinstance(spec, str):  # ("--connect ''" from an unset variable meant the default one)
        raise ConfigError(f"no endpoint given ({spec!r}); give one in Zenoh syntax, for example {DEFAULT_ENDPOINT!r}")
    return endpoints


def zenoh_config(
    mode: TransportMode,
    listen: Sequence[str],
    connect: Sequence[str],
    *,
    retry_init_s: float = 0.2,
    retry_max_s: float = 2.0,
    open_timeout_s: float = 10.0,
) -> zenoh.Config:
    """The Zenoh configuration described in the module docstring."""
    if mode is TransportMode.CLIENT and listen:
        raise ConfigError("a Zenoh client cannot listen; use peer mode to accept connections")
    if mode is TransportMode.CLIENT and not connect:
        raise ConfigError(f"a Zenoh client needs an endpoint to connect to, for example {DEFAULT_ENDPOINT!r}")
    if retry_init_s <= 0 or retry_max_s < retry_init_s:
        raise ConfigError(f"need 0 < retry_init_s <= retry_max_s, got {retry_init_s} and {retry_max_s}")
    peer = mode is TransportMode.PEER
    settings: dict[str, object] = {
        "mode": mode.value,
        "scouting/multicast/enabled": False,
        "listen/endpoints": list(listen),
        "listen/exit_on_failure": True,
        "connect/endpoints": list(connect),
        "connect/timeout_ms": -1 if peer else max(1, round(open_timeout_s * 1000)),
        "connect/exit_on_failure": not peer,
        "connect/retry": {
            "period_init_ms": max(1, round(retry_init_s * 1000)),
            "period_max_ms": max(1, round(retry_max_s * 1000)),
            "period_increase_factor": 2.0,
        },
    }
    config = zenoh.Config()
    for key, value in settings.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except zenoh.ZError as error:
            raise ConfigError(f"invalid Zenoh setting {key} = {value!r}: {_short(error)}") from None
    return config


_logging_lock = threading.Lock()
_logging_on = False


def enable_zenoh_logging(level: str = "warn") -> None:
    """Send Zenoh's log to stdout at ``level`` (``RUST_LOG`` wins); only the first call acts."""
    global _logging_on
    with _logging_lock:
        if not _logging_on:
            zenoh.init_log_from_env_or(level)
            _logging_on = True


class ZenohTransport:
    """A node's Zenoh session (implements ``Transport``); see the module docstring.

    Args:
        mode: peer (default) or client.
        listen: endpoints this node accepts connections on (the server), e.g. ``["tcp/127.0.0.1:7447"]``.
        connect: endpoints this node connects to (robots), retried until reachable.
        retry_init_s, retry_max_s: back-off between connection attempts, seconds.
        open_timeout_s: client mode only: how long opening waits for the endpoint.
    """

    def __init__(
        self,
        mode: TransportMode = TransportMode.PEER,
        listen: Sequence[str] = (),
        connect: Sequence[str] = (),
        *,
        retry_init_s: float = 0.2,
        retry_max_s: float = 2.0,
        open_timeout_s: float = 10.0,
    ) -> None:
        self.mode = mode
        self.listen = parse_endpoints(listen)
        self.connect = parse_endpoints(connect)
        config = zenoh_config(
            mode,
            self.listen,
            self.connect,
            retry_init_s=retry_init_s,
            retry_max_s=retry_max_s,
            open_timeout_s=open_timeout_s,
        )
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as error:
            raise _open_error(error, self.listen, self.connect) from None
        self._lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._subscribers: list[zenoh.Subscriber] = []
        self._closed = False

    def publish(self, key: str, payload: bytes) -> None:
        """Send ``payload`` reliably on ``key``; blocks (never drops) while the send queue is full."""
        publisher = self._publisher(key)
        try:
            publisher.put(bytes(payload))
        except zenoh.ZError as error:
            raise TransportError(f"publishing on {key!r} failed: {_short(error)}") from None

    def subscribe(self, key_expr: str, inbox: Inbox | None = None) -> Inbox:
        """Enqueue every message matching ``key_expr`` into ``inbox`` (new if None)."""
        validate_key_expr(key_expr)
        inbox = Inbox() if inbox is None else inbox

        def on_sample(sample: zenoh.Sample) -> None:
            inbox.put(str(sample.key_expr), sample.payload.to_bytes())

        with self._lock:
            self._check_open()
            try:
                # indirect=False: run on Zenoh's receiving thread, not one Python thread per
                # subscriber, so messages on different keys keep their order of arrival.
                handler = zenoh.handlers.Callback(on_sample, indirect=False)
                self._subscribers.append(self._session.declare_subscriber(key_expr, handler))
            except zenoh.ZError as error:
                raise TransportError(f"subscribing to {key_expr!r} failed: {_short(error)}") from None
        return inbox

    def wait_for_subscribers(self, key: str, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until some subscriber (in any connected node) matches ``key``."""
        publisher = self._publisher(key)
        deadline = time.monotonic() + timeout_s
        while not publisher.matching_status.matching:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def connected_nodes(self) -> int:
        """How many Zenoh peers and routers this session is connected to right now."""
        with self._lock:
            self._check_open()
            info = self._session.info
            return len(info.peers_zid()) + len(info.routers_zid())

    def close(self) -> None:
        """Undeclare everything and close the session; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for entity in [*self._subscribers, *self._publishers.values()]:
                try:
                    entity.undeclare()
                except zenoh.ZError:
                    pass  # the session is going away anyway
            self._subscribers.clear()
            self._publishers.clear()
            self._session.close()

    def _publisher(self, key: str) -> zenoh.Publisher:
        with self._lock:
            self._check_open()
            publisher = self._publishers.get(key)
            if publisher is None:
                validate_key_expr(key, concrete=True)
                try:
                    publisher = self._session.declare_publisher(
                        key,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                        reliability=zenoh.Reliability.RELIABLE,
                    )
                except zenoh.ZError as error:
                    raise TransportError(f"declaring a publisher on {key!r} failed: {_short(error)}") from None
                self._publishers[key] = publisher
            return publisher

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError("the Zenoh transport is closed; open a new one")

    def __enter__(self) -> ZenohTransport:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _short(error: Exception) -> str:
    """Zenoh's message without the Rust source locations (`` at /path/file.rs:N``)."""
    text = re.sub(r"\s*at /\S+\.rs:\d+\.?", "", str(error))
    return text.strip().rstrip(".") or type(error).__name__


def _open_error(error: Exception, listen: list[str], connect: list[str]) -> Exception:
    text = _short(error)
    if "Address already in use" in text or "os error 98" in text:
        return TransportError(
            f"cannot listen on {', '.join(listen)}: the port is already in use (another server "
            "still running?); stop it or choose another port with --listen"
        )
    if "Unable to connect" in text:
        return TransportError(f"cannot reach {', '.join(connect)}: is the server running there? ({text})")
    if "invalid" in text.lower() or "not supported" in text.lower():
        return ConfigError(f"invalid endpoint in listen={listen} connect={connect}: {text}")
    return TransportError(f"opening the Zenoh session failed (listen={listen}, connect={connect}): {text}")
