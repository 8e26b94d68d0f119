"""MAVLink driver benchmark: skyfix's simulator and the real ArduPilot Copter SITL firmware.

Measures, with a plain pymavlink client as the peer where one exists:
  1. command round trip (COMMAND_LONG -> COMMAND_ACK), median and p95 (goal: median <= 20 ms),
     on the simulator and on ArduPilot SITL at speed-up 1 (TCP);
  2. 500-item mission upload time (goal: <= 2 s) on both, and on the simulator completion
     with 10 % packet loss injected in both directions; on SITL both the item protocol
     (bound by the firmware's scheduler: ~5.8 ms per item) and one file over MAVLink FTP
     (ArduPilot's @MISSION/mission.dat, read back and compared), the goal judged on FTP;
  3. safety-violation latency on the simulator (run in its own process): from it sending the first telemetry message
     outside the fence to it receiving the driver's mode change (goal: <= 50 ms, worst case);
  4. ArduPilot SITL: the simulated receiver switched off (SIM_GPS1_ENABLE 0) -> skyfix's
     GnssFix flags no fix (goal: <= 1 s, worst case).

The SITL column is skipped (said so) where ../shared/sitl / $SKYFIX_SITL_DIR is absent.
``--soak N`` runs two copies of the quick benchmark at once, N times in a row, and fails
if any copy fails (the loaded-machine check). Wall-clock times (perf_counter / monotonic)
on a shared 2-core machine. Exit 1 when a goal is missed. The last line is the headline.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

os.environ.setdefault("MAVLINK20", "1")

import numpy as np
from pymavlink import mavutil

from skyfix.datasets import sitl
from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers import mission_ftp
from skyfix.drivers.mav import mavlink
from skyfix.drivers.mission import MissionItem
from skyfix.drivers.safety import Geofence, SafetyGate
from skyfix.drivers.vehicle import Vehicle

M = mavlink


def _pct(values, q):
    return float(np.percentile(np.asarray(values), q))


def _command_round_trips(v: Vehicle, n: int) -> list[float]:
    args = (M.MAVLINK_MSG_ID_ATTITUDE, 100_000)
    for _ in range(10):
        v.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, *args)
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        v.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, *args)
        out.append(time.perf_counter() - t0)
    return out


def _peer_round_trips(url: str, n: int, target_system: int = 1) -> list[float]:
    """A plain pymavlink send + recv_match loop."""
    master = mavutil.mavlink_connection(url, source_system=254)
    master.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    master.wait_heartbeat(timeout=10)
    args = (M.MAVLINK_MSG_ID_ATTITUDE, 100_000)
    peer = []
    for i in range(n + 10):
        t0 = time.perf_counter()
        master.mav.command_long_send(target_system, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0, *args, 0, 0, 0, 0, 0)
        ack = master.recv_match(type="COMMAND_ACK", blocking=True, timeout=1.0)
        if ack is not None and i >= 10:
            peer.append(time.perf_counter() - t0)
    master.close()
    return peer


def round_trip(n: int) -> tuple[list[float], list[float]]:
    """skyfix Vehicle.command vs a plain pymavlink loop, same simulator (speed 1)."""
    with Simulator(SimulatorConfig(vehicles=1, speed=1.0)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        ours = _command_round_trips(v, n)
        v.close()
        peer = _peer_round_trips(sim.url(0), n)
    return ours, peer


def _items(lat0: float, lon0: float, n: int) -> list[MissionItem]:
    return [MissionItem.waypoint(lat0 + 1e-5 * (i % 25), lon0 + 1e-5 * (i // 25), 10.0 + i % 5)
            for i in range(n)]


def mission_upload(n: int, loss: float, runs: int) -> list[tuple[float, int]]:
    """(seconds, retransmissions) per skyfix upload of ``n`` items."""
    out = []
    with Simulator(SimulatorConfig(vehicles=1, speed=1.0, loss_rate=loss, seed=11)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        home = v.wait_until(lambda s: s.home is not None, 5.0).home
        items = _items(home.lat_deg, home.lon_deg, n)
        for _ in range(runs):
            stats = v.upload_mission(items, item_timeout_s=0.02 if loss else 0.25)
            assert len(sim.vehicle(0).mission) == n + 1, "simulator did not store the whole mission"
            out.append((stats.elapsed_s, stats.retransmissions))
        v.close()
    return out


def _peer_upload(url: str, lat0: float, lon0: float, n: int, runs: int) -> list[float]:
    """A plain pymavlink upload loop (answer each MISSION_REQUEST(_INT) at once), seconds per run."""
    out = []
    master = mavutil.mavlink_connection(url, source_system=254)
    master.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    master.wait_heartbeat(timeout=10)
    target = master.target_system
    wire = [MissionItem.waypoint(lat0, lon0, 0.0)] + _items(lat0, lon0, n)
    for _ in range(runs):
        t0 = time.perf_counter()
        master.mav.mission_count_send(target, 1, len(wire), 0)
        while True:
            m = master.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"],
                                  blocking=True, timeout=2)
            if m is None or m.get_type() == "MISSION_ACK":
                break
            master.mav.send(wire[m.seq].to_message(m.seq, target, 1))
        out.append(time.perf_counter() - t0)
    master.close()
    return out


def _peer_ftp_upload(url: str, data: bytes, runs: int) -> list[float]:
    """pymavlink's own MAVFTP client (what MAVProxy's ``wp ftpload`` uses) writing the same
    ``@MISSION/mission.dat`` on its own connection, seconds per run (no read-back)."""
    import io

    from pymavlink import mavftp

    master = mavutil.mavlink_connection(url, source_system=254)
    master.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    master.wait_heartbeat(timeout=10)
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        ftp = mavftp.MAVFTP(master, master.target_system, 1)
        ftp.cmd_put(["mission", mission_ftp.MISSION_FILE], fh=io.BytesIO(data))
        if ftp.process_ftp_reply("put", timeout=10).error_code != 0:
            raise RuntimeError("pymavlink MAVFTP upload failed")
        out.append(time.perf_counter() - t0)
    master.close()
    return out


def mission_upload_peer(n: int, runs: int) -> list[float]:
    """The plain pymavlink upload against the simulator, for comparison."""
    with Simulator(SimulatorConfig(vehicles=1, speed=1.0)) as sim:
        t = sim.truth(0)
        return _peer_upload(sim.url(0), t["lat_deg"], t["lon_deg"], n, runs)


def _sim_process(conn, speed: float) -> None:
    """The simulator in its own process, as an autopilot is its own computer: the driver's
    latency is then not the simulator's share of one interpreter. Answers 'log' requests
    with its (monotonic time, kind, payload) log; CLOCK_MONOTONIC is shared by processes."""
    with Simulator(SimulatorConfig(vehicles=1, speed=speed)) as sim:
        conn.send(sim.url(0))
        while conn.recv() == "log":
            conn.send(list(sim.servers[0].log))


def violation_latency(trials: int) -> tuple[list[float], list[float]]:
    """(sim-side end-to-end latencies, driver-internal latencies) in seconds."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe()
    proc = ctx.Process(target=_sim_process, args=(there, 5.0), daemon=True)
    proc.start()
    end_to_end: list[float] = []
    try:
        v = Vehicle.connect(here.recv(), timeout_s=10.0)
        home = v.wait_until(lambda s: s.home is not None, 10.0).home
        v.set_mode("GUIDED")
        v.arm()
        v.takeoff(10.0)
        max_alt = 12.0
        v.set_safety(SafetyGate(Geofence.circle(home.lat_deg, home.lon_deg, 200.0, max_alt_rel_m=max_alt),
                                action="hold"))
        for _ in range(trials):
            v.goto(home.lat_deg, home.lon_deg, 10.0, wait=True, tolerance_m=0.5, timeout_s=30.0)
            t_start = time.monotonic()
            v.velocity(0.0, 0.0, -1.5)
            v.wait_until(lambda s: s.mode == "LOITER", 20.0, what="hold after the altitude breach")
            here.send("log")
            entries = [e for e in here.recv() if e[0] >= t_start]
            t_tel = next(t for t, kind, data in entries if kind == "position" and data[2] > max_alt)
            t_cmd = next(t for t, kind, data in entries if kind == "mode_request" and data[0] == "LOITER"
                         and t >= t_tel)
            end_to_end.append(t_cmd - t_tel)
        internal = [lat for lat, _ in v.safety_log]
        v.rtl()
        v.close()
    finally:
        here.send("stop")
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
    return end_to_end, internal


