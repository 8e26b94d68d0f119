"""Start and stop ArduPilot Copter SITL instances (the real autopilot firmware) for tests,
benchmarks and the recovery work.

The firmware and its launcher live in ``../shared/sitl`` next to the repository, or in
the folder named by the environment variable ``SKYFIX_SITL_DIR``. Each instance gets its
own instance number (all its TCP ports shift by 10 per instance), system id and working
folder (parameters, logs); the MAVLink URL of instance N is ``tcp:127.0.0.1:5760+10N``.
The firmware blocks at start until a client connects to that port.

    with SitlFleet(count=3, speedup=5) as fleet:
        for inst in fleet:
            v = Vehicle.connect(inst.url, timeout_s=30)

Instances are always stopped (SIGTERM, then SIGKILL) when the fleet closes.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from skyfix import validate
from skyfix.drivers.mav import mavlink as M
from skyfix.errors import ConfigurationError, InputError, LinkError

log = logging.getLogger(__name__)

ENV_DIR = "SKYFIX_SITL_DIR"
BASE_PORT = 5760
PORT_STEP = 10
DEFAULT_HOME = (46.52, 6.63, 372.0, 0.0)  # lat_deg, lon_deg, alt_amsl_m, heading_deg
_LAUNCHER = "run-sitl.sh"


def sitl_dir() -> Path | None:
    """The SITL folder (``$SKYFIX_SITL_DIR`` or ``../shared/sitl`` beside the repo), or None."""
    env = os.environ.get(ENV_DIR)
    candidates = [Path(env)] if env else []
    repo = Path(__file__).resolve().parents[1]
    candidates.append(repo.parent / "shared" / "sitl")
    for c in candidates:
        if (c / _LAUNCHER).is_file() and (c / "arducopter").is_file():
            return c
    return None


def missing_reason() -> str:
    """Why SITL cannot run here (empty when it can): for skip messages."""
    if sitl_dir() is not None:
        return ""
    env = os.environ.get(ENV_DIR)
    where = f"${ENV_DIR}={env}" if env else f"../shared/sitl (set ${ENV_DIR} to point elsewhere)"
    return f"ArduPilot SITL not found: no {_LAUNCHER} + arducopter in {where}"


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _listening(port: int) -> bool:
    """True when something listens on 127.0.0.1:``port`` (read from /proc, no connection made:
    connecting would release the firmware's wait-for-client before skyfix is there)."""
    hexport = f":{port:04X}"
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 3 and fields[1].endswith(hexport) and fields[3] == "0A":  # 0A: LISTEN
                return True
    return False


def free_instances(count: int, *, start: int = 0, limit: int = 60) -> list[int]:
    """``count`` instance numbers whose ports (5760..5763 + 10N, RC 5501 + 10N) are free now."""
    found = []
    for n in range(start, limit):
        base = BASE_PORT + PORT_STEP * n
        if all(_port_free(p) for p in (base, base + 2, base + 3)):
            found.append(n)
            if len(found) == count:
                return found
    raise ConfigurationError(f"no {count} free SITL instance numbers between {start} and {limit}")


@contextlib.contextmanager
def _instance_lock():
    """A machine-wide lock (flock on a file in the temp folder) around choosing ports."""
    import fcntl

    with open(Path(tempfile.gettempdir()) / "skyfix-sitl-ports.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


@dataclass
class SitlInstance:
    """One running firmware: ``url`` for skyfix, ``system_id``, ``workdir``, ``process``."""

    instance: int
    system_id: int
    workdir: Path
    process: subprocess.Popen
    log_path: Path

    @property
    def port(self) -> int:
        return BASE_PORT + PORT_STEP * self.instance

    @property
    def url(self) -> str:
        """Primary MAVLink port (SERIAL0); the firmware waits for a client here at start."""
        return f"tcp:127.0.0.1:{self.port}"

    @property
    def url_secondary(self) -> str:
        """SERIAL1 (5762 + 10N): a second client (e.g. MAVSDK) next to skyfix."""
        return f"tcp:127.0.0.1:{self.port + 2}"

    def alive(self) -> bool:
        return self.process.poll() is None

    def release_start_wait(self, timeout_s: float = 30.0) -> None:
        """Let the firmware finish booting without its client: connect to the first port
        (where it waits at start), wait until the second port listens, hang up. The first
        port then takes a new client, and the others can be used before it."""
        deadline = time.monotonic() + timeout_s
        with socket.create_connection(("127.0.0.1", self.port), timeout=timeout_s):
            while not _listening(self.port + 2):
                if not self.alive() or time.monotonic() > deadline:
                    raise LinkError(f"SITL instance {self.instance} did not open {self.url_secondary} "
                                    f"within {timeout_s:g} s; see {self.log_path}")
                time.sleep(0.05)

    def stop(self, timeout_s: float = 5.0) -> None:
        """SIGTERM, then SIGKILL after ``timeout_s``; waits for the process to end."""
        if self.process.poll() is not None:
            return
        try:
            os.killpg(self.process.pid, signal.SIGTERM)
        except ProcessLookupError:
            return
        try:
            self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(timeout_s)


class SitlFleet:
    """``count`` SITL instances started together; a context manager that always stops them.

    ``speedup``: simulated seconds per wall second. ``wipe``: erase the stored parameters
    at every boot, reboots included (the firmware re-runs with its arguments); a fresh
    working folder (the default) starts from the default parameters without it, and keeps
    what is set across a reboot (``GPS1_TYPE`` needs one).
    ``homes``: one (lat_deg, lon_deg, alt_amsl_m, heading_deg) per instance (default: the
    first 20 m apart east of ``DEFAULT_HOME``). ``workdir``: parent folder of the instance
    folders (a temporary folder, removed on close, by default). ``first_system_id``: system
    ids are consecutive from it. ``params``: parameters set at the first boot on top of the
    firmware's default set (a defaults file in each instance folder; what needs a reboot on
    a running autopilot, e.g. ``GPS2_TYPE``, is then in force from the start).
    """

    def __init__(self, count: int = 1, *, speedup: float = 5.0, wipe: bool = False,
                 homes: list[tuple[float, float, float, float]] | None = None,
                 workdir: str | Path | None = None, first_system_id: int = 1,
                 start_timeout_s: float = 20.0, params: dict[str, float] | None = None) -> None:
        if not 1 <= int(count) <= 10:
            raise InputError(f"count must be 1..10 SITL instances, got {count}")
        self.count = int(count)
        self.speedup = validate.positive_scalar("speedup", speedup)
        self.wipe = bool(wipe)
        if homes is not None and len(homes) != self.count:
            raise InputError(f"homes must give one home per instance ({self.count}), got {len(homes)}")
        self.homes = homes or [(DEFAULT_HOME[0], DEFAULT_HOME[1] + 2.6e-4 * i, DEFAULT_HOME[2],
                                DEFAULT_HOME[3]) for i in range(self.count)]
        if not 1 <= int(first_system_id) <= 255 - self.count:
            raise InputError(f"first_system_id must leave room for {self.count} ids in 1..254")
        self.first_system_id = int(first_system_id)
        self.start_timeout_s = float(start_timeout_s)
        self.params = {str(k).upper(): validate.finite_scalar(f"params[{k}]", v) for k, v in (params or {}).items()}
        self._own_tmp = workdir is None
        self.workdir = Path(workdir) if workdir is not None else None
        self.instances: list[SitlInstance] = []

    def start(self) -> SitlFleet:
        folder = sitl_dir()
        if folder is None:
            raise ConfigurationError(missing_reason())
        if self.workdir is None:
            self.workdir = Path(tempfile.mkdtemp(prefix="skyfix-sitl-"))
        try:
            with _instance_lock():  # two fleets starting at once must not pick the same ports
                for i, n in enumerate(free_instances(self.count)):
                    self.instances.append(self._start_one(folder, n, self.first_system_id + i, self.homes[i]))
                self._wait_listening()
        except BaseException:
            self.stop()
            raise
        return self

    def _wait_listening(self) -> None:
        deadline = time.monotonic() + self.start_timeout_s
        for inst in self.instances:
            while not _listening(inst.port):
                if not inst.alive():
                    raise LinkError(f"SITL instance {inst.instance} exited at start "
                                    f"(code {inst.process.returncode}); see {inst.log_path}")
                if time.monotonic() > deadline:
                    raise LinkError(f"SITL instance {inst.instance} did not open {inst.url} "
                                    f"within {self.start_timeout_s:.0f} s; see {inst.log_path}")
                time.sleep(0.05)

    def _start_one(self, folder: Path, n: int, sysid: int, home: tuple) -> SitlInstance:
        wd = self.workdir / f"sitl{n}"
        wd.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, SITL_SPEEDUP=f"{self.speedup:g}", SITL_WIPE="1" if self.wipe else "0",
                   SITL_SYSID=str(sysid))
        if self.params:  # the firmware's defaults, then ours (a later line wins)
            defaults = wd / "defaults.parm"
            extra = "".join(f"{k} {v:g}\n" for k, v in self.params.items())
            defaults.write_text((folder / "copter.parm").read_text() + "\n" + extra)
            env["SITL_DEFAULTS"] = str(defaults)
        home_s = ",".join(f"{x:.8g}" for x in home)
        log_path = wd / "sitl.out"
        with open(log_path, "wb") as out:
            proc = subprocess.Popen([str(folder / _LAUNCHER), str(wd), str(n), home_s], env=env,
                                    stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                    start_new_session=True)  # own process group: stop() ends it all
        log.info("SITL instance %d (sysid %d) pid %d in %s", n, sysid, proc.pid, wd)
        return SitlInstance(n, sysid, wd, proc, log_path)

    def stop(self) -> None:
        """Stop every instance (and remove the temporary working folder, unless the ``with`` block
        that started them raised: then it is kept and its path logged)."""
        for inst in self.instances:
            inst.stop()
        self.instances = []
        if self._own_tmp and self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None

    def __enter__(self) -> SitlFleet:
        return self.start()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and self._own_tmp and self.workdir is not None:
            # the firmware's own output is what tells why a link stayed silent: not removed with the folder
            self._own_tmp = False
            log.warning("SITL working folder kept after %s: %s (firmware output in sitl<N>/sitl.out)",
                        exc_type.__name__, self.workdir)
        self.stop()

    def __iter__(self):
        return iter(self.instances)

    def __getitem__(self, i: int) -> SitlInstance:
        return self.instances[i]

    def __len__(self) -> int:
        return len(self.instances)


def record_tlog(url: str, path: str | Path, duration_s: float, *, fly_to_m: float = 0.0) -> int:
    """Record what the autopilot at ``url`` sends for ``duration_s`` as a MAVLink telemetry
    log (``.tlog``: 8-byte big-endian microsecond time stamp before each raw packet, the
    format of Mission Planner/MAVProxy, readable with ``mavutil.mavlink_connection(path)``).
    With ``fly_to_m`` > 0 the vehicle is armed in GUIDED and climbs to that height first,
    so the log holds a flight. Returns the number of packets written."""
    from skyfix.drivers.vehicle import Vehicle

    duration_s = validate.positive_scalar("duration_s", duration_s)
    with Vehicle.connect(url, timeout_s=30.0) as v:
        packets = [0]
        out = open(path, "wb")

        def tap(msg, t_mono) -> None:
            import struct
            out.write(struct.pack(">Q", int(time.time() * 1e6)) + msg.get_msgbuf())
            packets[0] += 1

        v.link.taps.append(tap)
        try:
            if fly_to_m > 0:
                v.wait_until(lambda s: s.gps is not None and s.gps.fix_type >= 3 and s.home is not None,
                             60.0, what="GPS fix and home")
                v.set_mode("GUIDED")
                arm_when_ready(v, 60.0)
                v.takeoff(fly_to_m)
            time.sleep(duration_s)
        finally:
            v.link.taps.remove(tap)
            out.close()
        return packets[0]


def arm_when_ready(vehicle, timeout_s: float) -> None:
    """ArduPilot refuses to arm until its EKF has settled (pre-arm checks): retry until it arms."""
    from skyfix.errors import CommandRejected

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            vehicle.arm()
            return
        except CommandRejected:
            if time.monotonic() > deadline:
                raise
            time.sleep(1.0)


class SitlClock:
    """Stamps the firmware's telemetry on another clock that runs at the same speed-up (e.g. the
    :class:`skyfix.datasets.sim.Simulator` time sharing the world with it): a drivers record's
    ``autopilot_time_s`` (the firmware's boot clock, s) plus an offset, the smallest
    ``clock()``-at-reception minus ``autopilot_time_s`` over the last ``window_s`` wall seconds (the
    least-delayed message bounds the link's delay; the window follows a drift of the two clocks, a
    firmware short of CPU runs slower than its speed-up). A record without a stamp gets ``clock()``, a
    GNSS report without a fix its reception time (ArduPilot repeats the last fix's time in it). Stamping
    at processing instead puts a fix read 1 s late 10 m off at survey speed."""

    def __init__(self, clock: Callable[[], float], speedup: float = 1.0, window_s: float = 5.0) -> None:
        self.clock = clock
        self.speedup = validate.positive_scalar("speedup", speedup)
        self.window_s = validate.positive_scalar("window_s", window_s)
        self._offsets: deque[tuple[float, float]] = deque()  # (wall s at the call, offset s)
        self._lock = threading.Lock()

    def __call__(self, record) -> float:
        now = self.clock()
        t_ap = float(getattr(record, "autopilot_time_s", math.nan))
        if not math.isfinite(t_ap):
            return now
        wall = time.time()  # drivers records carry their reception time on this clock (time_s)
        received = now - max(0.0, wall - float(record.time_s)) * self.speedup
        if getattr(record, "fix_type", M.GPS_FIX_TYPE_3D_FIX) < M.GPS_FIX_TYPE_2D_FIX:  # a dead receiver's report: "no fix" is news now, not then
            return received
        with self._lock:
            self._offsets.append((wall, received - t_ap))
            while self._offsets[0][0] < wall - self.window_s:
                self._offsets.popleft()
            offset = min(o for _, o in self._offsets)
        return t_ap + offset


class SitlTruth:
    """The firmware's true state (its SIM_STATE messages) as they arrive on a skyfix Vehicle's
    link: for scoring and for drawing the drone in other vehicles' cameras, never for an
    estimate. Connect the vehicle with ``stream_rates_hz={"SIM_STATE": ...}``.

    ``home_alt_amsl_m``: the instance's home height (``SitlFleet.homes``), for ``alt_rel_m``.
    ``geoid_m``: the undulation N that turns SIM_STATE's AMSL height into ellipsoidal height.
    0 by default: SITL's world has no geoid (its simulated receiver reports ``alt_ellipsoid``
    equal to ``alt``, see the recorded fixture), so this is the height the firmware's own GNSS
    gives skyfix; a Simulator sharing the world must use the same (``geoid_m=0``). None: EGM96
    at the position (the real world's N, which SITL's receiver does not apply). ``speedup``: the firmware's, to move a message on by its age.
    """

    def __init__(self, vehicle, home_alt_amsl_m: float, *, geoid_m: float | None = 0.0,
                 speedup: float = 1.0) -> None:
        self.speedup = validate.positive_scalar("speedup", speedup)
        self.home_alt_amsl_m = validate.finite_scalar("home_alt_amsl_m", home_alt_amsl_m)
        self.geoid_m = None if geoid_m is None else validate.finite_scalar("geoid_m", geoid_m)
        self.messages = 0
        self._last = None
        vehicle.link.taps.append(self._tap)

    @classmethod
    def connect(cls, url: str, home_alt_amsl_m: float, *, geoid_m: float | None = 0.0,
                speedup: float = 1.0, rate_hz: float = 10.0) -> SitlTruth:
        """A truth tap with its own connection (e.g. ``SitlInstance.url_secondary``, next to
        the link that flies the drone), SIM_STATE at ``rate_hz`` of simulated time, GCS
        system id 254; :meth:`close` ends it. Waits (60 s) for the port: the firmware opens
        its second and third ports only once a client is connected to the first."""
        from skyfix.drivers.vehicle import Vehicle

        deadline = time.monotonic() + 60.0
        while True:  # the firmware opens its other ports once a client is on SERIAL0
            try:
                vehicle = Vehicle.connect(url, timeout_s=30.0, source_system=254,
                                          stream_rates_hz={"SIM_STATE": rate_hz * speedup})
                break
            except LinkError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        truth = cls(vehicle, home_alt_amsl_m, geoid_m=geoid_m, speedup=speedup)
        truth._own = vehicle
        return truth

    @property
    def vehicle(self):
        """The connection :meth:`connect` opened (a skyfix ``Vehicle``), or None."""
        return getattr(self, "_own", None)

    def close(self) -> None:
        """Close the connection :meth:`connect` opened (nothing otherwise)."""
        own = getattr(self, "_own", None)
        if own is not None:
            own.close()
            self._own = None

    def _tap(self, msg, t_mono: float) -> None:
        if msg.get_type() == "SIM_STATE":
            self._last = (msg, t_mono)
            self.messages += 1

    def wait(self, timeout_s: float) -> None:
        """Block until a first SIM_STATE arrived (LinkError after ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        while self._last is None:
            if time.monotonic() > deadline:
                raise LinkError(f"no SIM_STATE within {timeout_s:g} s (is it streamed?)")
            time.sleep(0.02)

    def truth(self, world=None) -> dict[str, float]:
        """The latest truth with the keys of ``Simulator.truth``: ``lat_deg``, ``lon_deg``,
        ``alt_m`` (ellipsoidal), ``alt_amsl_m``, ``alt_rel_m`` (above home), velocities
        (ENU m/s), attitude (degrees, yaw from north clockwise), ``age_s`` since reception;
        with a :class:`skyfix.geo.LocalFrame` ``world`` also ``east_m``/``north_m``/``up_m``."""
        if self._last is None:
            raise LinkError("no SIM_STATE received yet")
        m, t_mono = self._last
        lat, lon = m.lat_int / 1e7, m.lon_int / 1e7
        if self.geoid_m is None:
            from skyfix.geoid import geoid_undulation_m
            n_m = float(geoid_undulation_m(lat, lon))
        else:
            n_m = self.geoid_m
        out = {"lat_deg": lat, "lon_deg": lon, "alt_m": m.alt + n_m, "alt_amsl_m": float(m.alt),
               "alt_rel_m": m.alt - self.home_alt_amsl_m, "vel_east_mps": float(m.ve),
               "vel_north_mps": float(m.vn), "vel_up_mps": -float(m.vd),
               "speed_mps": math.sqrt(m.vn ** 2 + m.ve ** 2 + m.vd ** 2),
               "roll_deg": math.degrees(m.roll), "pitch_deg": math.degrees(m.pitch),
               "yaw_deg": math.degrees(m.yaw) % 360.0, "age_s": time.monotonic() - t_mono}
        if world is not None:
            e, n, u = world.to_enu(lat, lon, out["alt_m"])
            out.update(east_m=float(e), north_m=float(n), up_m=float(u))
        return out

    def target_pose(self):
        """The drone as a :class:`skyfix.datasets.drone_view.TargetPose` (for ``WorldCamera``'s
        ``extra_targets``), moved on by its velocity for the age of the message."""
        from skyfix.datasets.drone_view import TargetPose
        from skyfix.geo import destination

        t = self.truth()
        dt = t["age_s"] * self.speedup  # simulated seconds since it was sent
        east, north = t["vel_east_mps"] * dt, t["vel_north_mps"] * dt
        lat, lon = t["lat_deg"], t["lon_deg"]
        if east or north:
            lat, lon = destination(lat, lon, math.degrees(math.atan2(east, north)), math.hypot(east, north))
        return TargetPose(float(lat), float(lon), t["alt_m"] + t["vel_up_mps"] * dt, yaw_deg=t["yaw_deg"],
                          pitch_deg=t["pitch_deg"], roll_deg=t["roll_deg"])
