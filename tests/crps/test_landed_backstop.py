"""HelpLoop._landed_backstop: a drone its autopilot landed in LAND but left armed is disarmed by the companion
once it has been low and still for LANDED_FOR_S; never while it descends, hovers higher up, or flies another mode."""

from types import SimpleNamespace

import pytest

from skyfix.crps.help_loop import LANDED_FOR_S, LANDED_MAX_ALT_M, HelpLoop
from skyfix.crps.roles import Mode
from skyfix.drivers.state import Position, Velocity


class _Vehicle:
    def __init__(self) -> None:
        self.disarms: list[bool] = []

    def disarm(self, *, force: bool = False, timeout_s: float = 3.0) -> None:
        self.disarms.append(force)


def _loop(mode: Mode = Mode.LAND):
    vehicle = _Vehicle()
    actions = SimpleNamespace(busy=False, submit=lambda kind, what, fn: fn())
    loop = SimpleNamespace(id="d2", mode=mode, svc=SimpleNamespace(vehicle=vehicle), _actions=actions, _still_since_s=None,
                           events=[], _land_mode=lambda: "LAND")
    loop._event = lambda t, text: loop.events.append((t, text))
    return loop, vehicle


def _state(alt_rel_m: float, down_mps: float, mode: str = "LAND", armed: bool = True):
    return SimpleNamespace(armed=armed, mode=mode, position=Position(46.5, 6.6, 372.0 + alt_rel_m, alt_rel_m, 0.0),
                           velocity=Velocity(0.0, 0.0, down_mps, 0.0))


def _fly(loop, states, dt_s: float = 0.2) -> None:
    for k, st in enumerate(states):
        HelpLoop._landed_backstop(loop, k * dt_s, st)


def test_landed_and_still_for_long_enough_is_disarmed_once_forced():
    loop, vehicle = _loop()
    _fly(loop, [_state(0.1, 0.02)] * int(round(1.5 * LANDED_FOR_S / 0.2)))
    assert vehicle.disarms == [True]
    assert [t for t, _ in loop.events] == [pytest.approx(LANDED_FOR_S)]  # at LANDED_FOR_S, once


@pytest.mark.parametrize("alt_rel_m, down_mps, ap_mode, mode", [
    (0.8, 0.5, "LAND", Mode.LAND),                    # still descending
    (LANDED_MAX_ALT_M + 1.0, 0.0, "LAND", Mode.LAND),  # still but higher up (a hover)
    (0.1, 0.0, "BRAKE", Mode.LAND),                   # the autopilot is not landing
    (0.1, 0.0, "LAND", Mode.HOLD)])                   # the requester is not landing
def test_no_disarm_unless_landing_low_and_still(alt_rel_m, down_mps, ap_mode, mode):
    loop, vehicle = _loop(mode)
    _fly(loop, [_state(alt_rel_m, down_mps, ap_mode)] * int(3 * LANDED_FOR_S / 0.2))
    assert vehicle.disarms == []


def test_a_descent_resumed_restarts_the_count():
    loop, vehicle = _loop()
    half = int(round(0.6 * LANDED_FOR_S / 0.2))
    _fly(loop, [_state(0.3, 0.0)] * half + [_state(0.3, 0.4)] + [_state(0.3, 0.0)] * half)
    assert vehicle.disarms == []