def sitl_column(n_rt: int, runs: int, trials: int) -> dict[str, list[float]] | None:
    """The same measurements on ArduPilot Copter SITL at speed-up 1 (None when it is absent):
    round trips (skyfix on SERIAL0, plain pymavlink on SERIAL1), 500-item uploads, and the
    receiver switched off -> skyfix's GnssFix shows no fix."""
    reason = sitl.missing_reason()
    if reason:
        print(f"ArduPilot SITL column skipped: {reason}")
        return None
    out: dict[str, list[float]] = {}
    with sitl.SitlFleet(1, speedup=1.0) as fleet:
        inst = fleet[0]
        v = Vehicle.connect(inst.url, timeout_s=30.0)
        try:
            # measured once the firmware has settled (its first ~20 s after boot are busy)
            v.wait_until(lambda s: s.gps is not None and s.gps.fix_type >= 3 and s.home is not None, 90.0,
                         what="GPS fix and home")
            out["rt"] = _command_round_trips(v, n_rt)
            out["rt_peer"] = _peer_round_trips(inst.url_secondary, n_rt)
            lat0, lon0 = fleet.homes[0][:2]
            items = _items(lat0, lon0, 500)
            out["upload"] = []
            for _ in range(runs):
                out["upload"].append(v.upload_mission(items).elapsed_s)
            assert len(v.download_mission()) == 500, "ArduPilot did not store the whole mission"
            out["upload_peer"] = _peer_upload(inst.url_secondary, lat0, lon0, 500, runs)
            out["upload_ftp"] = [v.upload_mission(items, ftp=True).elapsed_s for _ in range(runs)]
            back = v.download_mission()  # the item protocol reads what the FTP upload stored
            assert len(back) == 500 and all(abs(a.lat_deg - b.lat_deg) < 2e-7 and a.alt_m == b.alt_m
                                            for a, b in zip(items, back, strict=True)), "FTP upload not stored as sent"
            out["upload_ftp_peer"] = _peer_ftp_upload(inst.url_secondary, mission_ftp.mission_file(v, items),
                                                      runs)
            out["gps_off"] = []
            for _ in range(trials):
                t0 = time.monotonic()
                v.set_param("SIM_GPS1_ENABLE", 0)
                v.wait_until(lambda s: s.gps.fix_type <= 1, 10.0, what="receiver off flagged")
                out["gps_off"].append(time.monotonic() - t0)
                v.set_param("SIM_GPS1_ENABLE", 1)
                v.wait_until(lambda s: s.gps.fix_type >= 3, 30.0, what="fix back")
        finally:
            v.close()
    return out


