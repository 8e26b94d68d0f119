"""``skyfix vehicle ...``: what a person checking a drone does over MAVLink.

status (bounded wait for GPS and home), arm, disarm, takeoff, goto, rtl, land, mission
upload/download, param get/set. A refusal prints the autopilot's own reason (its
STATUSTEXT and COMMAND_ACK result) and exits non-zero. The simulator command
(``skyfix sim``) lives in :mod:`skyfix.datasets.sim.cli`.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

from skyfix.errors import InputError, SkyfixTimeout

URL_HELP = "MAVLink URL: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a serial device /dev/ttyACM0:115200"


def register(subparsers: argparse._SubParsersAction) -> None:
    v = subparsers.add_parser(
        "vehicle", help="talk to a MAVLink autopilot: status, arm, takeoff, goto, rtl, mission, params",
        description="Check and fly a vehicle over MAVLink (ArduPilot or PX4). " + URL_HELP + ". "
                    "Altitudes of takeoff/goto are metres above home. Refusals print the autopilot's reason.")
    vsub = v.add_subparsers(dest="vehicle_command", metavar="ACTION", title="actions")
    s = _action(vsub, "status", "connect, wait (bounded) for GPS and home, print the state", run_status)
    s.add_argument("--json", action="store_true", help="print the state as JSON")
    s.add_argument("--wait", type=float, default=10.0, help="seconds to wait for GPS fix and home (default 10)")
    _action(vsub, "arm", "arm the motors (in the current mode)", run_arm)
    _action(vsub, "disarm", "disarm (refused in flight by the autopilot)", run_disarm)
    t = _action(vsub, "takeoff", "arm if needed and take off (ArduPilot: GUIDED; PX4: AUTO.TAKEOFF)", run_takeoff)
    t.add_argument("alt_m", type=float, help="altitude above home, metres")
    g = _action(vsub, "goto", "fly to a position (GUIDED / OFFBOARD) and wait for arrival", run_goto)
    g.add_argument("lat_deg", type=float, help="latitude, degrees WGS84")
    g.add_argument("lon_deg", type=float, help="longitude, degrees WGS84")
    g.add_argument("alt_m", type=float, help="altitude above home, metres")
    g.add_argument("--no-wait", action="store_true", help="return once the target is sent")
    for name, helptext in (("rtl", "return to launch"), ("land", "land where it is")):
        r = _action(vsub, name, f"{helptext}; with --wait until disarmed", run_rtl_land)
        r.add_argument("--wait", action="store_true", help="wait until landed and disarmed")
    m = vsub.add_parser("mission", help="upload or download the mission (JSON)",
                        description="Missions as JSON: {\"items\": [MissionItem fields...]}, the format "
                                    "'mission download' writes.")
    msub = m.add_subparsers(dest="mission_command", metavar="ACTION", title="actions")
    up = _action(msub, "upload", "upload a mission JSON file", run_mission_upload)
    up.add_argument("file", type=Path, help="mission JSON (as written by 'mission download'; schema: docs/schemas/mission.schema.json)")
    up.add_argument("--ftp", action="store_true",
                    help="ArduPilot: send the mission as one file over MAVLink FTP (@MISSION/mission.dat), "
                         "read back and compared; ~4x faster than item by item for long missions")
    down = _action(msub, "download", "download the mission to JSON", run_mission_download)
    down.add_argument("-o", "--output", default="-", help="JSON file (default: stdout)")
    m.set_defaults(func=lambda args: (m.print_help(), 2)[1])
    p = vsub.add_parser("param", help="read or write parameters", description="Read or write autopilot "
                        "parameters; integers are printed as integers.")
    psub = p.add_subparsers(dest="param_command", metavar="ACTION", title="actions")
    pg = _action(psub, "get", "print NAME VALUE for each parameter", run_param_get)
    pg.add_argument("names", nargs="+", help="parameter names, e.g. GPS1_TYPE EK3_SRC1_POSXY")
    ps = _action(psub, "set", "write one parameter and print what the autopilot holds", run_param_set)
    ps.add_argument("name", help="parameter name")
    ps.add_argument("value", type=float, help="new value")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
    v.set_defaults(func=lambda args: (v.print_help(), 2)[1])


def _action(sub, name: str, helptext: str, func) -> argparse.ArgumentParser:
    a = sub.add_parser(name, help=helptext, description=helptext[0].upper() + helptext[1:] + ".")
    a.add_argument("url", help=URL_HELP)
    a.add_argument("--system-id", type=int, default=None, help="vehicle system id (default: first heard)")
    a.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the vehicle (default 10)")
    a.set_defaults(func=func)
    return a


def _check_args(args: argparse.Namespace) -> None:
    """Refuse bad numbers before connecting (one line naming the argument, exit 2), not after
    a 10 s wait for the vehicle."""
    import math

    from skyfix.drivers.link import check_url

    check_url(args.url)
    for flag, value in (("--timeout", args.timeout), ("--wait", getattr(args, "wait", None))):
        if isinstance(value, float) and not (math.isfinite(value) and value > 0):
            raise InputError(f"{flag} must be a positive number of seconds, got {value:g}")
    if args.system_id is not None and not 1 <= args.system_id <= 255:
        raise InputError(f"--system-id must be 1..255, got {args.system_id}")
    alt = getattr(args, "alt_m", None)
    if alt is not None and not (math.isfinite(alt) and alt > 0):
        raise InputError(f"ALT_M must be a positive height above home in metres, got {alt:g}")
    lat, lon = getattr(args, "lat_deg", None), getattr(args, "lon_deg", None)
    if lat is not None and not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise InputError(f"LAT_DEG must be a latitude in -90..90 degrees, got {lat:g}")
    if lon is not None and not (math.isfinite(lon) and -180.0 <= lon <= 180.0):
        raise InputError(f"LON_DEG must be a longitude in -180..180 degrees, got {lon:g}")


def _connect(args: argparse.Namespace):
    from skyfix.drivers.vehicle import Vehicle

    _check_args(args)
    return Vehicle.connect(args.url, timeout_s=args.timeout, system_id=args.system_id)


def run_status(args: argparse.Namespace) -> int:
    from skyfix.drivers.mav import mavlink

    with _connect(args) as vehicle:
        try:
            st = vehicle.wait_until(lambda s: s.position is not None and s.home is not None and s.gps is not None
                                    and s.gps.fix_type >= mavlink.GPS_FIX_TYPE_3D_FIX, args.wait,
                                    what="GPS fix and home")
        except SkyfixTimeout:
            st = vehicle.state  # report what there is: a vehicle without GPS is worth seeing too
        if args.json:
            sys.stdout.write(json.dumps(asdict(st), indent=2, default=str) + "\n")
            return 0
        sys.stdout.write(st.summary() + "\n")
        if st.gps:
            g = st.gps
            sys.stdout.write(f"gps fix {g.fix_type}, {g.satellites} sats, h_acc {g.h_acc_m:.2f} m, v_acc "
                             f"{g.v_acc_m:.2f} m, HDOP {g.hdop:.2f}, {g.alt_amsl_m:.1f} m AMSL = "
                             f"{g.alt_ellipsoid_m:.1f} m ellipsoidal ({g.alt_ellipsoid_source})\n")
        if st.battery:
            sys.stdout.write(f"battery {st.battery.voltage_v:.2f} V {st.battery.remaining_pct:.0f} %\n")
        if st.home:
            sys.stdout.write(f"home {st.home.lat_deg:.7f},{st.home.lon_deg:.7f} {st.home.alt_amsl_m:.1f} m AMSL\n")
        else:
            sys.stdout.write("home not set (no GPS fix yet?)\n")
    return 0


def run_arm(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        vehicle.arm()
        sys.stdout.write(f"armed in {vehicle.state.mode}\n")
    return 0


def run_disarm(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        vehicle.disarm()
        sys.stdout.write("disarmed\n")
    return 0


def run_takeoff(args: argparse.Namespace) -> int:
    from skyfix.drivers.modes import role_mode

    with _connect(args) as vehicle:
        vehicle.wait_until(lambda s: s.home is not None, args.timeout, what="home (GPS fix)")
        if vehicle.autopilot == "ardupilot":
            vehicle.set_mode(role_mode("ardupilot", "takeoff"))
        if not vehicle.state.armed:
            vehicle.arm()
        vehicle.takeoff(args.alt_m)
        sys.stdout.write(f"at {vehicle.state.position.alt_rel_m:.1f} m above home\n")
    return 0


def run_goto(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        vehicle.goto(args.lat_deg, args.lon_deg, args.alt_m, wait=not args.no_wait)
        sys.stdout.write(vehicle.state.summary() + "\n")
    return 0


def run_rtl_land(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        (vehicle.rtl if args.vehicle_command == "rtl" else vehicle.land)(wait=args.wait)
        sys.stdout.write(vehicle.state.summary() + "\n")
    return 0


def run_mission_upload(args: argparse.Namespace) -> int:
    from skyfix.drivers.mission import MissionFile
    from skyfix.jsonfile import convert, read_json

    if not args.file.is_file():
        raise InputError(f"{args.file}: no such mission file")
    plan = convert(read_json(args.file, "mission file"), MissionFile, f"mission file {args.file}")
    with _connect(args) as vehicle:
        stats = vehicle.upload_mission(plan.items, ftp=args.ftp)
    how = "over MAVLink FTP, read back and compared" if args.ftp else f"{stats.retransmissions} retransmissions"
    sys.stdout.write(f"uploaded {stats.items} items in {stats.elapsed_s:.2f} s ({how})\n")
    return 0


def run_mission_download(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        items = [asdict(it) for it in vehicle.download_mission()]
    text = json.dumps({"system_id": vehicle.system_id, "items": items}, indent=2)
    if args.output == "-":
        sys.stdout.write(text + "\n")
    else:
        Path(args.output).write_text(text + "\n")
    return 0


def run_param_get(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        for name in args.names:
            sys.stdout.write(f"{name} {vehicle.get_param(name):g}\n")
    return 0


def run_param_set(args: argparse.Namespace) -> int:
    with _connect(args) as vehicle:
        sys.stdout.write(f"{args.name} {vehicle.set_param(args.name, args.value):g}\n")
    return 0
