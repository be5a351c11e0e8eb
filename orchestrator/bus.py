"""The zenoh session: the daemon in router mode (it routes between the tracking worker and any other
subscriber), processes that only connect in client mode; explicit endpoints, multicast scouting off unless asked.

Readers of frames use a ring channel (newest wins) so a slow subscriber never builds up
latency; subscribers are polled with ``try_recv`` because a thread blocked in ``recv`` makes
``undeclare`` abort the process (docs/architecture.md, zenoh).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from typing import Any

from orchestrator.config import BusConfig
from orchestrator.zenoh_security import zenoh_security_json5

log = logging.getLogger(__name__)


def zenoh_config(bus: BusConfig, *, listen: bool = True, connect: list[str] | None = None) -> Any:
    """A ``zenoh.Config`` for ``bus``; ``listen=False`` for a process that only connects.

    A process that only connects is a client: a router (or a peer) forwards it everything it subscribes
    to, whereas a peer with gossip off only hears the peers it connected to itself.
    """
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(bus.mode if listen else "client"))
    c.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast_scouting))
    c.insert_json5("scouting/gossip/enabled", json.dumps(bus.multicast_scouting))
    c.insert_json5("listen/endpoints", json.dumps(bus.listen if listen else []))
    c.insert_json5("connect/endpoints", json.dumps(bus.connect if connect is None else connect))
    for key, value in zenoh_security_json5(bus.tls, bus.access_control).items():  # TLS and ACL, when configured
        c.insert_json5(key, json.dumps(value))
    return c


def free_port() -> int:
    """A TCP port on 127.0.0.1 the OS just handed out: tests and benchmarks listen there, so two runs at
    the same time never share an endpoint."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def local_endpoints(endpoints: list[str]) -> list[str]:
    """Endpoints a process on this host can connect to (``0.0.0.0`` / ``[::]`` become loopback)."""
    return [e.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:") for e in endpoints]


class Bus:
    """One zenoh session with cached publishers under ``<prefix>/<station>/``."""

    def __init__(self, bus: BusConfig, station: str, *, listen: bool = True, connect: list[str] | None = None):
        import zenoh

        self.config = bus
        self.station = station
        try:
            self.session = zenoh.open(zenoh_config(bus, listen=listen, connect=connect))
        except Exception as e:  # zenoh raises ZError with the endpoint in the message
            raise RuntimeError(
                f"cannot open the zenoh session (listen={bus.listen if listen else []}, "
                f"connect={bus.connect if connect is None else connect}): {e}"
            ) from None
        self._publishers: dict[str, Any] = {}
        self._subscribers: list[Any] = []  # subscribers, queryables, liveliness tokens: undeclared on close
        self._lock = threading.Lock()

    def key(self, *parts: str) -> str:
        """``<prefix>/<station>/<parts>``."""
        return self.config.key(self.station, *parts)

    def put(self, key: str, payload: bytes) -> None:
        """Publish ``payload`` on the full key ``key`` (publisher declared once per key)."""
        with self._lock:
            pub = self._publishers.get(key)
            if pub is None:
                pub = self._publishers[key] = self.session.declare_publisher(key)
        pub.put(payload)

    def subscribe(self, key: str, ring: int | None = None, callback: Callable[[Any], None] | None = None) -> Any:
        """Subscribe to ``key``: a ring channel of ``ring`` samples (poll with try_recv), a FIFO, or a callback."""
        import zenoh

        if callback is not None:
            handler: Any = callback
        elif ring is not None:
            handler = zenoh.handlers.RingChannel(ring)
        else:
            handler = zenoh.handlers.FifoChannel(1024)
        sub = self.session.declare_subscriber(key, handler)
        self._subscribers.append(sub)
        return sub

    def queryable(self, key: str, handler: Callable[[Any], None]) -> Any:
        """Answer gets on ``key`` with ``handler(query)`` (it calls ``query.reply(key, payload)``)."""
        q = self.session.declare_queryable(key, handler)
        self._subscribers.append(q)
        return q

    def get(self, key: str, payload: bytes | None = None, timeout: float = 2.0) -> list[bytes]:
        """The payloads of every reply to a get on ``key`` (waits at most ``timeout`` s); errors are left out."""
        replies = self.session.get(key, payload=payload, timeout=timeout)
        return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]

    def declare_token(self, key: str) -> Any:
        """A liveliness token on ``key``: it disappears for every subscriber when this process dies."""
        tok = self.session.liveliness().declare_token(key)
        self._subscribers.append(tok)
        return tok

    def watch_liveliness(self, key: str, callback: Callable[[Any], None]) -> Any:
        """Liveliness subscriber on ``key`` (with the tokens alive now): samples of kind PUT (up) / DELETE (gone)."""
        sub = self.session.liveliness().declare_subscriber(key, callback, history=True)
        self._subscribers.append(sub)
        return sub

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        for ent in [*self._subscribers, *self._publishers.values()]:
            try:
                ent.undeclare()
            except Exception as e:  # already closed
                log.debug("undeclare failed: %s", e)
        self._subscribers.clear()
        self._publishers.clear()
        if not self.session.is_closed():
            self.session.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_client(bus: BusConfig, station: str, endpoints: list[str], timeout: float = 0.0) -> Bus:
    """A connect-only (client) Bus to ``endpoints``, retried every 0.5 s for ``timeout`` s (the session may be
    starting); raises RuntimeError naming the endpoints when none answers."""
    import time

    deadline = time.monotonic() + timeout
    while True:
        try:
            return Bus(bus, station, listen=False, connect=endpoints)
        except RuntimeError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.5)
