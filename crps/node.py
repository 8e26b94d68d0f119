"""The onboard node: one road from measurements to estimates and actions.

A :class:`Node` owns a drone's :class:`skyfix.fusion.FusionEngine`. Measurements come in
from the autopilot (:class:`skyfix.drivers.state.VehicleState` snapshots: GNSS from
GPS_RAW_INT, velocity from GLOBAL_POSITION_INT), from peers (their fused fixes and their
camera observations of this drone) and from this drone's own cameras; :meth:`Node.update`
runs the smoother and returns the estimates; :meth:`Node.fix` is the newest estimate
moved to the present, the position handed to the autopilot (GPS_INPUT) through the
drivers' injector and safety gate.

Both ``skyfix demo`` (one node fed with the whole simulated fleet) and ``skyfix serve``
(one node per drone, peers over the swarm network) go through this class. Every call
given to the engine is recorded, in call order, to a measurement log sink (the JSON-lines
:class:`skyfix.fusion.log.MeasurementLog` or the MCAP :class:`skyfix.fusion.log_mcap.McapLog`),
so ``skyfix fusion replay`` reproduces the estimates. Thread-safe: one lock around the engine.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from typing import Protocol

import numpy as np

from skyfix.crps.arrival_lag import ArrivalLag
from skyfix.errors import NotAvailableError, SkyfixError
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.engine import FusionEngine
from skyfix.fusion.estimate import Estimate
from skyfix.types import GeoFix, RelativeObservation

log = logging.getLogger(__name__)

#: A drone's acceleration, 1-sigma per axis (m/s^2), when :meth:`Node.fix` moves an estimate on with its velocity:
#: ArduPilot's default waypoint acceleration (WPNAV_ACCEL 250 cm/s^2): a drone braking to a stop (RTL over home)
#: leaves a held 5 m/s velocity 5 m wrong after 2 s. Taken as zero, a MAVLink drop's stale velocity (no autopilot
#: velocity for seconds) moved the fix 13 m past home with a 2.4 m sigma (two fault tests at once under load).
EXTRAPOLATION_ACCEL_MPS2 = 2.5

#: Velocity 1-sigma of GLOBAL_POSITION_INT's velocity, m/s (an EKF's output, not raw Doppler).
TELEMETRY_VELOCITY_SIGMA_MPS = 0.2
#: While the autopilot flies on the position skyfix injects, an EKF that takes no other velocity source
#: (ArduPilot with EK3_SRC2_VELXY 0) keeps its IMU's fast motion but takes the slow part of its velocity
#: from the injected positions: that part echoes the injected fix's own error rate, a wandering error of
#: ECHO_VELOCITY_SIGMA_MPS correlated over ECHO_CORRELATION_S. Fitted on ArduPilot Copter SITL (GLOBAL_POSITION_INT
#: velocity minus SIM_STATE's, over the first 16-17 s of injection while the helpers' observations still came,
#: three runs): 0.25-1.5 m/s per axis (worst run 1.5 m/s north, while the drone turned for home), 1/e time
#: 0.4-4 s. Taken as white 0.2 m/s it outvoted the helpers' observations and the drone ran away; a 1 m/s,
#: 10 s echo (walk 0.45 m/s per sqrt s) still let the fix fall 4 m behind on the way home. It is fused as the
#: velocity bias's walk of a Gauss-Markov process of that size (sigma sqrt(2 / tau) per sqrt s: 1.2 m/s per
#: sqrt s), which the helpers' observations then measure.
ECHO_VELOCITY_SIGMA_MPS = 1.5
ECHO_CORRELATION_S = 3.0


def echo_bias_walk(sigma_mps: float) -> float:
    """Bias random walk (m/s per sqrt s) matching an echo error of ``sigma_mps`` over ECHO_CORRELATION_S."""
    return sigma_mps * math.sqrt(2.0 / ECHO_CORRELATION_S)


def held_velocity_cov_m2(dt_s: float) -> np.ndarray:
    """(3, 3) ENU m^2 a position moved on ``dt_s`` at a held velocity gains: the drone may accelerate at
    :data:`EXTRAPOLATION_ACCEL_MPS2` meanwhile, (a dt^2 / 2)^2 per axis."""
    return np.eye(3) * (0.5 * EXTRAPOLATION_ACCEL_MPS2 * dt_s * dt_s) ** 2


class LogSink(Protocol):
    """Where a node records the engine's inputs (the measurement-log writers satisfy it)."""

    def record(self, op: str, args: dict | None = None) -> None: ...

    def truth(self, drone_id: str, time_s: float, lat_deg: float, lon_deg: float, alt_m: float) -> None: ...

    def close(self) -> None: ...


