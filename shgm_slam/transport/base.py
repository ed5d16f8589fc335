"""The transport seam: what a robot or the map server needs to exchange encoded messages.

A node (one robot front end, or the map server) is a single-threaded loop. It holds one
:class:`Transport`, publishes already-encoded ``bytes`` on a key (see :mod:`.keys`) and drains
:class:`Inbox` queues filled by its subscriptions. Transport threads (Zenoh's callbacks) only
ever enqueue; all message handling happens on the node's own thread, in arrival order.

Two implementations share this protocol, so the single-process run and the distributed run
share one code path:

- :class:`~shgm_slam.transport.inprocess.InProcessTransport`: several nodes on one
  :class:`~shgm_slam.transport.inprocess.InProcessBus`, synchronous and deterministic.
- :class:`~shgm_slam.transport.zenoh_transport.ZenohTransport`: Eclipse Zenoh sessions
  between processes or machines.

Key expressions follow Zenoh: ``/``-separated chunks, ``*`` matches exactly one chunk and
``**`` any number of chunks (including none).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from types import TracebackType
from typing import Protocol, runtime_checkable

Message = tuple[str, bytes]
"""One received message: the concrete key it was published on and its payload."""


class Inbox:
    """Thread-safe FIFO of received ``(key, payload)`` messages, unbounded (nothing is dropped).

    Producers (transport threads, or the in-process bus) call :meth:`put`; the node that owns
    the inbox calls :meth:`get` or :meth:`drain` from its loop. Several subscriptions may share
    one inbox, so a node sees all its messages in a single arrival order.
    """

    def __init__(self) -> None:
        self._items: deque[Message] = deque()
        self._cond = threading.Condition()

    def put(self, key: str, payload: bytes) -> None:
        """Enqueue one message (called by the transport, possibly from another thread)."""
        with self._cond:
            self._items.append((key, payload))
            self._cond.notify()

    def get(self, timeout_s: float | None = 0.0) -> Message | None:
        """Pop the oldest message, waiting up to ``timeout_s`` seconds (``None``: forever).

        Returns ``None`` when nothing arrived in time. ``timeout_s=0`` never blocks.
        """
        with self._cond:
            if not self._items and timeout_s != 0.0:
                deadline = None if timeout_s is None else time.monotonic() + timeout_s
                while not self._items:
                    remaining = None if deadline is None else deadline - time.monotonic()
                    if remaining is not None and remaining <= 0.0:
                        break
                    self._cond.wait(remaining)
            return self._items.popleft() if self._items else None

    def drain(self) -> list[Message]:
        """Pop every queued message at once, oldest first (never blocks)."""
        with self._cond:
            items = list(self._items)
            self._items.clear()
        return items

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


@runtime_checkable
class Transport(Protocol):
    """Carries encoded messages between nodes; one instance per node.

    Implementations are context managers (``with make_transport(...) as transport:``) and
    raise :class:`TransportError` (or :class:`~shgm_slam.errors.ConfigError` for bad keys and
    endpoints) with an actionable message.
    """

    def publish(self, key: str, payload: bytes) -> None:
        """Send ``payload`` on the concrete key ``key`` (no wildcards) to every matching subscriber."""
        ...

    def subscribe(self, key_expr: str, inbox: Inbox | None = None) -> Inbox:
        """Deliver every message whose key matches ``key_expr`` into ``inbox`` (a new one if None)."""
        ...

    def wait_for_subscribers(self, key: str, timeout_s: float) -> bool:
        """Whether some subscription (of any node) matches ``key``, waiting up to ``timeout_s`` seconds."""
        ...

    def close(self) -> None:
        """Stop all subscriptions and release the connection; idempotent."""
        ...

    def __enter__(self) -> Transport: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...
