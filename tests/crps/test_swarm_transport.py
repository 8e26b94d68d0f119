"""Swarm transport: zenoh peers on explicit loopback endpoints and the in-process bus, same interface."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from skyfix.crps.transport import Endpoints, InProcessBus, ZenohTransport, key_expr, split_key
from skyfix.crps.transport import free_tcp_ports as free_ports
from skyfix.errors import InputError, LinkError


class Inbox:
    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self.event = threading.Event()

    def __call__(self, key: str, data: bytes) -> None:
        self.items.append((key, data))
        self.event.set()


def wait_for(pred, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.02)
    return pred()


def test_endpoint_parsing_names_the_bad_entry():
    ep = Endpoints.parse("listen:tcp/127.0.0.1:7451, tcp/127.0.0.1:7452,tcp/localhost:7453")
    assert ep.listen == ("tcp/127.0.0.1:7451",) and ep.connect == ("tcp/127.0.0.1:7452", "tcp/localhost:7453")
    for bad in ("127.0.0.1:7451", "tcp/127.0.0.1", "tcp/127.0.0.1:99999", "carrier-pigeon/x:1", ""):
        with pytest.raises(InputError, match="--swarm"):
            Endpoints.parse(bad)
    assert split_key(key_expr("s1", "d2", "heartbeat")) == ("s1", "d2", "heartbeat")
    assert split_key("other/thing") is None


def test_bus_delivers_to_the_others_of_the_swarm_only():
    bus = InProcessBus()
    a, b, c = bus.attach("s", "a"), bus.attach("s", "b"), bus.attach("other", "c")
    ia, ib, ic = Inbox(), Inbox(), Inbox()
    a.subscribe(ia)
    b.subscribe(ib)
    c.subscribe(ic)
    a.publish("heartbeat", b"hello")
    assert ib.items == [("skyfix/s/a/heartbeat", b"hello")] and not ia.items and not ic.items
    b.close()
    a.publish("heartbeat", b"again")
    assert len(ib.items) == 1


def test_zenoh_peers_on_loopback_and_a_restart():
    p1, p2 = free_ports(2)
    e1, e2 = f"tcp/127.0.0.1:{p1}", f"tcp/127.0.0.1:{p2}"
    a = ZenohTransport("s", "a", Endpoints.parse(f"listen:{e1},{e2}"))
    b = ZenohTransport("s", "b", Endpoints.parse(f"listen:{e2},{e1}"))
    try:
        ia, ib = Inbox(), Inbox()
        a.subscribe(ia)
        b.subscribe(ib)
        # publish until heard: the sessions connect asynchronously
        assert wait_for(lambda: (b.publish("heartbeat", b"from b") or bool(ia.items)), 5.0)
        assert wait_for(lambda: (a.publish("estimate", b"from a") or bool(ib.items)), 5.0)
        assert ia.items[0] == ("skyfix/s/b/heartbeat", b"from b")
        assert all(k.startswith("skyfix/s/a/") for k, _ in ib.items)  # never one's own messages
        b.close()
        b = ZenohTransport("s", "b", Endpoints.parse(f"listen:{e2},{e1}"))
        n = len(ia.items)
        t0 = time.monotonic()
        assert wait_for(lambda: (b.publish("heartbeat", b"back") or len(ia.items) > n), 5.0)
        # a restarted peer is heard again within the lost time-out (2 s quiet; slack for a loaded machine)
        assert time.monotonic() - t0 < 4.0
    finally:
        a.close()
        b.close()


def test_zenoh_refuses_a_busy_listen_endpoint():
    (p,) = free_ports(1)
    holder = socket.socket()
    holder.bind(("127.0.0.1", p))
    holder.listen()
    try:
        with pytest.raises(LinkError, match="zenoh cannot open"):
            ZenohTransport("s", "a", Endpoints.parse(f"listen:tcp/127.0.0.1:{p}"))
    finally:
        holder.close()
