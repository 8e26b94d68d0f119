"""MAVLink driver benchmark against the built-in simulator on loopback.

Measures, with a plain pymavlink client as the peer where one exists:
  1. command round trip (COMMAND_LONG -> COMMAND_ACK), median and p95 (goal: median <= 20 ms);
  2. 500-item mission upload time (goal: <= 2 s), and completion with 10 % packet loss
     injected in both directions;
  3. safety-violation latency: from the simulator sending the first telemetry message that
     is outside the fence to it receiving the driver's mode change (goal: <= 50 ms, worst case),
     plus the driver-internal time from receipt to action sent.

Wall-clock times (time.perf_counter / monotonic) on a shared 2-core machine. Exit 1 when a
goal is missed. The last line is the headline.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("MAVLINK20", "1")

import numpy as np
from pymavlink import mavutil

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers.mav import mavlink
from skyfix.drivers.mission import MissionItem
from skyfix.drivers.safety import Geofence, SafetyGate
from skyfix.drivers.vehicle import Vehicle

M = mavlink


def _pct(values, q):
    return float(np.percentile(np.asarray(values), q))


def round_trip(n: int) -> tuple[list[float], list[float]]:
    """skyfix Vehicle.command vs a plain pymavlink send + recv_match loop, same simulator."""
    with Simulator(SimulatorConfig(vehicles=1, speed=1.0)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        args = (M.MAVLINK_MSG_ID_ATTITUDE, 100_000)
        for _ in range(10):
            v.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, *args)
        ours = []
        for _ in range(n):
            t0 = time.perf_counter()
            v.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, *args)
            ours.append(time.perf_counter() - t0)
        v.close()
        master = mavutil.mavlink_connection(sim.url(0), source_system=254)
        master.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        master.wait_heartbeat(timeout=5)
        peer = []
        for i in range(n + 10):
            t0 = time.perf_counter()
            master.mav.command_long_send(1, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0, *args, 0, 0, 0, 0, 0)
            ack = master.recv_match(type="COMMAND_ACK", blocking=True, timeout=1.0)
            if ack is not None and i >= 10:
                peer.append(time.perf_counter() - t0)
        master.close()
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


def mission_upload_peer(n: int, runs: int) -> list[float]:
    """A plain pymavlink upload loop (answer each MISSION_REQUEST_INT) for comparison."""
    out = []
    with Simulator(SimulatorConfig(vehicles=1, speed=1.0)) as sim:
        master = mavutil.mavlink_connection(sim.url(0), source_system=254)
        master.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        pos = master.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=5)
        wire = [MissionItem.waypoint(pos.lat / 1e7, pos.lon / 1e7, 0.0)] + _items(pos.lat / 1e7, pos.lon / 1e7, n)
        for _ in range(runs):
            t0 = time.perf_counter()
            master.mav.mission_count_send(1, 1, len(wire), 0)
            while True:
                m = master.recv_match(type=["MISSION_REQUEST_INT", "MISSION_ACK"], blocking=True, timeout=2)
                if m is None or m.get_type() == "MISSION_ACK":
                    break
                master.mav.send(wire[m.seq].to_message(m.seq, 1, 1))
            out.append(time.perf_counter() - t0)
        master.close()
    return out


def violation_latency(trials: int) -> tuple[list[float], list[float]]:
    """(sim-side end-to-end latencies, driver-internal latencies) in seconds."""
    end_to_end: list[float] = []
    with Simulator(SimulatorConfig(vehicles=1, speed=5.0)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        home = v.wait_until(lambda s: s.home is not None, 5.0).home
        v.set_mode("GUIDED")
        v.arm()
        v.takeoff(10.0)
        max_alt = 12.0
        v.set_safety(SafetyGate(Geofence.circle(home.lat_deg, home.lon_deg, 200.0, max_alt_rel_m=max_alt),
                                action="hold"))
        log = sim.servers[0].log
        for _ in range(trials):
            v.goto(home.lat_deg, home.lon_deg, 10.0, wait=True, tolerance_m=0.5)
            t_start = time.monotonic()
            v.velocity(0.0, 0.0, -1.5)
            v.wait_until(lambda s: s.mode == "LOITER", 20.0, what="hold after the altitude breach")
            entries = [e for e in list(log) if e[0] >= t_start]
            t_tel = next(t for t, kind, data in entries if kind == "position" and data[2] > max_alt)
            t_cmd = next(t for t, kind, data in entries if kind == "mode_request" and data[0] == "LOITER"
                         and t >= t_tel)
            end_to_end.append(t_cmd - t_tel)
        internal = [lat for lat, _ in v.safety_log]
        v.rtl()
        v.close()
    return end_to_end, internal


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    args = ap.parse_args(argv)
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
          f"(item timeout 20 ms, simulated autopilot re-requests after 10 ms)")
    print(f"  goal completes with 10 % loss: met ({len(lossy)}/{runs}); also <= 2 s: "
          f"{'yes' if lossy_s <= 2.0 else 'no'}")

    e2e, internal = violation_latency(trials)
    e_med, e_max = statistics.median(e2e) * 1e3, max(e2e) * 1e3
    i_med, i_max = statistics.median(internal) * 1e3, max(internal) * 1e3
    print(f"violation -> action ({trials} altitude-fence breaches): telemetry sent -> mode change received "
          f"by the autopilot median {e_med:.2f} ms, max {e_max:.2f} ms; driver receipt -> action sent "
          f"median {i_med:.3f} ms, max {i_max:.3f} ms")
    ok &= e_max <= 50.0
    print(f"  goal <= 50 ms: {'met' if e_max <= 50.0 else 'NOT met'}")
    print(f"HEADLINE: round trip median {med:.2f} ms (<= 20), 500-item upload {up_s:.2f} s (<= 2) / "
          f"{lossy_s:.2f} s at 10 % loss, violation->action max {e_max:.1f} ms (<= 50): "
          f"{'all goals met' if ok else 'GOAL MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
