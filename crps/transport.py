"""Swarm transport: Eclipse Zenoh peer to peer over explicit endpoints, and an in-process bus.

Both carry opaque datagrams (signed :mod:`skyfix.crps.messages`) under key expressions
that say what they carry, ``skyfix/<swarm>/<drone>/<topic>`` (topic: heartbeat,
estimate, relative, help), and share one interface (:class:`Transport`): ``publish``,
``subscribe`` (a callback receiving ``(key, data)`` for every drone's messages of the
swarm but one's own) and ``close``. Zenoh runs in peer mode without a broker; multicast
scouting is off, so a drone hears exactly the endpoints it is given: it listens on its
own and connects to its peers', and zenoh reconnects (back-off from 250 ms to 1 s) to a
peer that restarts. Callbacks run on one receiving thread per subscription and must return quickly.
"""

from __future__ import annotations

import json
import logging
import re
import socket
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from skyfix.errors import InputError, LinkError

log = logging.getLogger(__name__)

Callback = Callable[[str, bytes], None]
RX_QUEUE = 4096  # samples zenoh holds for the receiving thread (3 peers x 40 msg/s: ~30 s)
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic)/(\[[0-9a-fA-F:]+\]|[A-Za-z0-9.\-]+):(\d{1,5})$")
_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,32}$")


def key_expr(swarm: str, drone: str, topic: str) -> str:
    """Key expression of ``drone``'s ``topic`` in ``swarm``."""
    return f"skyfix/{swarm}/{drone}/{topic}"


def split_key(key: str) -> tuple[str, str, str] | None:
    """(swarm, drone, topic) of a key expression, or None when it is not one of skyfix's."""
    parts = str(key).split("/")
    return (parts[1], parts[2], parts[3]) if len(parts) == 4 and parts[0] == "skyfix" else None


def check_name(what: str, value: str) -> str:
    """A swarm or drone id: 1-32 letters, digits, '-' or '_' (it becomes a key-expression chunk)."""
    if not isinstance(value, str) or not _NAME.match(value):
        raise InputError(f"{what} must be 1-32 letters, digits, '-' or '_', got {value!r}")
    return value


@dataclass(frozen=True)
class Endpoints:
    """Zenoh endpoints (``tcp/HOST:PORT``) to listen on and to connect to."""

    listen: tuple[str, ...]
    connect: tuple[str, ...]

    @classmethod
    def parse(cls, spec: str, what: str = "--swarm") -> Endpoints:
        """``listen:tcp/127.0.0.1:7451,tcp/127.0.0.1:7452,...``: entries prefixed ``listen:`` are
        listened on, the others connected to (InputError naming the bad entry)."""
        listen, connect = [], []
        for raw in str(spec).split(","):
            item = raw.strip()
            target = listen if item.startswith("listen:") else connect
            endpoint = item.removeprefix("listen:")
            m = _ENDPOINT.match(endpoint)
            if m is None or not 0 < int(m.group(3)) < 65536:
                raise InputError(f"{what}: {item!r} is not an endpoint PROTO/HOST:PORT (e.g. tcp/127.0.0.1:7451, "
                                 "prefix listen: for this drone's own)")
            target.append(endpoint)
        if not listen and not connect:
            raise InputError(f"{what}: no endpoint given")
        return cls(tuple(listen), tuple(connect))


class Transport(Protocol):
    """What the service needs from a swarm network."""

    def publish(self, topic: str, data: bytes) -> None: ...

    def subscribe(self, callback: Callback) -> None: ...

    def close(self) -> None: ...


