"""``skyfix sim`` prints its ports, serves ground stations and stops cleanly on Ctrl-C;
``skyfix vehicle status|arm|takeoff|goto|rtl|mission|param`` fly and inspect it."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time

import pytest

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
        assert main(["-q", "vehicle", "param", "get", f"udpin:127.0.0.1:{udp_port}", "GPS2_TYPE"]) == 0
        assert capsys.readouterr().out.strip() == "GPS2_TYPE 14"
        # vehicle 1 has lost GPS from the start (--gps-fault 1:loss:0), vehicle 2 has not
        assert main(["-q", "vehicle", "status", f"udpin:127.0.0.1:{udp_port}", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["gps"]["fix_type"] <= 1
        assert state["gps"]["fix_type"] == 3
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        # what is asserted is a clean stop (exit 0), not its speed: 1-2 s here under six busy
        # processes, but once > 10 s in a suite run at load 7
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_sim_cli_stops_on_a_signal_even_when_started_with_sigint_ignored(udp_port, signum):
    """A simulator a script starts in the background inherits SIGINT ignored (no KeyboardInterrupt in Python):
    it still stops cleanly on SIGINT or SIGTERM (it waited 60 s and was killed before)."""
    proc = subprocess.Popen([sys.executable, "-m", "skyfix", "-q", "sim", "--base-port", str(udp_port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        assert [proc.stdout.readline() for _ in range(3)][-1].startswith("Ctrl-C to stop")
        time.sleep(0.3)
        proc.send_signal(signum)
        assert proc.wait(timeout=30) == 0
        assert "stopping" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sim_cli_rejects_bad_fault(capsys):
    assert main(["-q", "sim", "--gps-fault", "9:loss:0", "--duration", "0.1"]) == 2
    assert main(["-q", "sim", "--gps-fault", "1:meteor:0", "--duration", "0.1"]) == 2


@pytest.mark.parametrize(("args", "named"), [
    (["--param", "NOT_A_PARAM=3"], "NOT_A_PARAM"),
    (["--param", "GPS1_TYPE=1", "--param", "gps1_type=14"], "--param GPS1_TYPE is given twice"),
    (["--param", "GPS1_TYPE"], "--param must be NAME=VALUE"),
    (["--duration", "-3"], "--duration"),
    (["--duration", "nan"], "--duration"),
    (["--flavour", "px4", "--param", "GPS1_TYPE=14"], "unknown px4 parameter(s) GPS1_TYPE"),
])
def test_sim_cli_bad_arguments_are_one_line_errors(args, named):
    out = subprocess.run([sys.executable, "-m", "skyfix", "sim", *args], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("skyfix sim: error:") and named in lines[0]
    assert "Traceback" not in out.stderr and out.stdout == ""


def test_sim_keeps_sending_to_a_silent_udpin_ground_station(udp_port):
    """ArduPilot's udpclient output sends to the configured address whether or not anything
    answers; the simulator once stopped 10 s after the ground station's last packet."""
    import socket

    from skyfix.datasets.sim import Simulator, SimulatorConfig

    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", udp_port))
    gcs.settimeout(2.0)
    try:
        with Simulator(SimulatorConfig(vehicles=1, base_port=udp_port)) as sim:
            data, addr = gcs.recvfrom(4096)
            gcs.sendto(data, addr)  # the ground station speaks once (any MAVLink will do)...
            server, me = sim.servers[0], ("127.0.0.1", udp_port)
            deadline = time.monotonic() + 5.0
            while me not in server.peers and time.monotonic() < deadline:
                time.sleep(0.01)
            server.peers[me] -= 11.0  # ...and has been silent for 11 s since
            while True:  # drain what was sent before
                gcs.settimeout(0.05)
                try:
                    gcs.recvfrom(4096)
                except TimeoutError:
                    break
            gcs.settimeout(2.0)
            assert gcs.recvfrom(4096)[0]  # telemetry still arrives
    finally:
        gcs.close()


def test_vehicle_cli_unreachable_exits_1(udp_port, capsys):
    assert main(["-q", "vehicle", "status", f"udpout:127.0.0.1:{udp_port}", "--timeout", "0.5"]) == 1