def _report_sitl(col: dict[str, list[float]] | None) -> tuple[bool, str]:
    if col is None:
        return True, "ArduPilot SITL: skipped"
    med, p95 = statistics.median(col["rt"]) * 1e3, _pct(col["rt"], 95) * 1e3
    pmed = statistics.median(col["rt_peer"]) * 1e3
    print(f"ArduPilot SITL (speed-up 1, TCP) command round trip (n={len(col['rt'])}): skyfix median "
          f"{med:.2f} ms, p95 {p95:.2f} ms; plain pymavlink median {pmed:.2f} ms; ratio {med / pmed:.2f}")
    print(f"  goal median <= 20 ms: {'met' if med <= 20.0 else 'NOT met'}")
    item = statistics.median(col["upload"])
    pitem = statistics.median(col["upload_peer"])
    print(f"ArduPilot SITL mission upload, 500 items, item protocol ({len(col['upload'])} runs): skyfix median "
          f"{item:.3f} s, max {max(col['upload']):.3f} s (downloaded back: 500 items); plain pymavlink loop "
          f"{pitem:.3f} s; ratio {item / pitem:.2f} (bound by the firmware: one request per item, "
          f"answered on its next 400 Hz scheduler ticks)")
    up = statistics.median(col["upload_ftp"])
    pup = statistics.median(col["upload_ftp_peer"])
    print(f"ArduPilot SITL mission upload, 500 items, one file over MAVLink FTP (@MISSION/mission.dat, "
          f"{len(col['upload_ftp'])} runs): skyfix median {up:.3f} s incl. read-back check, max "
          f"{max(col['upload_ftp']):.3f} s (downloaded back with the item protocol: equal); pymavlink's "
          f"MAVFTP put (MAVProxy's wp ftpload) {pup:.3f} s without read-back; ratio {up / pup:.2f}")
    print(f"  goal <= 2 s (FTP upload): {'met' if up <= 2.0 else 'NOT met'}; item protocol alone: "
          f"{'met' if item <= 2.0 else 'not met'}")
    off = max(col["gps_off"])
    print(f"ArduPilot SITL receiver off (SIM_GPS1_ENABLE 0) -> flagged by skyfix ({len(col['gps_off'])} "
          f"trials): median {statistics.median(col['gps_off']) * 1e3:.0f} ms, max {off * 1e3:.0f} ms "
          f"(GPS_RAW_INT at 5 Hz)")
    print(f"  goal <= 1 s: {'met' if off <= 1.0 else 'NOT met'}")
    ok = med <= 20.0 and up <= 2.0 and off <= 1.0
    return ok, (f"ArduPilot SITL round trip {med:.2f} ms / 500-item upload {up:.2f} s over FTP ({item:.2f} s item "
                f"protocol) / GPS off flagged {off * 1e3:.0f} ms")


