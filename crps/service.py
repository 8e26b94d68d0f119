"""``skyfix serve``: the process that runs on each drone's companion computer.

One :class:`Service` per drone: MAVLink telemetry in (:mod:`skyfix.drivers`, reconnected
with back-off when the link is lost), the drone's :class:`skyfix.crps.node.Node` (its
fusion engine), signed peer messages in and out over the swarm transport, optionally
camera frames in (:mod:`skyfix.crps.camera_feed`), and actions out (GPS_INPUT injection
of the fused position while the drone's own GNSS is lost, ``--inject``). Everything goes
to the MCAP log (``--log``) and the live Foxglove view (``--live``).

Threads: the drivers' MAVLink reader; the MAVLink supervisor (connect, reconnect with
back-off); the transport's receive callbacks, which only verify and queue; the main loop
(10 Hz: peer messages, own telemetry, fusion, estimate and heartbeat out, peer
book-keeping). Queues are bounded; peer messages wait rather than being dropped, camera
frames are dropped when the detector is behind. SIGINT/SIGTERM stop it cleanly.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from skyfix.crps import messages as M
from skyfix.crps.inject_policy import InjectionPolicy
from skyfix.crps.node import ECHO_VELOCITY_SIGMA_MPS, Node
from skyfix.crps.observation import POINTING_SIGMA_DEG
from skyfix.crps.outputs import Outputs
from skyfix.crps.swarm import PeerTable
from skyfix.crps.transport import Endpoints, Transport, ZenohTransport, split_key
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import LinkError, SkyfixError
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.engine import FusionEngine

log = logging.getLogger("skyfix.crps.service")

INBOX_SIZE = 4096           # peer datagrams waiting for the main loop (3 peers x 40 msg/s: ~30 s)
PEER_FIX_PERIOD_S = 0.5     # a peer's fused position goes into this drone's engine at most at 2 Hz (its velocity always)
LINK_LOST_RECONNECT_S = 0.5  # link marked lost (no heartbeat for 2 s) this long before the link is reopened
BACKOFF_S = (0.5, 5.0)      # first and longest wait between MAVLink connection attempts
GNSS_OK_FIX_TYPE = 3



#: share of a receiver's wandering GNSS error that the swarm's receivers have in common (FusionConfig.gnss_common_share):
#: drones tens of metres apart see the same satellites through the same atmosphere (AGI's GPS error budget: ~90 %
#: of a standalone receiver's range-error variance). Fused as independent, two helpers' fixes halved that shared
#: error's variance: the drone they placed stated a sigma 2.4x too small in variance against the truth
#: (benchmarks/recovery_replay.py, ten recorded recoveries); 0 for receivers whose errors are their own
GNSS_COMMON_SHARE = 0.9


def fusion_config(roster: tuple[str, ...] | None, lag_s: float, gnss_common_share: float = GNSS_COMMON_SHARE
                  ) -> FusionConfig:
    """The node's fusion settings: ``roster`` the trusted observers; a relative source is silent, and no
    longer among an estimate's sources, only when nothing came for the engine's usual time-out AFTER the
    lag. Peers' camera observations reach the node a frame's pipeline late (seconds on a loaded companion)
    and are still fused while inside the lag; the plain 2 s time-outs called such a helper silent between
    two of its frames and kept it on 5 s of probation, unfused. GPS_RAW_INT's time_usec is its send time
    (ArduPilot: fix time + time since): a fix up to one 5 Hz receiver period old (``gnss_fix_age_max_s``);
    the same fix re-sent is dropped. ``gnss_common_share``: see :data:`GNSS_COMMON_SHARE`."""
    base = FusionConfig()
    # a helper's pointing error is its heading reference's, shared by all its frames (crps.observation's figure)
    return FusionConfig(roster=tuple(roster or ()), relative_timeout_s=float(lag_s) + base.relative_timeout_s,
                        contributing_window_s=float(lag_s) + base.contributing_window_s, gnss_fix_age_max_s=0.2,
                        gnss_common_share=float(gnss_common_share), relative_pointing_sigma_deg=POINTING_SIGMA_DEG)


@dataclass(frozen=True)
class ServiceConfig:
    """Everything ``skyfix serve`` is told; see ``skyfix serve --help`` for each field."""

    drone_id: str
    mavlink_url: str
    endpoints: Endpoints
    key: bytes
    swarm: str = "skyfix"
    roster: tuple[str, ...] | None = None
    origin: tuple[float, float, float] | None = None
    log_path: Path | None = None
    live: str | None = None
    estimate_hz: float = 10.0
    inject_hz: float = 5.0  # GPS_INPUT rate, per wall second (ArduPilot calls a GPS unhealthy beyond ~245 ms gaps)
    lag_s: float = 2.0      # fusion's smoothing window, s of the clock (late camera observations within it count)
    max_lag_s: float | None = None  # above lag_s: the window grows up to this while camera observations come late
    gnss_common_share: float = GNSS_COMMON_SHARE  # the swarm's receivers' shared error (FusionConfig.gnss_common_share)
    # 1-sigma error (m/s) of the autopilot's velocity while it flies on the injected fix: its EKF, with no other
    # velocity source, echoes that fix (node.ECHO_VELOCITY_SIGMA_MPS); None: its velocity does not depend on the
    # injected position (optical flow, or a simulator reporting its true velocity)
    injected_velocity_sigma_mps: float | None = ECHO_VELOCITY_SIGMA_MPS
    heartbeat_hz: float = 2.0
    inject: bool = False
    safety: object | None = None  # a drivers SafetyGate installed on the vehicle at every (re)connection
    help: object | None = None  # a crps.help_loop.HelpSetup: ask for help on GNSS loss, answer others' requests
    clock: Callable[[], float] | None = None  # the swarm's clock, s (None: UNIX time; a simulator's time in tests)
    time_of: Callable[[object], float] | None = None  # telemetry record -> clock (None: its reception time)


class Service:
    """One drone's service; :meth:`run` until ``stop`` is set. ``transport`` replaces zenoh (tests)."""

    def __init__(self, config: ServiceConfig, transport: Transport | None = None) -> None:
        self.cfg = config
        self.clock = config.clock or time.time
        self.codec = M.SwarmCodec(config.drone_id, config.key, config.roster, clock=self.clock)
        self.peers = PeerTable()
        self.outputs = Outputs(config.log_path, config.live, name=f"skyfix {config.drone_id}")
        self.node: Node | None = None
        self.vehicle = None
        self.injector = None
        self.camera = None
        self.help = None  # the HelpLoop, once fusion has an origin (config.help)
        self.stop = threading.Event()
        self.inbox: queue.Queue[tuple[float, M.Envelope]] = queue.Queue(INBOX_SIZE)
        self.counters = {"mavlink_connects": 0, "mavlink_lost": 0, "inbox_overflow": 0, "sent": 0,
                         "estimates": 0, "loop_errors": 0, "loop_faults": 0, "help_faults": 0}
        self._peer_fix_s: dict[str, float] = {}
        self._gnss_echo = True  # GPS_RAW_INT shows the injected fix (GPS1_TYPE=14), not a receiver
        self._gps_switched = False  # the autopilot flies on the injected GPS instance (use_injected_gps)
        self._inject_job: threading.Thread | None = None  # starting or stopping the injection
        self._inject_notes: list[dict] = []  # what that job did, logged by the main loop
        self._dropped_logged: dict[str, int] = {}
        self.inject_policy = InjectionPolicy(self)  # what is injected while GNSS is lost (crps.inject_policy)
        _warm_up()
        try:
            self.transport = transport or ZenohTransport(config.swarm, config.drone_id, config.endpoints)
        except SkyfixError:
            self.outputs.close()
            raise
        self.transport.subscribe(self._on_datagram)
        self._mav_thread = threading.Thread(target=self._mavlink_loop, daemon=True, name="skyfix-serve-mavlink")

    @property
    def faults(self) -> int:
        """Unexpected exceptions this service survived (logged with their tracebacks); 0 in a sound run."""
        return self.counters["loop_faults"] + self.counters["help_faults"]

    # -- life cycle ---------------------------------------------------------------------------
    def run(self) -> None:
        """The main loop; returns after :attr:`stop` is set, everything closed."""
        self._mav_thread.start()
        period = 1.0 / self.cfg.estimate_hz
        next_hb = next_tick = time.monotonic()
        try:
            while not self.stop.is_set():
                try:
                    self._drain_inbox()
                    for event in self.peers.check(self.clock()):  # every tick: lost at most 1.5 s + one period after
                        self._peer_event(event)
                    self._tick()
                    now = time.monotonic()
                    if now >= next_hb:
                        next_hb = now + 1.0 / self.cfg.heartbeat_hz
                        self._heartbeat()
                except SkyfixError as exc:  # a service never dies of one bad input: log it, go on
                    self.counters["loop_errors"] += 1
                    log.error("main loop: %s", exc)
                except Exception:  # noqa: BLE001 - nor of a fault of its own: the next tick may still inject
                    self.counters["loop_faults"] += 1
                    _log_fault("main loop", self.counters["loop_faults"])
                next_tick += period
                self.stop.wait(max(0.0, next_tick - time.monotonic()))
                if time.monotonic() - next_tick > 1.0:  # far behind (machine stalled): do not burst
                    next_tick = time.monotonic()
        finally:
            self.close()

    def close(self) -> None:
        self.stop.set()
        if self._mav_thread.is_alive():
            self._mav_thread.join(timeout=3.0)
        self.transport.close()
        if self.camera is not None:
            self.camera.stop()
        if self.help is not None:
            self.help.close()
        if self.vehicle is not None:
            self.vehicle.close()
        self.outputs.json("/swarm/dropped", self._drop_report())
        if self.node is not None:
            self.node.close()
        self.outputs.close()
        log.info("service %s stopped: %s", self.cfg.drone_id, self._drop_report())

    # -- peers ---------------------------------------------------------------------------------
    def _on_datagram(self, key: str, data: bytes) -> None:
        """Transport thread: verify and queue; a bad datagram is dropped and counted by the codec."""
        parts = split_key(key)
        env = self.codec.decode(data)
        if env is None:
            return
        if parts is None or parts[1] != env.sender:  # signed by one drone, published under another's key
            self.codec.dropped["wrong_key_expr"] += 1
            return
        try:
            self.inbox.put((self.clock(), env), timeout=0.5)  # heard now, even if the main loop is busy
        except queue.Full:
            self.counters["inbox_overflow"] += 1
            log.error("peer inbox full for 0.5 s: main loop stalled; message from %s lost", env.sender)

    def _drain_inbox(self) -> None:
        while True:
            try:
                heard_s, env = self.inbox.get_nowait()
            except queue.Empty:
                return
            self._handle(env, heard_s)

    def _handle(self, env: M.Envelope, heard_s: float) -> None:
        event = self.peers.heard(env, heard_s)
        if event is not None:
            self._peer_event(event)
        body = env.body
        self.outputs.json(f"/swarm/in/{type(body).__name__}", M.to_builtins(env), env.time_s)
        if self.help is not None:
            self.help.receive(env, heard_s)
        if self.node is None:
            return
        try:
            if isinstance(body, M.FusedEstimate):
                self.outputs.location_fix(env.sender, body.time_s, body.lat_deg, body.lon_deg, body.alt_m,
                                          body.cov_enu_m2)
                fix = None
                if body.time_s - self._peer_fix_s.get(env.sender, -math.inf) >= PEER_FIX_PERIOD_S:
                    self._peer_fix_s[env.sender] = body.time_s
                    fix = M.estimate_fix(body, env.sender)
                self.node.add_peer(env.sender, body.time_s, body.vel_enu_mps, fix)
            elif isinstance(body, M.RelativeObs) and body.target_id == self.cfg.drone_id:
                self.node.add_relative(M.relative_observation(body, env.sender))
        except (SkyfixError, ValueError) as exc:  # signed but not physical (NaN, bad covariance...)
            self.codec.dropped["invalid_content"] += 1
            log.warning("message from %s dropped: %s", env.sender, exc)

    def _peer_event(self, event) -> None:
        log.info("peer %s %s", event.drone_id, event.kind)
        self.outputs.json("/swarm/peers", {"event": event.kind, "drone": event.drone_id, "time_s": event.time_s},
                          event.time_s)

    def _publish(self, body) -> None:
        env, data = self.codec.seal(body)
        topic = M.TOPIC_OF[type(body)]
        try:
            self.transport.publish(topic, data)
        except Exception as exc:  # noqa: BLE001 - zenoh raises its own errors; the loop must go on
            log.warning("swarm publish on %s failed: %s", topic, exc)
            return
        self.counters["sent"] += 1
        self.outputs.json(f"/swarm/out/{type(body).__name__}", M.to_builtins(env), env.time_s)

    def _heartbeat(self) -> None:
        est = self.node.latest.get(self.cfg.drone_id) if self.node is not None else None
        mav_ok = self.vehicle is not None and self.vehicle.state.link_ok
        if est is None:
            health, source, sigma = "no_fix", "none", math.nan
        else:
            sigma = est.sigma_horizontal_m
            source = "gnss" if "gnss" in est.sources else (est.sources[0] if est.sources else "prediction")
            health = "ok" if mav_ok and sigma < 5.0 else "degraded"
        self._publish(M.Heartbeat(health, source, sigma, mav_ok, len(self.peers.live())))
        report = self._drop_report()
        if report != self._dropped_logged:
            self._dropped_logged = report
            self.outputs.json("/swarm/dropped", report)

    def _drop_report(self) -> dict[str, int]:
        return {**dict(self.codec.dropped), "inbox_overflow": self.counters["inbox_overflow"]}

    def sim_camera(self):
        """``--camera sim``: the simulator's renderer pointed from this drone's fix at the nearest peer."""
        from skyfix.crps.sim_camera import SimCamera

        def own():
            fix = self.node.fix(self.cfg.drone_id, self.clock()) if self.node is not None else None
            return None if fix is None else (fix.lat_deg, fix.lon_deg, fix.alt_m)

        def peers():
            return [(p.lat_deg, p.lon_deg, p.alt_m) for p in self.peers.snapshot()
                    if not p.lost and math.isfinite(p.alt_m)]

        return SimCamera(own, peers)

    # -- fusion ---------------------------------------------------------------------------------
    def _tick(self) -> None:
        vehicle = self.vehicle
        state = vehicle.state if vehicle is not None else None
        if self.node is None:
            origin = self.cfg.origin or _origin_of(state)
            if origin is None:
                return
            # the swarm's roster is the fusion's roster of trusted observers
            config = fusion_config(self.cfg.roster, self.cfg.lag_s, self.cfg.gnss_common_share)
            self.node = Node(self.cfg.drone_id, origin, lag_s=self.cfg.lag_s, config=config, max_lag_s=self.cfg.max_lag_s,
                             make_sink=self.outputs.fusion_sink)
            log.info("fusion origin %.7f, %.7f, %.2f m", *origin)
        if state is not None and state.link_ok:
            self.node.add_telemetry(self.cfg.drone_id, state, self.cfg.time_of or (lambda m: m.time_s),
                                    use_gnss=self.injector is None or not self._gnss_echo,
                                    velocity_sigma_mps=None if self.injector is None else self.cfg.injected_velocity_sigma_mps)
        estimates = self.node.update((self.cfg.drone_id,))  # peers publish their own
        now = self.clock()
        fix = self.node.fix(self.cfg.drone_id, now)
        if self.help is None and self.cfg.help is not None and state is not None and state.home is not None:
            self.help = self.cfg.help.build(self)
        if self.help is not None:
            try:
                self.help.step(now, state)
            except Exception:  # noqa: BLE001 - a fault in the help logic must not stop the estimate and the injection
                self.counters["help_faults"] += 1
                _log_fault("help step (the estimate and the injection go on)", self.counters["help_faults"])
        if fix is None:
            return
        own = next((e for e in estimates if e.drone_id == self.cfg.drone_id), self.node.latest[self.cfg.drone_id])
        self.counters["estimates"] += 1
        self._publish(M.FusedEstimate(now, fix.lat_deg, fix.lon_deg, fix.alt_m, M._flat(fix.cov_enu_m2),
                                      tuple(float(v) for v in own.vel_enu_mps), tuple(own.sources)))
        self.outputs.json(f"/estimate/{self.cfg.drone_id}", {**own.to_dict(), "now_s": now}, own.time_s)
        self.outputs.location_fix(self.cfg.drone_id, now, fix.lat_deg, fix.lon_deg, fix.alt_m, fix.cov_enu_m2)
        if self.cfg.inject and vehicle is not None:
            self._injection(vehicle, state, fix)

    def _injection(self, vehicle, state, fix) -> None:
        """GPS_INPUT of the fused fix while the drone's own GNSS is lost; stop when it is back. Switching takes
        several parameter round trips: done on a worker thread, the loop (fusion, swarm) goes on meanwhile."""
        gnss_lost = state is not None and state.gps is not None and state.gps.fix_type < GNSS_OK_FIX_TYPE
        if self.help is not None and self.help.recovering:
            gnss_lost = True  # until fusion finds GNSS healthy and consistent again, whatever the receiver says
        job = self._inject_job
        if job is not None:
            if job.is_alive():
                return
            self._inject_job = None
            for action in self._inject_notes:
                self.outputs.json("/action", action)
            self._inject_notes = []
        if gnss_lost and self.injector is None:
            self._inject_job = threading.Thread(target=self._start_injection, args=(vehicle, fix.sigma_horizontal_m),
                                                daemon=True, name=f"skyfix-inject-{self.cfg.drone_id}")
            self._inject_job.start()
        elif not gnss_lost and self.injector is not None and state.gps is not None:
            injector, self.injector = self.injector, None
            self._inject_job = threading.Thread(target=self._stop_injection, args=(vehicle, injector), daemon=True,
                                                name=f"skyfix-inject-{self.cfg.drone_id}")
            self._inject_job.start()

    def _start_injection(self, vehicle, sigma_h_m: float) -> None:
        try:
            self._switch_gps(vehicle, True)
            echo = _reports_injection(vehicle)
            # the message's time stamp is UNIX time (GPS week/ms), whatever the swarm's clock
            injector = vehicle.start_gps_injection(self.inject_policy.fix, rate_hz=self.cfg.inject_hz)
        except SkyfixError as exc:
            log.error("cannot inject the fused position: %s", exc)
            return
        self._gnss_echo, self.injector = echo, injector
        self._inject_notes.append({"action": "gps_injection_start", "sigma_h_m": sigma_h_m,
                                   "gps_raw_echoes_injection": echo, "injected_gps_primary": self._gps_switched})

    @property
    def injection_withheld(self) -> bool:
        """True while no position is injected on purpose (:attr:`InjectionPolicy.withheld`): the help loop then
        lands the drone."""
        return self.injector is not None and self.inject_policy.withheld

    def _stop_injection(self, vehicle, injector) -> None:
        injector.stop()
        self.inject_policy.gnss_back()
        self._switch_gps(vehicle, False)
        self._inject_notes.append({"action": "gps_injection_stop", "injected_gps_primary": self._gps_switched})

    def _switch_gps(self, vehicle, on: bool) -> None:
        """ArduPilot set up for it (GPS_AUTO_SWITCH=0): fly on the injected GPS instance while injecting, so a
        receiver that comes back wrong is not used; without that setup the injection alone is sent."""
        if vehicle.autopilot != "ardupilot" or (not on and not self._gps_switched):
            return
        try:
            vehicle.use_injected_gps(on)
            self._gps_switched = on
        except SkyfixError as exc:
            log.warning("injected GPS %s: %s", "not made primary" if on else "still primary", exc)

    # -- MAVLink supervision ----------------------------------------------------------------------
    def _mavlink_loop(self) -> None:
        delay = BACKOFF_S[0]
        lost_since = None
        while not self.stop.is_set():
            if self.vehicle is None:
                try:
                    self.vehicle = Vehicle.connect(self.cfg.mavlink_url, timeout_s=2.0, heartbeat_timeout_s=2.0)
                except LinkError as exc:
                    log.warning("MAVLink %s: %s; next attempt in %.1f s", self.cfg.mavlink_url, exc, delay)
                    self.stop.wait(delay)
                    delay = min(2 * delay, BACKOFF_S[1])
                    continue
                delay, lost_since = BACKOFF_S[0], None
                if self.cfg.safety is not None:
                    self.vehicle.set_safety(self.cfg.safety)
                self.counters["mavlink_connects"] += 1
                self._mav_event("connected")
            elif not self.vehicle.state.link_ok:
                lost_since = lost_since or time.monotonic()
                if time.monotonic() - lost_since > LINK_LOST_RECONNECT_S:
                    self.counters["mavlink_lost"] += 1
                    self._mav_event("lost")
                    vehicle, self.vehicle, self.injector = self.vehicle, None, None
                    vehicle.close()
                    continue
            else:
                lost_since = None
            self.stop.wait(0.1)

    def _mav_event(self, kind: str) -> None:
        log.info("MAVLink %s %s", self.cfg.mavlink_url, kind)
        self.outputs.json("/mavlink/state", {"event": kind, "url": self.cfg.mavlink_url, **self.counters})


