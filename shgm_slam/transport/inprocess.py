"""In-process transport: every node of a single-process run on one shared bus.

``InProcessBus`` is the "network"; each node (robot or server) gets its own
``InProcessTransport(bus)``. ``publish`` delivers synchronously, before it returns, into every
inbox whose subscription matches the key (Zenoh matching: ``*`` one chunk, ``**`` any chunks),
in subscription order. There are no threads and no timing, so a run is deterministic.

Semantics kept identical to the Zenoh transport: a node also receives its own publications when
it subscribes to them; a message matching two subscriptions of one node arrives twice; nothing
published before a subscription exists is replayed to it.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from types import TracebackType

from shgm_slam.errors import TransportError
from shgm_slam.transport.base import Inbox
from shgm_slam.transport.keys import key_matches, validate_key_expr


@dataclass(frozen=True)
class _Subscription:
    owner: int
    key_expr: str
    inbox: Inbox


class InProcessBus:
    """The shared medium of in-process transports; counts what passes through it."""

    def __init__(self) -> None:
        self._subscriptions: list[_Subscription] = []
        self._lock = threading.Lock()
        self._next_owner = 0
        self.messages_published = 0
        self.bytes_published = 0

    def _register(self) -> int:
        with self._lock:
            self._next_owner += 1
            return self._next_owner

    def _subscribe(self, owner: int, key_expr: str, inbox: Inbox) -> None:
        with self._lock:
            self._subscriptions.append(_Subscription(owner, key_expr, inbox))

    def _has_subscriber(self, key: str) -> bool:
        with self._lock:
            return any(key_matches(s.key_expr, key) for s in self._subscriptions)

    def _unsubscribe_all(self, owner: int) -> None:
        with self._lock:
            self._subscriptions = [s for s in self._subscriptions if s.owner != owner]

    def _publish(self, key: str, payload: bytes) -> int:
        with self._lock:
            targets = [s.inbox for s in self._subscriptions if key_matches(s.key_expr, key)]
            self.messages_published += 1
            self.bytes_published += len(payload)
        for inbox in targets:
            inbox.put(key, payload)
        return len(targets)


class InProcessTransport:
    """One node's handle on an :class:`InProcessBus` (implements ``Transport``)."""

    def __init__(self, bus: InProcessBus) -> None:
        self._bus = bus
        self._owner = bus._register()
        self._closed = False

    def publish(self, key: str, payload: bytes) -> None:
        """Deliver ``payload`` now into every matching inbox on the bus."""
        self._check_open()
        validate_key_expr(key, concrete=True)
        self._bus._publish(key, bytes(payload))

    def subscribe(self, key_expr: str, inbox: Inbox | None = None) -> Inbox:
        """Receive every later publication matching ``key_expr`` into ``inbox`` (new if None)."""
        self._check_open()
        validate_key_expr(key_expr)
        inbox = Inbox() if inbox is None else inbox
        self._bus._subscribe(self._owner, key_expr, inbox)
        return inbox

    def wait_for_subscribers(self, key: str, timeout_s: float) -> bool:
        """Whether a subscription on the bus matches ``key`` now (nothing changes while waiting)."""
        self._check_open()
        validate_key_expr(key, concrete=True)
        return self._bus._has_subscriber(key)

    def close(self) -> None:
        """Remove this node's subscriptions from the bus; idempotent."""
        if not self._closed:
            self._closed = True
            self._bus._unsubscribe_all(self._owner)

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError("the in-process transport is closed; open a new one on the bus")

    def __enter__(self) -> InProcessTransport:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
