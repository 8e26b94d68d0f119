"""``skyfix sim`` prints its ports, serves ground stations and stops cleanly on Ctrl-C;
``skyfix vehicle status|params|mission`` talk to it."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

from skyfix.cli import main


def test_sim_cli_serves_and_stops_on_ctrl_c(udp_port, capsys):
    proc = subprocess.Popen([sys.executable, "-m", "skyfix", "-q", "sim", "--vehicles", "2",
                             "--base-port", str(udp_port), "--speed", "2", "--param", "GPS2_TYPE=14",
                             "--gps-fault", "1:loss:0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline() for _ in range(4)]
        assert f"connect udpin:127.0.0.1:{udp_port}" in lines[1]
        assert f"connect udpin:127.0.0.1:{udp_port + 1}" in lines[2]
        assert main(["-q", "vehicle", "status", f"udpin:127.0.0.1:{udp_port + 1}", "--json",
                     "--timeout", "5"]) == 0
        state = json.loads(capsys.readouterr().out)
        assert state["system_id"] == 2 and state["autopilot"] == "ardupilot" and state["link_ok"]
        assert abs(state["position"]["lat_deg"] + 35.363) < 0.01  # SITL's default site
        assert main(["-q", "vehicle", "params", f"udpin:127.0.0.1:{udp_port}", "GPS2_TYPE"]) == 0
        assert capsys.readouterr().out.strip() == "GPS2_TYPE 14"
        # vehicle 1 has lost GPS from the start (--gps-fault 1:loss:0), vehicle 2 has not
        assert main(["-q", "vehicle", "status", f"udpin:127.0.0.1:{udp_port}", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["gps"]["fix_type"] <= 1
        assert state["gps"]["fix_type"] == 3
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sim_cli_rejects_bad_fault(capsys):
    assert main(["-q", "sim", "--gps-fault", "9:loss:0", "--duration", "0.1"]) == 1
    assert main(["-q", "sim", "--gps-fault", "1:meteor:0", "--duration", "0.1"]) == 1


def test_vehicle_cli_unreachable_exits_1(udp_port, capsys):
    assert main(["-q", "vehicle", "status", f"udpout:127.0.0.1:{udp_port}", "--timeout", "0.5"]) == 1
