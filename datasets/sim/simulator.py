"""The multi-vehicle simulator: N vehicles, each a MAVLink autopilot on its own UDP socket.

Vehicle ``i`` has system id ``i + 1``. Like ArduPilot SITL with a ground-station
output, it sends to ``127.0.0.1:base_port + i`` (when ``base_port`` is given) and
answers whoever talks to its own socket (``Simulator.addresses[i]``), so a ground
station either listens with ``udpin:127.0.0.1:P+i`` or sends with
``udpout:127.0.0.1:<vehicle port>``. Everything stays on loopback.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from skyfix import validate
from skyfix.datasets.sim.gps import GpsFault
from skyfix.datasets.sim.server import VehicleServer
from skyfix.datasets.sim.vehicle import SimVehicle, SimVehicleConfig
from skyfix.datasets.sim.wind import WindField
from skyfix.errors import InputError
from skyfix.geo import LocalFrame

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
#: Default home per flavour: ArduPilot SITL's CMAC field and PX4 SITL's Zurich default.
DEFAULT_HOME = {"ardupilot": (-35.363261, 149.165230, 584.0), "px4": (47.397742, 8.545594, 488.0)}


@dataclass
class SimulatorConfig:
    """Settings of a simulator run (one comment per field)."""

    vehicles: int = 1  # number of vehicles; vehicle i gets system id i + 1
    flavour: str = "ardupilot"  # "ardupilot" (Copter) or "px4"
    base_port: int | None = None  # vehicle i sends to 127.0.0.1:base_port+i; None: only answers
    share_gcs_port: bool = False  # all vehicles send to base_port (one link, several system ids)
    bind_ports: Sequence[int] | None = None  # own UDP ports; None: ephemeral
    home: tuple[float, float, float] | None = None  # lat_deg, lon_deg, alt_amsl_m of vehicle 0
    geoid_m: float | None = None  # geoid undulation N (AMSL = ellipsoidal - N); None: EGM96 at home
    spacing_m: float = 5.0  # vehicles start this far apart along east
    speed: float = 1.0  # simulated seconds per wall second
    dt_s: float = 0.02  # physics step, simulated seconds
    loss_rate: float = 0.0  # fraction of datagrams dropped in each direction
    wind: WindField = field(default_factory=WindField)
    params: dict[str, float] = field(default_factory=dict)  # overrides for every vehicle
    legacy_params: bool = False  # ArduPilot parameter names before 4.6 (GPS_TYPE, SIM_GPS_DISABLE)
    seed: int = 0

    def __post_init__(self) -> None:
        if int(self.vehicles) < 1:
            raise InputError(f"vehicles must be >= 1, got {self.vehicles}")
        if self.flavour not in DEFAULT_HOME:
            raise InputError(f"flavour must be 'ardupilot' or 'px4', got {self.flavour!r}")
        validate.positive_scalar("speed", self.speed)
        validate.positive_scalar("dt_s", self.dt_s)
        if not 0.0 <= float(self.loss_rate) < 1.0:
            raise InputError(f"loss_rate must be in [0, 1), got {self.loss_rate}")
        if self.base_port is not None and not 0 < int(self.base_port) < 65536 - int(self.vehicles):
            raise InputError(f"base_port must be a UDP port number, got {self.base_port}")


class Simulator:
    """Runs the vehicles on a background thread; use as a context manager or start()/stop().

    Thread safety: public methods take the simulator's lock, so tests may inspect
    ground truth or inject faults while ground stations talk MAVLink to it.
    """

    def __init__(self, config: SimulatorConfig | None = None, **kwargs) -> None:
        self.config = config or SimulatorConfig(**kwargs)
        cfg = self.config
        home = cfg.home or DEFAULT_HOME[cfg.flavour]
        lat0 = float(validate.latitude("home[0]", home[0]))
        lon0 = float(validate.longitude("home[1]", home[1]))
        if cfg.geoid_m is None:
            from skyfix.geoid import geoid_undulation_m
            self.geoid_m = float(geoid_undulation_m(lat0, lon0))
        else:
            self.geoid_m = validate.finite_scalar("geoid_m", cfg.geoid_m)
        self.world = LocalFrame(lat0, lon0, validate.finite_scalar("home[2]", home[2]) + self.geoid_m)
        self.lock = threading.RLock()
        self.servers: list[VehicleServer] = []
        rng = np.random.default_rng(cfg.seed)
        for i in range(int(cfg.vehicles)):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            port = int(cfg.bind_ports[i]) if cfg.bind_ports else 0
            sock.bind((LOOPBACK, port))
            sock.setblocking(False)
            vcfg = SimVehicleConfig(flavour=cfg.flavour, system_id=i + 1,
                                    start_enu_m=(i * cfg.spacing_m, 0.0, 0.0), seed=cfg.seed * 100 + i,
                                    params=dict(cfg.params), geoid_m=self.geoid_m,
                                    legacy_params=cfg.legacy_params)
            gcs = (LOOPBACK, int(cfg.base_port) + (0 if cfg.share_gcs_port else i)) if cfg.base_port is not None else None
            self.servers.append(VehicleServer(SimVehicle(vcfg, self.world, cfg.wind), sock,
                                              gcs_address=gcs, loss_rate=cfg.loss_rate,
                                              rng=np.random.default_rng(rng.integers(1 << 31))))
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.overruns = 0
        # (behind, speed): while ``behind()`` is True (a consumer of the simulation, e.g. a camera pipeline
        # sharing the CPU, has fallen behind) the clock runs at that speed instead of ``config.speed``
        self.pace: tuple[Callable[[], bool], float] | None = None
        self.paced_s = 0.0  # simulated seconds run at the slower pace

    # ------------------------------------------------------------------ API
    @property
    def addresses(self) -> list[tuple[str, int]]:
        """(host, port) of each vehicle's own socket: connect with ``udpout:host:port``."""
        return [s.sock.getsockname() for s in self.servers]

    def url(self, index: int = 0) -> str:
        """A pymavlink URL a ground station can use to reach vehicle ``index``."""
        host, port = self.addresses[index]
        return f"udpout:{host}:{port}"

    def vehicle(self, index: int = 0) -> SimVehicle:
        return self.servers[index].vehicle

    @property
    def time_s(self) -> float:
        return self.servers[0].vehicle.t_s

    def add_gps_fault(self, index: int, fault: GpsFault) -> None:
        """Schedule a GPS fault on vehicle ``index`` (times in simulated seconds)."""
        with self.lock:
            self.vehicle(index).gps.faults.append(fault)

    def clear_gps_faults(self, index: int) -> None:
        with self.lock:
            self.vehicle(index).gps.faults.clear()

    def truth(self, index: int = 0) -> dict[str, float]:
        """Ground truth of vehicle ``index``: lat/lon, ``alt_m`` above the WGS84 ellipsoid and
        ``alt_amsl_m`` (= alt_m - geoid_m, what the autopilot reports), world ENU
        position and velocity, attitude (degrees), the autopilot's horizontal estimate error, and its horizontal
        estimate and home in world ENU (``est_east_m`` ..., ``home_east_m`` ...: scoring where it lands)."""
        with self.lock:
            v = self.vehicle(index)
            lat, lon, alt = v.geodetic(v.pos_enu_m)
            e, n, u = (float(x) for x in v.pos_enu_m)
            est = v.est_pos_enu_m
            return {"lat_deg": lat, "lon_deg": lon, "alt_m": alt, "alt_amsl_m": alt - self.geoid_m, "east_m": e, "north_m": n, "up_m": u,
                    "alt_rel_m": u - float(v.home_enu_m[2]), "time_s": v.t_s,
                    "est_error_m": float(np.hypot(*(est[:2] - v.pos_enu_m[:2]))),
                    "est_east_m": float(est[0]), "est_north_m": float(est[1]),
                    "home_east_m": float(v.home_enu_m[0]), "home_north_m": float(v.home_enu_m[1]),
                    "speed_mps": float(np.linalg.norm(v.vel_enu_mps)),
                    "vel_east_mps": float(v.vel_enu_mps[0]), "vel_north_mps": float(v.vel_enu_mps[1]),
                    "vel_up_mps": float(v.vel_enu_mps[2]), "roll_deg": v.roll_deg,
                    "pitch_deg": v.pitch_deg, "yaw_deg": v.yaw_deg}

    def set_param(self, index: int, name: str, value: float) -> None:
        with self.lock:
            self.vehicle(index).params[name] = float(value)

    def start(self) -> Simulator:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="skyfix-sim", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the loop and close the sockets."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for s in self.servers:
            s.sock.close()

    def __enter__(self) -> Simulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def run_steps(self, n_steps: int) -> None:
        """Advance ``n_steps`` physics steps synchronously (no sockets); for offline use."""
        with self.lock:
            for _ in range(int(n_steps)):
                self._step()

    # ------------------------------------------------------------------ loop
    def _step(self) -> None:
        dt = self.config.dt_s
        self.config.wind.step(dt)
        for s in self.servers:
            s.vehicle.step(dt)
            s.after_step()

    def _run(self) -> None:
        cfg = self.config
        socks = {s.sock: s for s in self.servers}
        next_step = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            steps = 0
            pace = self.pace
            slow = pace is not None and pace[1] < cfg.speed and pace[0]()
            wall_dt = cfg.dt_s / (pace[1] if slow else cfg.speed)
            with self.lock:
                while now >= next_step and steps < 20:
                    self._step()
                    next_step += wall_dt
                    steps += 1
            self.paced_s += slow * steps * cfg.dt_s
            if now - next_step > 0.5:  # starved of CPU: slow down instead of racing to catch up
                self.overruns += 1
                next_step = now
            uploading = any(s.upload_active for s in self.servers)
            timeout = max(0.0, min(next_step - time.monotonic(), 0.002 if uploading else 0.05))
            try:
                ready, _, _ = select.select(list(socks), [], [], timeout)
            except (OSError, ValueError):
                if self._stop.is_set():
                    break
                raise
            for sock in ready:
                server = socks[sock]
                for _ in range(256):
                    try:
                        data, addr = sock.recvfrom(65535)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:  # e.g. ICMP port unreachable from a departed peer
                        break
                    with self.lock:
                        server.handle_datagram(data, addr)
            if uploading:
                with self.lock:
                    for s in self.servers:
                        s.service_upload()
