"""Commands whose every COMMAND_ACK is lost, over a real UDP link.

On a lossy radio an ACK can be lost on every attempt while the command itself got through
(15 % loss each way: a round trip fails 28 % of the time, four in a row 0.6 %; a loaded suite
saw takeoff time out that way). Arm, mode changes and takeoff are then confirmed by what the
autopilot reports next: the heartbeat's armed flag and mode, EXTENDED_SYS_STATE's landed state.
A relay between the vehicle and the simulator forwards every datagram except COMMAND_ACK.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.datasets.sim.relay import UdpRelay
from skyfix.drivers.mav import mavlink
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import SkyfixTimeout


def _acks_dropped() -> Callable[[bytes], bool]:
    """A relay filter: True for a datagram carrying a COMMAND_ACK (the simulator sends one message a datagram)."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return lambda data: any(m.get_type() == "COMMAND_ACK" for m in parser.parse_buffer(data) or [])


@pytest.fixture
def relayed():
    with Simulator(SimulatorConfig(vehicles=1, speed=2.0, seed=3)) as sim:
        relay = UdpRelay(sim.addresses[0], drop_from_vehicle=_acks_dropped())
        v = Vehicle.connect(relay.url, timeout_s=5.0)
        try:
            v.wait_until(lambda s: s.position is not None and s.home is not None, 10.0, what="telemetry")
            yield sim, v, relay
        finally:
            v.close()
            relay.close()


def test_arm_mode_and_takeoff_confirmed_without_any_ack(relayed):
    _, v, relay = relayed
    v.set_mode("GUIDED")
    v.arm()
    v.takeoff(5.0, timeout_s=30.0)
    assert v.state.armed and v.state.mode == "GUIDED"
    assert v.state.position.alt_rel_m >= 4.5
    assert relay.dropped >= 3  # every one of the three commands was answered, and every answer eaten


def test_a_command_nothing_confirms_still_times_out(relayed):
    _, v, relay = relayed
    # a parameter-free request with no state to show for it: without its ACK there is no proof
    with pytest.raises(SkyfixTimeout):
        v.command(mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1, timeout_s=0.3, retries=1)
    assert relay.dropped >= 1
