"""Onboard service benchmark: swarm latency, log throughput, CPU per service, on loopback.

  1. Peer latency, sign -> send -> receive -> verify -> decode, one way, under the load of
     3 drones each sending 10 Hz fused estimates and 30 Hz relative observations (120 msg/s):
     three sender sessions in one process, the receiver in another (CLOCK_MONOTONIC is shared
     by processes). Peer: the same signed datagrams over plain UDP sockets (no middleware),
     the floor any transport sits on. Goal: zenoh p99 <= 5 ms.
  2. Log writer throughput: typical engine records (GNSS, velocity, relative observation,
     update) through the MCAP log (chunks flushed every 50 ms by its thread) against the
     JSON-lines measurement log of skyfix.fusion on the same records. Goal: >= 20 000 records/s.
  3. CPU per service: the simulator (3 vehicles, in this process), three ``skyfix serve`` (10 Hz estimates,
     heartbeats, MCAP log) and a helper drone publishing 10 Hz estimates and 30 Hz signed
     camera observations of each of the three (built from their broadcast estimates with 3 %
     range / 0.2 deg noise), which every service verifies, decodes and fuses. CPU time from
     /proc over a 15 s window, once every service fuses observations. Goal: <= 25 % of one core per service.

A shared 2-core machine: figures taken under other people's load are printed with the load
average. Exit 1 when a goal is missed. The last line is the headline.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from skyfix.crps import messages as M
from skyfix.crps.transport import Endpoints, ZenohTransport
from skyfix.crps.transport import free_tcp_ports as free_ports
from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.fusion.log import MeasurementLog
from skyfix.fusion.log_mcap import McapLog
from skyfix.types import RelativeObservation

KEY = b"benchmark swarm key, 32 bytes!!!"
SENDERS = ("d1", "d2", "d3")
EST_HZ, OBS_HZ = 10.0, 30.0


def _bodies(rng: np.random.Generator):
    est = M.FusedEstimate(time.time(), 46.5 + rng.normal(0, 1e-4), 6.6, 420.0, tuple(np.eye(3).ravel().tolist()),
                          (1.0, 2.0, 0.0), ("gnss", "velocity"))
    obs = M.RelativeObs("d9", time.time(), (0.6, 0.8, 0.0), 40.0, tuple((np.eye(3) * 1.4).ravel().tolist()),
                        46.5, 6.6, 430.0)
    return est, obs


# -- 1. latency ---------------------------------------------------------------------------------
def _receiver(kind: str, port: int, n_expected: int, out: mp.Queue, finished) -> None:
    codec = M.SwarmCodec("rx", KEY, clock=time.time)
    got: list[tuple[str, int, int]] = []
    done = threading.Event()

    def on(_key: str, data: bytes) -> None:
        env = codec.decode(data)
        if env is not None:
            got.append((env.sender, env.seq, time.monotonic_ns()))
            if len(got) >= n_expected:
                done.set()

    if kind == "zenoh":
        t = ZenohTransport("bench", "rx", Endpoints.parse(f"listen:tcp/127.0.0.1:{port}"))
        t.subscribe(on)
    else:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", port))
        sock.settimeout(0.2)

        def loop() -> None:
            while not done.is_set():
                try:
                    on("", sock.recv(65535))
                except TimeoutError:
                    continue
        threading.Thread(target=loop, daemon=True).start()
    out.put("ready")
    while not done.wait(0.1) and not finished.is_set():
        pass
    time.sleep(0.5)  # what is still in flight when the senders stop
    out.put(got)
    if kind == "zenoh":
        t.close()


def latency(kind: str, seconds: float) -> np.ndarray:
    """One-way latencies (s) of every message of 3 senders at 10 Hz + 30 Hz each, over ``kind``."""
    ctx = mp.get_context("spawn")
    (port,) = free_ports(1)
    per_sender = int(seconds * (EST_HZ + OBS_HZ))
    out, finished = ctx.Queue(), ctx.Event()
    rx = ctx.Process(target=_receiver, args=(kind, port, per_sender * len(SENDERS), out, finished))
    rx.start()
    assert out.get(timeout=60) == "ready"
    sent: dict[tuple[str, int], int] = {}

    def sender(drone: str) -> None:
        codec = M.SwarmCodec(drone, KEY)
        rng = np.random.default_rng(abs(hash(drone)) % 2**32)
        if kind == "zenoh":
            tx = ZenohTransport("bench", drone, Endpoints.parse(f"tcp/127.0.0.1:{port}"))
            time.sleep(1.5)  # session up
            publish = tx.publish
        else:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

            def publish(_topic: str, data: bytes) -> None:
                sock.sendto(data, ("127.0.0.1", port))
        period = 1.0 / OBS_HZ
        t_next = time.monotonic()
        for k in range(int(seconds * OBS_HZ)):
            est, obs = _bodies(rng)
            for body in ([obs, est] if k % 3 == 0 else [obs]):
                t0 = time.monotonic_ns()
                env, data = codec.seal(body)
                sent[(drone, env.seq)] = t0
                publish(M.TOPIC_OF[type(body)], data)
            t_next += period
            time.sleep(max(0.0, t_next - time.monotonic()))
        if kind == "zenoh":
            time.sleep(1.0)
            tx.close()

    threads = [threading.Thread(target=sender, args=(d,)) for d in SENDERS]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    finished.set()
    got = out.get(timeout=60)
    rx.join(timeout=10)
    lat = [(t1 - sent[(s, q)]) * 1e-9 for s, q, t1 in got if (s, q) in sent]
    print(f"  {kind}: {len(lat)} of {len(sent)} messages received")
    return np.asarray(lat)


# -- 2. log throughput --------------------------------------------------------------------------------
def _records(n: int) -> list[tuple[str, dict | None]]:
    rng = np.random.default_rng(0)
    obs = RelativeObservation("d2", "d1", 0.0, np.array([0.6, 0.8, 0.0]), 40.0, np.eye(3) * 1.4)
    recs = []
    for i in range(n):
        t = 1.7e9 + 0.01 * i
        kind = i % 4
        if kind == 0:
            recs.append(("gnss", {"drone_id": "d1", "time_s": t, "lat_deg": 46.5 + rng.normal(0, 1e-5),
                                  "lon_deg": 6.6, "alt_m": 420.0, "fix_type": 3, "satellites": 12,
                                  "h_sigma_m": 0.8, "v_sigma_m": 1.5, "hdop": 0.9}))
        elif kind == 1:
            recs.append(("velocity", {"drone_id": "d1", "time_s": t, "vel_enu_mps": rng.normal(0, 1, 3),
                                      "sigma_mps": 0.2}))
        elif kind == 2:
            recs.append(("relative", {"obs": obs}))
        else:
            recs.append(("update", None))
    return recs


def log_throughput(n: int) -> tuple[float, float]:
    """(MCAP records/s, JSON-lines records/s) writing the same ``n`` records, close included."""
    recs = _records(n)
    header = {"origin": [46.5, 6.6, 420.0], "lag_s": 2.0, "config": {}}
    rates = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, make in (("mcap", lambda p: McapLog(p, header)), ("jsonl", lambda p: MeasurementLog(p, header))):
            path = Path(tmp) / f"log.{name}"
            t0 = time.perf_counter()
            log = make(path)
            for op, args in recs:
                log.record(op, args)
            log.close()
            rates.append(n / (time.perf_counter() - t0))
            print(f"  {name}: {rates[-1]:,.0f} records/s, {path.stat().st_size / n:.0f} bytes/record")
    return rates[0], rates[1]


# -- 3. CPU per service -----------------------------------------------------------------------------
def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _helper(ports: list[int], stop: threading.Event, rng: np.random.Generator) -> None:
    """Helper drone h1: 10 Hz estimate, 30 Hz signed observations of each drone it hears."""
    from skyfix.geo import LocalFrame

    codec = M.SwarmCodec("h1", KEY)
    tx = ZenohTransport("skyfix", "h1", Endpoints.parse(",".join(f"tcp/127.0.0.1:{p}" for p in ports)))
    latest: dict[str, M.FusedEstimate] = {}
    decoder = M.SwarmCodec("h1-rx", KEY)

    def on(_key: str, data: bytes) -> None:
        env = decoder.decode(data)
        if env is not None and isinstance(env.body, M.FusedEstimate):
            latest[env.sender] = env.body
    tx.subscribe(on)
    k = 0
    while not stop.wait(1.0 / OBS_HZ):
        if not latest:
            continue
        ref = next(iter(latest.values()))
        frame = LocalFrame(ref.lat_deg, ref.lon_deg, ref.alt_m)
        me = np.array([0.0, -30.0, 20.0])  # 30 m south of the first drone, 20 m up
        lat, lon, alt = (float(c) for c in frame.to_geodetic(*me))
        now = time.time()
        if k % 3 == 0:
            tx.publish("estimate", codec.encode(M.FusedEstimate(now, lat, lon, alt, tuple((np.eye(3) * 0.25).ravel()
                                                                                             .tolist()), (0.0, 0.0, 0.0))))
        for drone, est in list(latest.items()):
            off = np.array([float(c) for c in frame.to_enu(est.lat_deg, est.lon_deg, est.alt_m)]) - me
            rng_m = float(np.linalg.norm(off)) * (1 + 0.03 * rng.normal())
            b = off / np.linalg.norm(off) + np.radians(0.2) * rng.normal(size=3)
            b /= np.linalg.norm(b)
            cov = (0.03 * rng_m) ** 2 * np.outer(b, b) + (rng_m * np.radians(0.2)) ** 2 * (np.eye(3) - np.outer(b, b))
            tx.publish("relative", codec.encode(M.RelativeObs(drone, now, tuple(b.tolist()), rng_m,
                                                              tuple(cov.ravel().tolist()), lat, lon, alt)))
        k += 1
    tx.close()


def cpu_per_service(warm_s: float, window_s: float) -> list[float]:
    """CPU (% of one core) of each of three skyfix serve processes under the swarm load."""
    tmp = Path(tempfile.mkdtemp())
    (tmp / "key").write_bytes(KEY)
    ports = free_ports(3)
    sim = Simulator(SimulatorConfig(vehicles=3)).start()  # the autopilots, in this process
    mav = [port for _, port in sim.addresses]
    procs = []
    for i in range(3):
        swarm = ",".join([f"listen:tcp/127.0.0.1:{ports[i]}"] + [f"tcp/127.0.0.1:{p}" for j, p in enumerate(ports)
                                                                  if j != i])
        procs.append(subprocess.Popen([sys.executable, "-m", "skyfix", "-q", "serve", "--id", f"d{i + 1}", "--mavlink",
                                       f"udpout:127.0.0.1:{mav[i]}", "--swarm", swarm, "--swarm-key-file",
                                       str(tmp / "key"), "--roster", "d1,d2,d3,h1",
                                       "--log", str(tmp / f"d{i + 1}.mcap")]))
    stop = threading.Event()
    helper = threading.Thread(target=_helper, args=(ports, stop, np.random.default_rng(1)), daemon=True)
    helper.start()
    try:
        # started: every service fusing its own telemetry and the helper's observations
        t_end = time.monotonic() + 120.0
        while time.monotonic() < t_end and not all(_count(tmp / f"d{i + 1}.mcap", "/fusion/relative") > 30
                                                   for i in range(3)):
            time.sleep(1.0)
        time.sleep(warm_s)
        c0 = [_cpu_s(p.pid) for p in procs]
        time.sleep(window_s)
        cpu = [100.0 * (_cpu_s(p.pid) - a) / window_s for p, a in zip(procs, c0, strict=True)]
        stop.set()
        helper.join(timeout=5)
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
            p.wait(timeout=20)
        sim.stop()
    for i in range(3):
        log = tmp / f"d{i + 1}.mcap"
        print(f"  d{i + 1}: {_count(log, '/fusion/relative')} observations and {_count(log, '/fusion/update')} "
              f"smoother updates in its log")
    return cpu


def _count(log: Path, topic: str) -> int:
    from skyfix.fusion.log_mcap import iter_messages

    return sum(1 for _ in iter_messages(log, [topic])) if log.exists() else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="shorter runs (for a smoke test)")
    args = ap.parse_args()
    secs = 5.0 if args.quick else 15.0
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print("1. peer latency, one way, 3 drones x (10 Hz estimates + 30 Hz observations):")
    lat = {kind: latency(kind, secs) for kind in ("udp", "zenoh")}
    p50, p99 = (float(np.percentile(lat["zenoh"], q)) * 1e3 for q in (50, 99))
    u50, u99 = (float(np.percentile(lat["udp"], q)) * 1e3 for q in (50, 99))
    print(f"  plain UDP: p50 {u50:.3f} ms, p99 {u99:.3f} ms; zenoh: p50 {p50:.3f} ms, p99 {p99:.3f} ms "
          f"(ratio p99 {p99 / u99:.1f}x)")
    print("2. log writer throughput:")
    mcap_rate, jsonl_rate = log_throughput(20_000 if args.quick else 100_000)
    print(f"  MCAP / JSON lines: {mcap_rate / jsonl_rate:.2f}x")
    print("3. CPU per skyfix serve (sim + 3 services + helper's 30 Hz observations of each):")
    cpu = cpu_per_service(3.0, 8.0 if args.quick else 15.0)
    print(f"  CPU % of one core: {', '.join(f'd{i + 1} {c:.1f}' for i, c in enumerate(cpu))}; "
          f"load average {os.getloadavg()[0]:.1f}")
    goals = {"peer latency p99 <= 5 ms": p99 <= 5.0, "log >= 20000 records/s": mcap_rate >= 20_000,
             "CPU <= 25 % of a core per service": max(cpu) <= 25.0}
    for name, ok in goals.items():
        print(f"  goal {name}: {'MET' if ok else 'NOT MET'}")
    print(json.dumps({"zenoh_p50_ms": p50, "zenoh_p99_ms": p99, "udp_p99_ms": u99, "mcap_records_per_s": mcap_rate,
                      "jsonl_records_per_s": jsonl_rate, "cpu_pct": cpu}))
    print(f"service: peer latency p50 {p50:.2f} / p99 {p99:.2f} ms ({p99 / u99:.1f}x plain UDP), log "
          f"{mcap_rate:,.0f} records/s ({mcap_rate / jsonl_rate:.1f}x JSON lines), CPU max {max(cpu):.1f} % of a core "
          f"per service: {'all goals MET' if all(goals.values()) else 'goal(s) NOT MET'}")
    return 0 if all(goals.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