def test_vehicle_cli_flies_a_mission_and_reports_refusals(tmp_path, capsys, caplog):
    from skyfix.datasets.sim import Simulator, SimulatorConfig
    from skyfix.drivers.mission import MissionItem

    with Simulator(SimulatorConfig(vehicles=1, speed=5.0, seed=12)) as sim:
        url = sim.url(0)
        assert main(["-q", "vehicle", "status", url]) == 0
        out = capsys.readouterr().out
        assert "h_acc 0.80 m" in out and "HDOP 1.20" in out and "home " in out
        # a refusal carries the autopilot's reason
        assert main(["-q", "vehicle", "disarm", url]) == 0
        assert main(["-q", "vehicle", "takeoff", url, "8"]) == 0
        assert abs(sim.truth(0)["alt_rel_m"] - 8.0) < 1.0
        assert main(["vehicle", "disarm", url]) == 1
        assert "Disarm: vehicle is flying" in caplog.text  # the one-line error skyfix logs
        t = sim.truth(0)
        lat, lon = t["lat_deg"] + 1.5e-4, t["lon_deg"]
        assert main(["-q", "vehicle", "goto", url, str(lat), str(lon), "10"]) == 0
        t = sim.truth(0)
        assert math.hypot((t["lat_deg"] - lat) * 111_320, (t["lon_deg"] - lon) * 78_000) < 2.0
        plan = tmp_path / "mission.json"
        items = [MissionItem.waypoint(lat + 1e-4 * i, lon, 10.0 + i) for i in range(4)]
        plan.write_text(json.dumps({"items": [dict(vars(it)) for it in items]}))
        assert main(["-q", "vehicle", "mission", "upload", url, str(plan)]) == 0
        assert "uploaded 4 items" in capsys.readouterr().out
        back = tmp_path / "back.json"
        assert main(["-q", "vehicle", "mission", "download", url, "-o", str(back)]) == 0
        assert [it["lat_deg"] for it in json.loads(back.read_text())["items"]] == \
            pytest.approx([it.lat_deg for it in items], abs=1e-7)
        assert main(["-q", "vehicle", "param", "set", url, "RTL_ALT", "2000"]) == 0
        assert capsys.readouterr().out.strip() == "RTL_ALT 2000"
        assert main(["-q", "vehicle", "rtl", url, "--wait"]) == 0
        assert not sim.vehicle(0).armed and sim.truth(0)["alt_rel_m"] < 0.5
        assert main(["-q", "vehicle", "mission", "upload", url, str(tmp_path / "missing.json")]) == 2  # bad input: exit 2


def test_vehicle_cli_ftp_upload_refused_on_px4(tmp_path, caplog):
    """`mission upload --ftp` is ArduPilot's @MISSION/mission.dat: refused up front on PX4,
    in one line naming the reason (the SITL test uploads over FTP for real)."""
    from skyfix.datasets.sim import Simulator, SimulatorConfig

    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"items": [{"command": 16, "lat_deg": 47.0, "lon_deg": 8.0, "alt_m": 10.0}]}))
    with Simulator(SimulatorConfig(vehicles=1, flavour="px4", speed=2.0)) as sim:
        assert main(["vehicle", "mission", "upload", sim.url(0), str(plan), "--ftp"]) == 1
    assert "needs ArduPilot" in caplog.text


@pytest.mark.parametrize(("args", "named"), [
    (["takeoff", "udpin:127.0.0.1:14599", "-5"], "ALT_M"),
    (["goto", "udpin:127.0.0.1:14599", "95", "6", "10"], "LAT_DEG"),
    (["goto", "udpin:127.0.0.1:14599", "46", "190", "10"], "LON_DEG"),
    (["status", "udpin:127.0.0.1:14599", "--timeout", "-1"], "--timeout"),
    (["status", "udpin:127.0.0.1:14599", "--wait", "0"], "--wait"),
    (["arm", "udpin:127.0.0.1:14599", "--system-id", "300"], "--system-id"),
    (["mission", "upload", "udpin:127.0.0.1:14599", "/nonexistent/plan.json"], "no such mission file"),
])
def test_vehicle_cli_bad_arguments_fail_at_once(args, named, monkeypatch):
    """Bad numbers are refused before any connection (no 10 s wait for a vehicle), in one
    line naming the argument, exit 2."""
    def no_connect(*_a, **_k):
        raise AssertionError("the CLI tried to connect before checking its arguments")

    # in-process: "before any connection" is checked by connecting being an error, not by a
    # wall-clock bound (a loaded machine starts Python in more than 8 s)
    monkeypatch.setattr("skyfix.drivers.vehicle.Vehicle.connect", no_connect)
    assert main(["-q", "vehicle", *args]) == 2
    out = subprocess.run([sys.executable, "-m", "skyfix", "vehicle", *args], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and named in lines[0] and "Traceback" not in out.stderr
