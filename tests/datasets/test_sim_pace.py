"""skyfix.datasets.sim.Simulator.pace: the simulated clock slows to the given speed while a consumer of the
simulation (a camera pipeline sharing the CPU) says it is behind, and runs at its own speed again after."""

from __future__ import annotations

import time

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig


def _rate(sim: Simulator, wall_s: float) -> float:
    """Simulated seconds per wall second over ``wall_s``."""
    t0_wall, t0 = time.monotonic(), sim.time_s
    time.sleep(wall_s)
    return (sim.time_s - t0) / (time.monotonic() - t0_wall)


def test_pace_slows_the_clock_while_a_consumer_is_behind():
    behind = [True]
    with Simulator(SimulatorConfig(vehicles=1, speed=3.0)) as sim:
        sim.pace = (lambda: behind[0], 1.0)
        slow = _rate(sim, 1.0)
        behind[0] = False
        fast = _rate(sim, 1.0)
        paced_s = sim.paced_s
    assert slow == pytest.approx(1.0, abs=0.15)  # real time while behind
    assert fast == pytest.approx(3.0, abs=0.45)  # its own speed again (a loaded machine may lose a little)
    assert paced_s == pytest.approx(slow * 1.0, abs=0.3)  # and it counts the simulated time run slower
