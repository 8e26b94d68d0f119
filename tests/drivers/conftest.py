"""Fixtures: a simulator on loopback (ephemeral ports) and a connected skyfix Vehicle."""

from __future__ import annotations

import socket

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers.vehicle import Vehicle

SPEED = 5.0  # simulated seconds per wall second in tests


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago (for udpin listeners)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.fixture
def sim():
    with Simulator(SimulatorConfig(vehicles=1, speed=SPEED, seed=3)) as s:
        yield s


@pytest.fixture
def vehicle(sim):
    v = Vehicle.connect(sim.url(0), timeout_s=5.0)
    v.wait_until(lambda st: st.position is not None and st.gps is not None and st.home is not None,
                 5.0, what="first telemetry")
    yield v
    v.close()


@pytest.fixture
def udp_port() -> int:
    return free_udp_port()
