"""``skyfix sim`` (the built-in MAVLink simulator) and ``skyfix vehicle`` (talk to an autopilot)."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict

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
    p.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    p.set_defaults(func=run_sim)

    v = subparsers.add_parser("vehicle", help="talk to a MAVLink autopilot (status, params, mission)",
                              description="Inspect a vehicle over MAVLink. URL: udpin:HOST:PORT, "
                                          "udpout:HOST:PORT, tcp:HOST:PORT or /dev/ttyACM0:115200.")
    vsub = v.add_subparsers(dest="vehicle_command", metavar="ACTION", title="actions")
    s = vsub.add_parser("status", help="connect and print the vehicle state",
                        description="Connect, wait for telemetry and print the state.")
    _common(s)
    s.add_argument("--json", action="store_true", help="print the state as JSON")
    s.set_defaults(func=run_status)
    pa = vsub.add_parser("params", help="read autopilot parameters",
                         description="Read parameters by name and print NAME VALUE lines.")
    _common(pa)
    pa.add_argument("names", nargs="+", help="parameter names, e.g. GPS_TYPE")
    pa.set_defaults(func=run_params)
    m = vsub.add_parser("mission", help="download the vehicle's mission to JSON",
                        description="Download the mission (MISSION_ITEM_INT) and write it as JSON.")
    _common(m)
    m.add_argument("-o", "--output", default="-", help="JSON file (default: stdout)")
    m.set_defaults(func=run_mission_download)
    v.set_defaults(func=lambda args: (v.print_help(), 2)[1])


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("url", help="MAVLink URL, e.g. udpin:127.0.0.1:14550")
    p.add_argument("--system-id", type=int, default=None, help="vehicle system id (default: first heard)")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the vehicle")


def run_sim(args: argparse.Namespace) -> int:
    from skyfix.datasets.sim import Simulator, SimulatorConfig, WindField

    speed, from_deg = _floats(args.wind, 2, "--wind")
    to_rad = math.radians(from_deg + 180.0)
    wind = WindField((speed * math.sin(to_rad), speed * math.cos(to_rad), 0.0), gust_sigma_mps=args.gusts)
    params = {}
    for item in args.param:
        name, _, value = item.partition("=")
        params[name.strip().upper()] = _floats(value, 1, f"--param {name}")[0]
    cfg = SimulatorConfig(vehicles=args.vehicles, flavour=args.flavour, base_port=args.base_port,
                          home=_floats(args.home, 3, "--home") if args.home else None, speed=args.speed,
                          loss_rate=args.loss, wind=wind, params=params)
    faults = [_gps_fault(spec, cfg.vehicles) for spec in args.gps_fault]
    sim = Simulator(cfg)
    for index, fault in faults:
        sim.add_gps_fault(index, fault)
    out = sys.stdout
    out.write(f"skyfix sim: {cfg.vehicles} {cfg.flavour} vehicle(s) on 127.0.0.1 at {cfg.speed:g}x "
              f"real time\n")
    for i, (host, port) in enumerate(sim.addresses):
        gcs = args.base_port + i
        out.write(f"  vehicle {i + 1}: sends to 127.0.0.1:{gcs} (connect udpin:127.0.0.1:{gcs}), "
                  f"listens on {host}:{port} (or connect udpout:{host}:{port})\n")
    out.write("Ctrl-C to stop.\n")
    out.flush()
    sim.start()
    try:
        t_end = time.monotonic() + args.duration if args.duration else math.inf
        while time.monotonic() < t_end:
            time.sleep(min(0.2, max(0.0, t_end - time.monotonic())))
    except KeyboardInterrupt:
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


def _connect(args: argparse.Namespace):
    from skyfix.drivers.vehicle import Vehicle

    return Vehicle.connect(args.url, timeout_s=args.timeout, system_id=args.system_id)


def run_status(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        try:
            st = vehicle.wait_until(lambda s: None not in (s.position, s.gps, s.home),
                                    min(args.timeout, 5.0), what="position, GPS and home reports")
        except TimeoutError:
            st = vehicle.state
        if args.json:
            sys.stdout.write(json.dumps(asdict(st), indent=2, default=str) + "\n")
        else:
            sys.stdout.write(st.summary() + "\n")
            if st.battery:
                sys.stdout.write(f"battery {st.battery.voltage_v:.2f} V {st.battery.remaining_pct:.0f} %\n")
            if st.home:
                sys.stdout.write(f"home {st.home.lat_deg:.7f},{st.home.lon_deg:.7f} "
                                 f"{st.home.alt_amsl_m:.1f} m AMSL\n")
    return 0


def run_params(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        for name in args.names:
            sys.stdout.write(f"{name} {vehicle.get_param(name):g}\n")
    return 0


def run_mission_download(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        items = [asdict(it) for it in vehicle.download_mission()]
    text = json.dumps({"system_id": vehicle.system_id, "items": items}, indent=2)
    if args.output == "-":
        sys.stdout.write(text + "\n")
    else:
        with open(args.output, "w") as f:
            f.write(text + "\n")
    return 0
