"""``skyfix serve`` and ``skyfix swarm``: argument checking and registration (light imports only,
so ``skyfix --help`` stays fast; the service itself is :mod:`skyfix.crps.service`)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from skyfix.errors import InputError, LinkError

log = logging.getLogger("skyfix.crps.service")


def config_from_args(args):
    """The :class:`ServiceConfig` of ``skyfix serve``'s arguments (InputError naming the bad one)."""
    from skyfix.crps.messages import read_key
    from skyfix.crps.service import ServiceConfig
    from skyfix.crps.transport import Endpoints, check_name
    from skyfix.drivers.link import check_url

    check_name("--id", args.id)
    check_name("--swarm-name", args.swarm_name)
    check_url(args.mavlink)
    roster = None
    if args.roster:
        roster = tuple(check_name("--roster entry", r.strip()) for r in args.roster.split(","))
        if args.id not in roster:
            raise InputError(f"--roster {args.roster!r} must include this drone's --id {args.id!r}")
    origin = None
    if args.origin:
        try:
            lat, lon, alt = (float(x) for x in args.origin.split(","))
        except ValueError:
            raise InputError(f"--origin must be LAT,LON,ALT_M, got {args.origin!r}") from None
        origin = (lat, lon, alt)
    rate = float(args.rate)
    if not 0.5 <= rate <= 50.0:
        raise InputError(f"--rate must be 0.5-50 Hz, got {args.rate}")
    shared = {}
    if args.gnss_common_share is not None:
        shared["gnss_common_share"] = float(args.gnss_common_share)
        if not 0.0 <= shared["gnss_common_share"] < 1.0:
            raise InputError(f"--gnss-common-share must be in [0, 1), got {args.gnss_common_share}")
    gate = safety_gate(args.fence, args.max_alt_m, args.max_speed_mps, args.fence_action)
    return ServiceConfig(args.id, args.mavlink, Endpoints.parse(args.swarm), read_key(args.swarm_key_file),
                         swarm=args.swarm_name, roster=roster, origin=origin, log_path=args.log,
                         live=args.live, estimate_hz=rate, inject=args.inject, safety=gate, **shared)


def safety_gate(fence_path: Path | None, max_alt_m: float | None, max_speed_mps: float | None, action: str):
    """The drivers' :class:`SafetyGate` of ``--fence``/``--max-alt-m``/``--max-speed-mps`` (None: no gate)."""
    import json
    import math

    import numpy as np
    import shapely.geometry

    from skyfix.drivers.safety import Geofence, SafetyGate

    if fence_path is None and max_alt_m is None and max_speed_mps is None:
        return None
    polygons = []
    if fence_path is not None:
        try:
            doc = json.loads(Path(fence_path).read_text())
            features = doc.get("features", [doc]) if doc.get("type") == "FeatureCollection" else [doc]
            geoms = [shapely.geometry.shape(f.get("geometry", f)) for f in features]
        except (OSError, ValueError, AttributeError, TypeError, KeyError) as exc:
            raise InputError(f"--fence {fence_path}: not a readable GeoJSON polygon file ({exc})") from None
        for g in geoms:
            for poly in getattr(g, "geoms", [g]):
                if poly.geom_type != "Polygon":
                    raise InputError(f"--fence {fence_path}: {poly.geom_type} is not a polygon")
                polygons.append(np.asarray(poly.exterior.coords)[:-1, ::-1])  # (lon, lat) -> (lat, lon)
    ceiling = math.inf if max_alt_m is None else max_alt_m
    return SafetyGate(Geofence(polygons, max_alt_rel_m=ceiling), max_speed_mps=max_speed_mps or math.inf,
                      max_alt_rel_m=ceiling, action=action)


SERVE_DESCRIPTION = (
    "Run on a drone's companion computer: MAVLink telemetry in (reconnected with back-off when the link "
    "is lost), the drone's fusion engine, signed messages to and from the other drones over Zenoh, camera "
    "frames in, GPS_INPUT injection out (--inject); every input, message, estimate and action to an MCAP "
    "log and a live Foxglove view. SIGINT/SIGTERM stop it cleanly; a bad argument is a one-line error "
    "(exit 2).")

SERVE_EPILOG = """\
example (drone 2 of three on one machine, simulator from 'skyfix sim --vehicles 3'):
  head -c 32 /dev/urandom > swarm.key
  skyfix serve --id d2 --mavlink udpin:127.0.0.1:14551 \\
      --swarm listen:tcp/127.0.0.1:7452,tcp/127.0.0.1:7451,tcp/127.0.0.1:7453 \\
      --swarm-key-file swarm.key --roster d1,d2,d3 --log d2.mcap --live 8766

--swarm lists zenoh endpoints: the one prefixed listen: is this drone's own, the others
its peers' (no multicast discovery: a drone hears exactly the peers it is given).
Every message is signed with the swarm key (HMAC-SHA256); forged, replayed, stale,
oversized or malformed messages and senders not on --roster are dropped and counted.
Logs: 'skyfix fusion replay d2.mcap' reproduces the estimates; the .mcap opens in Foxglove
(topics /fix/<drone> are LocationFix: a map panel shows the swarm).
"""


