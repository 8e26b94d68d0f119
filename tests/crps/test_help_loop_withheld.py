"""HelpLoop._command_mode while the service withholds the injected position: the requester's autopilot is sent
to LAND, not back to the hold or return the help roles want (its own position is dead reckoning then; on SITL,
BRAKE commanded over ArduPilot's briefly cleared EKF failsafe flew a wound-up position controller on for 12 s).
"""

import math
from types import SimpleNamespace

import pytest

from skyfix.crps.help_loop import HelpLoop
from skyfix.drivers.state import VehicleState


class _Actions:
    busy = False

    def submit(self, kind, what, fn) -> None:
        fn()


def _loop(withheld: bool, autopilot_mode: str) -> tuple[SimpleNamespace, list[str], VehicleState]:
    sent: list[str] = []
    vehicle = SimpleNamespace(set_mode=sent.append, autopilot="ardupilot")
    svc = SimpleNamespace(vehicle=vehicle, injection_withheld=withheld)
    loop = SimpleNamespace(svc=svc, id="d2", _want="BRAKE", _want_sent_wall_s=-math.inf, _actions=_Actions(),
                           recovering=True)
    loop._land_mode = lambda: "LAND"
    return loop, sent, VehicleState(1, autopilot="ardupilot", mode=autopilot_mode, link_ok=True)


@pytest.mark.parametrize("withheld, autopilot_mode, expected", [
    (False, "AUTO", ["BRAKE"]),   # GNSS lost, injecting: hold
    (True, "AUTO", ["LAND"]),     # nothing injected on purpose: land
    (True, "LAND", []),           # already landing (e.g. ArduPilot's own EKF failsafe): left alone
    (True, "BRAKE", ["LAND"]),    # holding when the injection is withheld: land now
])
def test_a_withheld_injection_lands_the_requester(withheld, autopilot_mode, expected):
    loop, sent, state = _loop(withheld, autopilot_mode)
    HelpLoop._command_mode(loop, state)
    assert sent == expected