def log_header(engine: FusionEngine) -> dict:
    """The measurement-log header that lets replay rebuild ``engine`` (origin, lag, configuration)."""
    return {"origin": list(engine.origin), "lag_s": engine.lag_s, "config": engine.config.to_dict()}


class Node:
    """Fusion of one drone (and whatever else it hears of) in the ENU frame about ``origin``.

    ``origin`` (lat_deg, lon_deg, ellipsoidal alt_m); ``lag_s`` and ``config`` as for
    :class:`FusionEngine`; ``max_lag_s`` above ``lag_s``: the lag follows how late camera observations
    arrive, up to that (:class:`skyfix.crps.arrival_lag.ArrivalLag`); ``sink`` opened by ``make_sink(header)`` receives every engine
    input. Times are seconds on one clock shared by every input (UNIX time in the
    service, simulated time in the demo).
    """

    def __init__(self, drone_id: str, origin: tuple[float, float, float], *, lag_s: float = 2.0,
                 config: FusionConfig | None = None, max_lag_s: float | None = None,
                 make_sink: Callable[[dict], LogSink] | None = None) -> None:
        self.drone_id = str(drone_id)
        self.engine = FusionEngine(origin, lag_s=lag_s, config=config)
        self.arrival_lag = ArrivalLag(lag_s, lag_s if max_lag_s is None else max_lag_s)
        self.frame = self.engine.frame
        self._sink = make_sink(log_header(self.engine)) if make_sink is not None else None
        self._lock = threading.Lock()
        self._gps_seen: dict[str, float] = {}
        self.latest: dict[str, Estimate] = {}
        self.n_refused = 0
        self.observed_s: dict[str, float] = {}  # per target: the newest camera observation of it fused, clock s

    # -- inputs ---------------------------------------------------------------------------
    def add_telemetry(self, drone_id: str, state, time_of: Callable[[object], float], *,
                      use_gnss: bool = True, velocity_sigma_mps: float | None = None) -> None:
        """Velocity and (new) GNSS of ``drone_id`` from a drivers ``VehicleState`` snapshot.

        ``time_of(message)`` maps a telemetry record to the node's clock. ``use_gnss`` False
        while skyfix injects this drone's position: the receiver report would only echo it.
        ``velocity_sigma_mps``: while the autopilot flies on the injected fix, the 1-sigma of its velocity's
        echo of that fix (:data:`ECHO_VELOCITY_SIGMA_MPS`; None: the EKF's usual white error only), fused as
        the velocity bias's walk (:func:`echo_bias_walk`).
        Heights: the fix's ellipsoidal height (``GnssFix.alt_ellipsoid_m``); sigmas: the
        receiver's h_acc/v_acc in metres, else HDOP (unitless) for the engine's UERE model.
        """
        vel = state.velocity
        if vel is not None:
            walk = {} if velocity_sigma_mps is None else {"bias_walk_mps_per_sqrt_s": echo_bias_walk(velocity_sigma_mps)}
            self._call("velocity", drone_id=drone_id, time_s=time_of(vel), sigma_mps=TELEMETRY_VELOCITY_SIGMA_MPS,
                       vel_enu_mps=[vel.east_mps, vel.north_mps, -vel.down_mps], **walk)
        gps = state.gps
        if gps is None or not use_gnss or gps.time_s == self._gps_seen.get(drone_id):
            return
        self._gps_seen[drone_id] = gps.time_s
        def known(x: float) -> float | None:
            return x if math.isfinite(x) and x > 0 else None

        self._call("gnss", drone_id=drone_id, time_s=time_of(gps), lat_deg=gps.lat_deg, lon_deg=gps.lon_deg,
                   alt_m=gps.alt_ellipsoid_m, fix_type=gps.fix_type, satellites=gps.satellites,
                   h_sigma_m=known(gps.h_acc_m), v_sigma_m=known(gps.v_acc_m), hdop=known(gps.hdop))

    def add_relative(self, obs: RelativeObservation) -> None:
        """A camera observation of one drone by another (this drone's or a peer's); how late it came
        (engine time minus exposure) sizes the lag for the next ones."""
        with self._lock:
            now_s = self.engine.now_s
            self.arrival_lag.arrived(now_s, now_s - float(obs.time_s))
            lag_s = self.arrival_lag.propose(now_s)
            if lag_s is not None:
                if self._sink is not None:
                    self._sink.record("lag", {"lag_s": lag_s})
                self.engine.set_lag(lag_s)
                log.info("node %s: fusion lag %.2f s (camera observations arrive late)", self.drone_id, lag_s)
        refused = self.n_refused
        self._call("relative", obs=obs)
        if self.n_refused == refused:
            self.observed_s[obs.target_id] = max(obs.time_s, self.observed_s.get(obs.target_id, -math.inf))

    def add_fix(self, drone_id: str, fix: GeoFix) -> None:
        """An absolute position of ``drone_id`` whose errors are independent from fix to fix (a tag fix)."""
        self._call("fix", drone_id=drone_id, fix=fix)

    def add_peer(self, drone_id: str, time_s: float, vel_enu_mps, fix: GeoFix | None = None) -> None:
        """A peer's fused estimate at ``time_s``: its velocity (m/s, ENU) and, when given, its position.

        The position rides on the peer's GNSS, whose error wanders for about a minute: fused as a
        correlated fix (:meth:`FusionEngine.add_fix`). The velocity keeps the peer, an observer of this
        drone, known between its fixes; it is the peer's autopilot velocity, bias-corrected by the peer's
        fusion, taken at the telemetry's 1-sigma (the message carries no velocity covariance).
        """
        if fix is not None:
            self._call("fix", drone_id=drone_id, fix=fix, correlated=True)
        self._call("velocity", drone_id=drone_id, time_s=time_s, vel_enu_mps=list(vel_enu_mps),
                   sigma_mps=TELEMETRY_VELOCITY_SIGMA_MPS)

    def record_truth(self, drone_id: str, time_s: float, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """Ground truth into the log (simulations only; never given to the engine)."""
        if self._sink is not None:
            self._sink.truth(str(drone_id), time_s, lat_deg, lon_deg, alt_m)

    # -- answers --------------------------------------------------------------------------
    def update(self, drone_ids: tuple[str, ...] | None = None) -> list[Estimate]:
        """Run the smoother; the estimates of ``drone_ids`` (default: every drone), localised ones only,
        also kept in ``latest``. (A covariance per estimate: ask only for the drones needed.)"""
        with self._lock:
            if self._sink is not None:
                self._sink.record("update")
            self.engine.update()
            out = []
            for drone_id in self.engine.drone_ids if drone_ids is None else drone_ids:
                if drone_id not in self.engine.drone_ids:
                    continue
                try:
                    est = self.engine.estimate(drone_id)
                except NotAvailableError:
                    continue
                except SkyfixError as exc:  # e.g. a peer silent for longer than the lag: no estimate now
                    log.debug("node %s: no estimate of %s: %s", self.drone_id, drone_id, exc)
                    continue
                out.append(est)
                self.latest[drone_id] = est
            return out

    def fix(self, drone_id: str, now_s: float, time_stamp_s: float | None = None, frame: bool = False
            ) -> GeoFix | None:
        """Newest estimate of ``drone_id`` moved to ``now_s`` with its fused velocity (None before the
        first); ``time_stamp_s`` stamps the GeoFix (default ``now_s``); ``frame``: its covariance in the
        swarm's GNSS frame (:attr:`skyfix.fusion.Estimate.decision_cov_enu_m2`)."""
        est = self.latest.get(str(drone_id))
        if est is None:
            return None
        dt = max(0.0, now_s - est.time_s)
        enu = est.enu_m + est.vel_enu_mps * dt
        lat, lon, alt = (float(c) for c in self.frame.to_geodetic(*enu))
        cov = (est.decision_cov_enu_m2 if frame else est.cov_enu_m2) + est.vel_cov_enu_m2ps2 * dt * dt \
            + held_velocity_cov_m2(dt)
        return GeoFix(lat, lon, alt, cov, now_s if time_stamp_s is None else time_stamp_s, "skyfix.fusion")

    def close(self) -> None:
        """Flush and close the log."""
        if self._sink is not None:
            self._sink.close()

    # -- internals ---------------------------------------------------------------------------
    def _call(self, op: str, **args) -> None:
        """Record and apply one engine input; a refused input is counted and logged, never raised."""
        with self._lock:
            if self._sink is not None:
                self._sink.record(op, args)
            try:
                getattr(self.engine, f"add_{op}")(**args)
            except SkyfixError as exc:
                self.n_refused += 1
                if self.n_refused <= 5 or self.n_refused % 1000 == 0:  # counted always, logged sparingly
                    log.warning("node %s: %s input refused (%d so far): %s", self.drone_id, op, self.n_refused, exc)