class ZenohTransport:
    """``drone``'s zenoh peer session in ``swarm`` over explicit ``endpoints`` (no multicast scouting)."""

    def __init__(self, swarm: str, drone: str, endpoints: Endpoints) -> None:
        import zenoh

        self.swarm, self.drone = check_name("swarm", swarm), check_name("drone id", drone)
        conf = zenoh.Config()
        settings = {"mode": "peer", "listen/endpoints": list(endpoints.listen),
                    "connect/endpoints": list(endpoints.connect), "scouting/multicast/enabled": False,
                    "connect/retry": {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}}
        try:
            for path, value in settings.items():
                conf.insert_json5(path, json.dumps(value))
            self._session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise LinkError(f"swarm endpoints {endpoints}: zenoh cannot open them ({str(exc).split(' at /')[0]})"
                            ) from None
        self._publishers: dict[str, object] = {}
        self._subscribers: list[object] = []
        self._readers: list[threading.Thread] = []
        self._lock = threading.Lock()

    def publish(self, topic: str, data: bytes) -> None:
        with self._lock:
            pub = self._publishers.get(topic)
            if pub is None:
                pub = self._publishers[topic] = self._session.declare_publisher(
                    key_expr(self.swarm, self.drone, topic), express=True)  # small messages: no batching delay
        pub.put(data)

    def subscribe(self, callback: Callback) -> None:
        import zenoh

        # Samples wait in zenoh's own bounded FIFO and a Python thread takes them out: zenoh's threads
        # never need the interpreter, so a busy Python side cannot stall (or deadlock) the network side.
        sub = self._session.declare_subscriber(f"skyfix/{self.swarm}/**", zenoh.handlers.FifoChannel(RX_QUEUE))
        self._subscribers.append(sub)
        reader = threading.Thread(target=self._receive, args=(sub, callback), daemon=True,
                                  name=f"skyfix-zenoh-rx {self.drone}")
        self._readers.append(reader)
        reader.start()

    def _receive(self, sub, callback: Callback) -> None:
        import zenoh

        own = f"skyfix/{self.swarm}/{self.drone}/"
        while True:
            try:
                sample = sub.recv()
            except (zenoh.ZError, RuntimeError):  # the session closed: the transport is closing
                return
            key = str(sample.key_expr)
            if not key.startswith(own):
                callback(key, sample.payload.to_bytes())

    def close(self) -> None:
        self._session.close()  # ends the subscribers' channels: the receiving threads return
        for reader in self._readers:
            reader.join(timeout=1.0)
        self._subscribers.clear()


class InProcessBus:
    """A swarm inside one process (tests, the simulator): :meth:`attach` gives each drone a transport."""

    def __init__(self) -> None:
        self._members: list[BusTransport] = []
        self._lock = threading.Lock()

    def attach(self, swarm: str, drone: str) -> BusTransport:
        member = BusTransport(self, check_name("swarm", swarm), check_name("drone id", drone))
        with self._lock:
            self._members.append(member)
        return member

    def _deliver(self, sender: BusTransport, key: str, data: bytes) -> None:
        with self._lock:
            members = list(self._members)
        for m in members:
            if m is not sender and m.swarm == sender.swarm:
                for cb in m.callbacks:
                    cb(key, data)

    def _detach(self, member: BusTransport) -> None:
        with self._lock:
            if member in self._members:
                self._members.remove(member)


class BusTransport:
    """One drone's attachment to an :class:`InProcessBus` (delivers synchronously, in the sender's thread)."""

    def __init__(self, bus: InProcessBus, swarm: str, drone: str) -> None:
        self.bus, self.swarm, self.drone = bus, swarm, drone
        self.callbacks: list[Callback] = []

    def publish(self, topic: str, data: bytes) -> None:
        self.bus._deliver(self, key_expr(self.swarm, self.drone, topic), data)

    def subscribe(self, callback: Callback) -> None:
        self.callbacks.append(callback)

    def close(self) -> None:
        self.bus._detach(self)


def open_transport(swarm: str, drone: str, endpoints: Endpoints | Sequence[str] | str) -> ZenohTransport:
    """A zenoh transport from endpoints in any accepted form (an ``--swarm`` string, or parsed)."""
    if not isinstance(endpoints, Endpoints):
        endpoints = Endpoints.parse(endpoints if isinstance(endpoints, str) else ",".join(endpoints))
    return ZenohTransport(swarm, drone, endpoints)


def free_tcp_ports(count: int) -> list[int]:
    """``count`` distinct TCP ports on 127.0.0.1 free at the time of the call (for loopback swarms)."""
    socks = [socket.socket() for _ in range(count)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()