def soak(rounds: int) -> int:
    """Two copies of ``--quick`` at once, ``rounds`` times: the loaded-machine check."""
    failures = 0
    for r in range(rounds):
        procs = [subprocess.Popen([sys.executable, __file__, "--quick"], stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True) for _ in range(2)]
        for i, p in enumerate(procs):
            text, _ = p.communicate()
            lines = text.strip().splitlines()
            print(f"round {r + 1} copy {i + 1}: exit {p.returncode}: {lines[-1] if lines else '(no output)'}")
            failures += p.returncode != 0
        sys.stdout.flush()
    print(f"HEADLINE: soak {rounds} rounds x 2 concurrent copies: {2 * rounds - failures}/{2 * rounds} "
          f"passed: {'all goals met' if not failures else 'GOAL MISSED'}")
    return 0 if not failures else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    ap.add_argument("--soak", type=int, metavar="N", default=0,
                    help="run two --quick copies at once, N times in a row (the loaded-machine check)")
    ap.add_argument("--no-sitl", action="store_true", help="skip the ArduPilot SITL column")
    args = ap.parse_args(argv)
    if args.soak:
        return soak(args.soak)
    n_rt, runs, trials = (100, 2, 8) if args.quick else (300, 5, 20)
    ok = True

    ours, peer = round_trip(n_rt)
    med, p95 = statistics.median(ours) * 1e3, _pct(ours, 95) * 1e3
    pmed = statistics.median(peer) * 1e3
    print(f"command round trip (n={n_rt}): skyfix median {med:.2f} ms, p95 {p95:.2f} ms; "
          f"plain pymavlink median {pmed:.2f} ms; ratio skyfix/pymavlink {med / pmed:.2f}")
    ok &= med <= 20.0
    print(f"  goal median <= 20 ms: {'met' if med <= 20.0 else 'NOT met'}")

    up = mission_upload(500, 0.0, runs)
    up_s = statistics.median(t for t, _ in up)
    peer_s = statistics.median(mission_upload_peer(500, runs))
    print(f"mission upload, 500 items, no loss ({runs} runs): skyfix median {up_s:.3f} s; "
          f"plain pymavlink loop {peer_s:.3f} s; ratio {up_s / peer_s:.2f}")
    ok &= up_s <= 2.0
    print(f"  goal <= 2 s: {'met' if up_s <= 2.0 else 'NOT met'}")
    lossy = mission_upload(500, 0.10, runs)
    lossy_s = statistics.median(t for t, _ in lossy)
    resent = statistics.median(r for _, r in lossy)
    print(f"mission upload, 500 items, 10 % loss each way ({runs} runs): all completed, median "
          f"{lossy_s:.3f} s, median {resent:.0f} packets resent by skyfix "
          f"(skyfix item timeout 20 ms; the simulated ArduPilot re-requests after 1 s)")
    print(f"  goal completes with 10 % loss: met ({len(lossy)}/{runs}); also <= 2 s: "
          f"{'yes' if lossy_s <= 2.0 else 'no'}")

    e2e, internal = violation_latency(trials)
    e_med, e_max = statistics.median(e2e) * 1e3, max(e2e) * 1e3
    i_med, i_max = statistics.median(internal) * 1e3, max(internal) * 1e3
    print(f"violation -> action ({trials} altitude-fence breaches, simulator in its own process): telemetry "
          f"sent -> mode change received "
          f"by the autopilot median {e_med:.2f} ms, max {e_max:.2f} ms; driver receipt -> action sent "
          f"median {i_med:.3f} ms, max {i_max:.3f} ms")
    ok &= e_max <= 50.0
    print(f"  goal <= 50 ms: {'met' if e_max <= 50.0 else 'NOT met'}")
    sitl_ok, sitl_head = _report_sitl(None if args.no_sitl else sitl_column(n_rt, runs, 3 if args.quick else 5))
    ok &= sitl_ok
    print(f"HEADLINE: sim round trip median {med:.2f} ms (<= 20), 500-item upload {up_s:.2f} s (<= 2) / "
          f"{lossy_s:.2f} s at 10 % loss, violation->action max {e_max:.1f} ms (<= 50); {sitl_head}: "
          f"{'all goals met' if ok else 'GOAL MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
