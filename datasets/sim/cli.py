"""``skyfix sim``: the built-in multi-vehicle MAVLink simulator on 127.0.0.1 (a harness
command, registered by :mod:`skyfix.datasets.cli`)."""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time

from skyfix.errors import InputError


def _floats(text: str, n: int, name: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise InputError(f"{name} must be {n} comma-separated numbers, got {text!r}") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise InputError(f"{name} must be {n} comma-separated finite numbers, got {text!r}")
    return vals


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``sim`` command."""
    p = subparsers.add_parser(
        "sim", help="run the multi-vehicle MAVLink simulator on 127.0.0.1",
        description="Run N simulated multirotors (ArduPilot Copter or PX4 flavour), each speaking "
                    "MAVLink over UDP on loopback. Vehicle i has system id i+1 and, like ArduPilot "
                    "SITL, sends to 127.0.0.1:BASE_PORT+i and answers whoever talks to it: connect a "
                    "ground station with udpin:127.0.0.1:BASE_PORT+i. Ctrl-C stops it.")
    p.add_argument("--vehicles", type=int, default=1, help="number of vehicles (default 1)")
    p.add_argument("--base-port", type=int, default=14550,
                   help="vehicle i sends to 127.0.0.1:BASE_PORT+i (default 14550)")
    p.add_argument("--flavour", choices=("ardupilot", "px4"), default="ardupilot",
                   help="autopilot to emulate (default ardupilot)")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second")
    p.add_argument("--home", default=None, metavar="LAT,LON,ALT",
                   help="home of vehicle 1, degrees and metres AMSL (default: SITL's default site)")
    p.add_argument("--wind", default="0,0", metavar="SPEED,FROM_DEG",
                   help="mean wind speed m/s and the direction it blows from, degrees (default 0,0)")
    p.add_argument("--gusts", type=float, default=0.0, help="gust standard deviation, m/s")
    p.add_argument("--loss", type=float, default=0.0, help="fraction of packets to drop (0..1)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="override an autopilot parameter on every vehicle (repeatable)")
    p.add_argument("--gps-fault", action="append", default=[], metavar="VEHICLE:KIND:START[:DURATION]",
                   help="schedule a GPS fault on vehicle VEHICLE (system id), KIND one of loss, "
                        "degraded, jump, spoof, START/DURATION in simulated seconds (repeatable), "
                        "e.g. 2:loss:30:20")
    p.add_argument("--legacy-params", action="store_true",
                   help="ArduPilot parameter names of firmware before 4.6 (GPS_TYPE, SIM_GPS_DISABLE) "
                        "instead of GPS1_TYPE, SIM_GPS1_ENABLE")
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    p.set_defaults(func=run_sim)


def run_sim(args: argparse.Namespace) -> int:
    """The ``skyfix sim`` command: exit 0 when stopped, 2 on a bad argument (one line)."""
    try:
        sim, cfg = _build(args)
    except InputError as exc:
        sys.stderr.write(f"skyfix sim: error: {exc}\n")
        return 2
    return _serve(sim, cfg, args)


def _build(args: argparse.Namespace):
    from skyfix.datasets.sim import Simulator, SimulatorConfig, WindField

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise InputError(f"--duration must be a positive number of seconds, got {args.duration:g}")
    speed, from_deg = _floats(args.wind, 2, "--wind")
    to_rad = math.radians(from_deg + 180.0)
    wind = WindField((speed * math.sin(to_rad), speed * math.cos(to_rad), 0.0), gust_sigma_mps=args.gusts)
    params = {}
    for item in args.param:
        name, eq, value = item.partition("=")
        name = name.strip().upper()
        if not eq or not name:
            raise InputError(f"--param must be NAME=VALUE, got {item!r}")
        if name in params:
            raise InputError(f"--param {name} is given twice")
        params[name] = _floats(value, 1, f"--param {name}")[0]
    cfg = SimulatorConfig(vehicles=args.vehicles, flavour=args.flavour, base_port=args.base_port,
                          home=_floats(args.home, 3, "--home") if args.home else None, speed=args.speed,
                          loss_rate=args.loss, wind=wind, params=params,
                          legacy_params=args.legacy_params)
    faults = [_gps_fault(spec, cfg.vehicles) for spec in args.gps_fault]
    sim = Simulator(cfg)  # unknown --param names are refused here (InputError)
    for index, fault in faults:
        sim.add_gps_fault(index, fault)
    return sim, cfg


def _serve(sim, cfg, args: argparse.Namespace) -> int:
    out = sys.stdout
    out.write(f"skyfix sim: {cfg.vehicles} {cfg.flavour} vehicle(s) on 127.0.0.1 at {cfg.speed:g}x "
              f"real time\n")
    for i, (host, port) in enumerate(sim.addresses):
        gcs = args.base_port + i
        out.write(f"  vehicle {i + 1}: sends to 127.0.0.1:{gcs} (connect udpin:127.0.0.1:{gcs}), "
                  f"listens on {host}:{port} (or connect udpout:{host}:{port})\n")
    out.write("Ctrl-C to stop.\n")
    out.flush()
    # SIGINT and SIGTERM stop it cleanly however it was started: a process launched in the background by a
    # script inherits SIGINT ignored, and Python then raises no KeyboardInterrupt (a suite started that way
    # waited 60 s on Ctrl-C here)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    sim.start()
    try:
        t_end = time.monotonic() + args.duration if args.duration else math.inf
        while not stop.wait(min(0.2, max(0.0, t_end - time.monotonic()))) and time.monotonic() < t_end:
            pass
        if stop.is_set():
            out.write("stopping\n")
    finally:
        sim.stop()
    return 0


def _gps_fault(spec: str, vehicles: int):
    """Parse VEHICLE:KIND:START[:DURATION] into (vehicle index, GpsFault)."""
    from skyfix.datasets.sim import GpsFault

    parts = spec.split(":")
    if len(parts) not in (3, 4):
        raise InputError(f"--gps-fault must be VEHICLE:KIND:START[:DURATION], got {spec!r}")
    try:
        sysid, start = int(parts[0]), float(parts[2])
        duration = float(parts[3]) if len(parts) == 4 else math.inf
    except ValueError:
        raise InputError(f"--gps-fault numbers are malformed in {spec!r}") from None
    if not 1 <= sysid <= vehicles:
        raise InputError(f"--gps-fault vehicle must be a system id 1..{vehicles}, got {sysid}")
    return sysid - 1, GpsFault(parts[1], start, duration)
