"""Serial links (pyserial under pymavlink): ``/dev/...:BAUD`` URLs reach an autopilot on a
pseudo-terminal, both ways (HEARTBEAT in, COMMAND_LONG out, COMMAND_ACK in)."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest

from skyfix.drivers.mav import mavlink as M
from skyfix.drivers.vehicle import Vehicle

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pseudo-terminals: Linux")


def test_serial_url_reaches_an_autopilot_on_a_pty():
    import tty

    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    ap = M.MAVLink(None, srcSystem=7, srcComponent=1)
    parser = M.MAVLink(None)
    stop = threading.Event()
    commands: list[int] = []

    def autopilot() -> None:  # heartbeats at 10 Hz; ACKs every COMMAND_LONG addressed to it
        next_hb = 0.0
        os.set_blocking(master, False)
        while not stop.is_set():
            if time.monotonic() >= next_hb:
                next_hb = time.monotonic() + 0.1
                os.write(master, ap.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                     M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 3, 3).pack(ap))
            try:
                data = os.read(master, 4096)
            except BlockingIOError:
                time.sleep(0.005)
                continue
            for msg in parser.parse_buffer(data) or []:
                if msg.get_type() == "COMMAND_LONG" and msg.target_system == 7:
                    commands.append(msg.command)
                    os.write(master, ap.command_ack_encode(msg.command, M.MAV_RESULT_ACCEPTED, 0, 0,
                                                           msg.get_srcSystem(), msg.get_srcComponent()).pack(ap))

    worker = threading.Thread(target=autopilot, daemon=True)
    worker.start()
    try:
        with Vehicle.connect(f"{os.ttyname(slave)}:57600", timeout_s=5.0) as v:
            assert v.system_id == 7
            assert v.wait_until(lambda s: s.mode == "GUIDED", 2.0).mode == "GUIDED"
            assert v.command(M.MAV_CMD_DO_SET_HOME, 1) == M.MAV_RESULT_ACCEPTED
        assert M.MAV_CMD_DO_SET_HOME in commands
    finally:
        stop.set()
        worker.join(2.0)
        os.close(master)
        os.close(slave)