def _warm_up() -> None:
    """Pay the one-time costs (scipy.stats behind the engine's gates, foxglove's schemas: seconds on a
    loaded companion computer, holding the interpreter) before peers are listened to, so they do not
    silence a running service."""
    import foxglove.messages  # noqa: F401

    FusionEngine((0.0, 0.0, 0.0))


def _reports_injection(vehicle) -> bool:
    """Whether the autopilot's GPS_RAW_INT is the injected fix itself: ArduPilot with GPS1_TYPE (GPS_TYPE
    before 4.6) = 14; with GPS2_TYPE=14 it stays the real receiver, whose return fusion must see."""
    if vehicle.autopilot != "ardupilot":
        return True
    for name in ("GPS1_TYPE", "GPS_TYPE"):
        try:
            return int(vehicle.get_param(name, timeout_s=0.5, retries=2)) == 14
        except SkyfixError:
            continue
    return True


def _origin_of(state) -> tuple[float, float, float] | None:
    """The local frame's origin: the autopilot's home, else its first 3-D GNSS fix (ellipsoidal m)."""
    if state is None:
        return None
    if state.home is not None and math.isfinite(getattr(state.home, "alt_ellipsoid_m", math.nan)):
        return state.home.lat_deg, state.home.lon_deg, state.home.alt_ellipsoid_m
    gps = state.gps
    if gps is not None and gps.fix_type >= GNSS_OK_FIX_TYPE and math.isfinite(gps.alt_ellipsoid_m):
        return gps.lat_deg, gps.lon_deg, gps.alt_ellipsoid_m
    return None


def _log_fault(where: str, count: int) -> None:
    """Log an unexpected exception with its traceback: the first 10, then every 100th (a fault that repeats every
    tick must not fill the disk)."""
    if count <= 10 or count % 100 == 0:
        log.exception("%s failed (%d so far)", where, count)