def register(subparsers) -> None:
    """Add ``skyfix serve`` and ``skyfix swarm``."""
    p = subparsers.add_parser("serve", help="the onboard service: MAVLink + fusion + swarm network + MCAP log",
                              description=SERVE_DESCRIPTION, epilog=SERVE_EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--id", required=True, help="this drone's id in the swarm (letters, digits, - and _)")
    p.add_argument("--mavlink", required=True, metavar="URL",
                   help="autopilot link: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or /dev/ttyACM0[:BAUD]")
    p.add_argument("--swarm", required=True, metavar="ENDPOINTS",
                   help="comma-separated zenoh endpoints: listen:tcp/HOST:PORT (own), tcp/HOST:PORT (peers)")
    p.add_argument("--swarm-key-file", required=True, type=Path, metavar="FILE",
                   help="the swarm's shared secret (at least 16 bytes)")
    p.add_argument("--swarm-name", default="skyfix", help="swarm name in the key expressions (default skyfix)")
    p.add_argument("--roster", default=None, metavar="IDS",
                   help="comma-separated ids allowed to speak (default: anyone holding the key)")
    p.add_argument("--origin", default=None, metavar="LAT,LON,ALT_M",
                   help="fusion frame origin (default: the autopilot's home or first GNSS fix)")
    p.add_argument("--camera", default=None, metavar="SRC",
                   help="camera frames (a folder of images, an OpenCV device index or stream URL, or 'sim': the "
                        "simulator's renderer drawing the nearest peer where it says it is, 5 Hz) through a "
                        "drop-oldest queue to the drone detector; detections are logged on /camera/detections")
    p.add_argument("--log", type=Path, default=None, metavar="FILE.mcap", help="MCAP log to write (never overwritten)")
    p.add_argument("--live", default=None, metavar="[HOST:]PORT",
                   help="stream the log's topics over the Foxglove WebSocket protocol (default host 127.0.0.1)")
    p.add_argument("--rate", type=float, default=10.0, help="fusion and estimate rate, Hz (default 10)")
    p.add_argument("--gnss-common-share", type=float, default=None, metavar="SHARE",
                   help="share (0 to <1) of a receiver's wandering GNSS error that the swarm's receivers have in common "
                        "(the same satellites through the same sky); fused as shared, it is not averaged away when "
                        "neighbours position this drone (default 0.9, skyfix.crps.service.GNSS_COMMON_SHARE; 0: each "
                        "receiver's error its own)")
    p.add_argument("--inject", action="store_true",
                   help="while the drone's own GNSS is lost, inject the fused position as GPS_INPUT")
    p.add_argument("--fence", type=Path, default=None, metavar="GEOJSON",
                   help="safety gate: inclusion polygon(s) (GeoJSON Polygon/MultiPolygon/Feature(Collection), "
                        "lon,lat); a position outside triggers --fence-action")
    p.add_argument("--max-alt-m", type=float, default=None, help="safety gate: ceiling above home, m")
    p.add_argument("--max-speed-mps", type=float, default=None, help="safety gate: speed limit, m/s")
    p.add_argument("--fence-action", choices=("rtl", "hold", "land"), default="rtl",
                   help="what the safety gate commands on a violation (default rtl)")
    p.set_defaults(func=run_serve)

    from skyfix.crps.swarm import register_status

    register_status(subparsers)


def run_serve(args) -> int:
    """The ``skyfix serve`` command: exit 0 after SIGINT/SIGTERM, 2 on a bad argument."""
    import faulthandler
    import signal
    import sys

    from skyfix.crps.service import Service

    try:
        cfg = config_from_args(args)
        service = Service(cfg)
    except (InputError, LinkError) as exc:
        sys.stderr.write(f"skyfix serve: error: {exc}\n")
        return 2
    if args.camera:
        from skyfix.crps.camera_feed import CameraFeed

        try:
            source = service.sim_camera() if args.camera == "sim" else args.camera
            service.camera = CameraFeed(source, service.outputs, folder_fps=5.0 if args.camera == "sim" else 10.0
                                        ).start()
        except InputError as exc:
            service.close()
            sys.stderr.write(f"skyfix serve: error: {exc}\n")
            return 2

    def on_signal(signum, _frame) -> None:
        log.info("signal %d: stopping", signum)
        service.stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # kill -USR1 PID: every thread's stack to stderr
    log.info("skyfix serve %s: MAVLink %s, swarm %s", cfg.drone_id, cfg.mavlink_url, args.swarm)
    service.run()
    return 0
