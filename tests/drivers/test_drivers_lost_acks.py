"""Commands whose every COMMAND_ACK is lost, over a real UDP link.

On a lossy radio an ACK can be lost on every attempt while the command itself got through
(15 % loss each way: a round trip fails 28 % of the time, four in a row 0.6 %; a loaded suite
saw takeoff time out that way). Arm, mode changes and takeoff are then confirmed by what the
autopilot reports next: the heartbeat's armed flag and mode, EXTENDED_SYS_STATE's landed state.
A relay between the vehicle and the simulator forwards every datagram except COMMAND_ACK.
"""

from __future__ import annotations

import socket
import threading

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers.mav import mavlink
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import SkyfixTimeout


class AckEater:
    """UDP relay: the vehicle side at ``port``, the simulator at ``target``; COMMAND_ACK never gets back."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        for s in (self.front, self.back):
            s.settimeout(0.1)
        self.port = self.front.getsockname()[1]
        self.client: tuple[str, int] | None = None
        self.eaten = 0
        self.stop = threading.Event()
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self.threads = [threading.Thread(target=self._pump, args=(up,), daemon=True) for up in (True, False)]
        for t in self.threads:
            t.start()

    def _pump(self, up: bool) -> None:
        src = self.front if up else self.back
        while not self.stop.is_set():
            try:
                data, addr = src.recvfrom(65536)
            except (TimeoutError, OSError):
                continue
            if up:
                self.client = addr
                self.back.sendto(data, self.target)
                continue
            msgs = self._parser.parse_buffer(data) or []
            if any(m.get_type() == "COMMAND_ACK" for m in msgs):
                self.eaten += 1
                continue
            if self.client is not None:
                self.front.sendto(data, self.client)

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(2.0)
        self.front.close()
        self.back.close()


@pytest.fixture
def relayed():
    with Simulator(SimulatorConfig(vehicles=1, speed=2.0, seed=3)) as sim:
        relay = AckEater(sim.addresses[0])
        v = Vehicle.connect(f"udpout:127.0.0.1:{relay.port}", timeout_s=5.0)
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
    assert relay.eaten >= 3  # every one of the three commands was answered, and every answer eaten


def test_a_command_nothing_confirms_still_times_out(relayed):
    _, v, relay = relayed
    # a parameter-free request with no state to show for it: without its ACK there is no proof
    with pytest.raises(SkyfixTimeout):
        v.command(mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1, timeout_s=0.3, retries=1)
    assert relay.eaten >= 1
