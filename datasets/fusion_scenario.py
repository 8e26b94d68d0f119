"""Measurement-level simulation of a three-drone survey for the fusion engine.

Drone ``"A"`` flies a lawnmower survey; helpers ``"B"`` and ``"C"`` fly near it
(30-80 m, seen from A at least 60 degrees apart) and report where they see A. Every
sensor is simulated at the message level, with the same arguments the engine's
``add_*`` methods take (``skyfix.fusion``, see ``feed``):

* GNSS, 5 Hz per drone: white noise ``gnss_h_sigma_m`` per horizontal axis and
  ``gnss_v_sigma_m`` vertical, optionally plus a Gauss-Markov wander (``gnss_gm_*``) and
  multipath outliers (:func:`correlated_scenario`); fix type 3, 10-14 satellites, hdop
  0.8-1.2; the reported accuracy is the total of white and wandering parts.
* Velocity, 10 Hz per drone, in the ENU axes at the drone: truth + bias + white noise.
  The bias is a random walk (see :class:`NoiseModel`) as for an autopilot velocity that
  is not GNSS-aided (optical flow scaled by a height estimate, or IMU + drag model).
* Altitude (barometer, referred to the ellipsoid), 10 Hz: white noise and an optional
  slow random-walk drift.
* Relative observations, 5 Hz from each helper of A: the offset A - helper in the ENU
  axes at the observer, range noise 3 % and bearing noise 0.2 deg (1-sigma per axis),
  with the covariance a monocular ranger would report (the shared model of
  :mod:`skyfix.datasets.observations`). The observer's own position is
  left NaN: the observer does not know it; the engine uses its own estimate.

Faults: a GNSS outage on one drone ("silent": no messages; "no_fix": messages with
fix type 1 and lat/lon 0 as receivers report) and a spoofed jump on another (the fix
moves by a fixed horizontal offset and follows the drone, with a normal fix type and
satellite count); further spoof windows (``faults``) may drift at a constant rate. Delivery: each event has its measurement time ``time_s`` and its
arrival time ``arrival_s``; a fraction of relative observations and GNSS messages
arrive 0.2-1.0 s late, and events are ordered by arrival.

Frames: truth is in the ENU frame of :attr:`FusionScenario.frame` (metres about the
origin, heights ellipsoidal); every ENU <-> geodetic conversion goes through
:class:`skyfix.geo.LocalFrame`, and vectors measured at a drone are rotated into the
ENU axes at that drone with ``LocalFrame.enu_rotation_at``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from skyfix import validate
from skyfix.datasets.fusion_messages import (
    altitude_table,
    concat_tables,
    gnss_table,
    relative_table,
    sample_times,
    truth_at,
    velocity_table,
)
from skyfix.datasets.fusion_world import (
    DEFAULT_FORMATIONS,
    DRONE_IDS,
    KINDS,
    OUTAGE_MODES,
    Formation,
    MessageTable,
    NoiseModel,
    Outage,
    Spoof,
    SurveyPath,
)
from skyfix.datasets.gauss_markov import gauss_markov
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation


@dataclass(frozen=True)
class FusionEvent:
    """One message as the engine receives it.

    ``kind`` is "gnss" | "velocity" | "altitude" | "relative"; ``data`` holds the keyword
    arguments of the matching ``FusionEngine.add_*`` call after ``drone_id`` and
    ``time_s`` (for "relative": ``{"obs": RelativeObservation}``, ``drone_id`` is the
    observer). ``time_s`` is the measurement time, ``arrival_s`` when it reaches the engine.
    """

    time_s: float
    arrival_s: float
    kind: str
    drone_id: str
    data: dict[str, Any]


def feed(engine: Any, event: FusionEvent) -> None:
    """Give ``event`` to ``engine`` through the matching ``add_*`` method."""
    if event.kind == "relative":
        engine.add_relative(event.data["obs"])
    elif event.kind == "gnss":
        engine.add_gnss(event.drone_id, event.time_s, **event.data)
    elif event.kind == "velocity":
        engine.add_velocity(event.drone_id, event.time_s, **event.data)
    elif event.kind == "altitude":
        engine.add_altitude(event.drone_id, event.time_s, **event.data)
    else:
        raise InputError(f"event.kind must be one of {KINDS}, got {event.kind!r}")


@dataclass
class FusionScenario:
    """A simulated survey: truth, measurement events, fault windows and noise model.

    Truth is exact at any time (:meth:`truth_enu`, :meth:`truth_geodetic`); a 10 Hz
    sampling is in :attr:`truth_t_s` / :attr:`truth_enu_m` / :attr:`truth_vel_enu_mps`.
    Events come in arrival order from :meth:`events` (built lazily: an hour is ~300 000
    messages); :meth:`table` gives one kind's messages as arrays for tests and baselines.
    """

    frame: LocalFrame
    duration_s: float
    seed: int
    noise: NoiseModel
    outage: Outage | None
    spoof: Spoof | None
    path: SurveyPath
    formations: dict[str, Formation]
    truth_t_s: np.ndarray = field(repr=False)
    truth_enu_m: dict[str, np.ndarray] = field(repr=False)
    truth_vel_enu_mps: dict[str, np.ndarray] = field(repr=False)
    velocity_bias_mps: dict[str, np.ndarray] = field(repr=False)  # (N_vel, 3) per drone, ENU at drone
    _tables: dict[str, MessageTable] = field(repr=False)
    _order: np.ndarray = field(repr=False)  # (n_events, 2): kind index, row, in arrival order

    drone_ids: tuple[str, ...] = DRONE_IDS
    faults: tuple[Spoof, ...] = ()  # further spoofs (drifts, offsets after an outage), besides ``spoof``

    @property
    def spoofs(self) -> tuple[Spoof, ...]:
        """Every spoof window: ``spoof`` first, then ``faults``."""
        return ((self.spoof,) if self.spoof is not None else ()) + self.faults

    @property
    def origin(self) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_m ellipsoidal) of the ENU frame."""
        return (self.frame.lat0_deg, self.frame.lon0_deg, self.frame.alt0_m)

    @property
    def n_events(self) -> int:
        return int(self._order.shape[0])

    def truth_enu(self, drone_id: str, t_s) -> np.ndarray:
        """Exact true ENU position (N, 3) m of ``drone_id`` at times ``t_s`` (scalar or (N,))."""
        return truth_at(self.path, self.formations, drone_id, np.atleast_1d(np.asarray(t_s, float)))[0]

    def truth_vel_enu(self, drone_id: str, t_s) -> np.ndarray:
        """Exact true velocity (N, 3) m/s in the frame's ENU axes."""
        return truth_at(self.path, self.formations, drone_id, np.atleast_1d(np.asarray(t_s, float)))[1]

    def truth_geodetic(self, drone_id: str, t_s) -> np.ndarray:
        """True (lat_deg, lon_deg, alt_m) (N, 3) of ``drone_id`` at times ``t_s``."""
        return self.frame.to_geodetic_points(self.truth_enu(drone_id, t_s))

    def table(self, kind: str) -> MessageTable:
        """All messages of ``kind`` as columns (measurement order, not arrival order)."""
        if kind not in self._tables:
            raise InputError(f"kind must be one of {KINDS}, got {kind!r}")
        return self._tables[kind]

    def gnss_valid_mask(self, drone_id: str, t_s) -> np.ndarray:
        """True where a GNSS message of ``drone_id`` at ``t_s`` is honest (no outage/spoof)."""
        t = np.atleast_1d(np.asarray(t_s, float))
        ok = np.ones(t.shape, bool)
        for w in (self.outage, *self.spoofs):
            if w is not None and w.drone_id == drone_id:
                ok &= ~((t >= w.start_s) & (t < w.end_s))
        return ok

    def events(self, start: int = 0, stop: int | None = None) -> Iterator[FusionEvent]:
        """Events ``start:stop`` in arrival order (ties: velocity, altitude, gnss, relative)."""
        ids = self.drone_ids
        for k, row in self._order[start:stop]:
            kind = KINDS[k]
            tab = self._tables[kind]
            c = tab.cols
            if kind == "velocity":
                data = {"vel_enu_mps": c["vel_enu_mps"][row].copy(), "sigma_mps": float(c["sigma_mps"][row])}
            elif kind == "altitude":
                data = {"alt_m": float(c["alt_m"][row]), "sigma_m": float(c["sigma_m"][row])}
            elif kind == "gnss":
                fix = int(c["fix_type"][row])
                data = {"lat_deg": float(c["lat_deg"][row]), "lon_deg": float(c["lon_deg"][row]),
                        "alt_m": float(c["alt_m"][row]), "fix_type": fix,
                        "satellites": int(c["satellites"][row])}
                if fix >= 2:
                    data.update(h_sigma_m=float(c["h_sigma_m"][row]), v_sigma_m=float(c["v_sigma_m"][row]),
                                hdop=float(c["hdop"][row]))
                else:  # a receiver without a fix reports no accuracy (eph/epv unknown)
                    data.update(h_sigma_m=None, v_sigma_m=None, hdop=None)
            else:
                data = {"obs": RelativeObservation(
                    observer_id=ids[int(tab.drone[row])], target_id=ids[int(c["target"][row])],
                    time_s=float(tab.time_s[row]), bearing_unit_enu=c["bearing_enu"][row].copy(),
                    range_m=float(c["range_m"][row]), cov_enu_m2=c["cov_enu_m2"][row].copy())}
            yield FusionEvent(float(tab.time_s[row]), float(tab.arrival_s[row]), kind,
                              ids[int(tab.drone[row])], data)


def survey_scenario(duration_s: float = 600.0, seed: int = 0, *,
                    origin: tuple[float, float, float] = (42.8716, -76.9813, 190.0),
                    outage: tuple[str, float, float] | None = ("A", 200.0, 120.0),
                    outage_mode: str = "silent",
                    spoof: tuple[str, float, float, float] | None = ("B", 420.0, 30.0, 50.0),
                    noise: NoiseModel | None = None,
                    path: SurveyPath | None = None,
                    formations: dict[str, Formation] | None = None,
                    faults: tuple[Spoof, ...] = ()) -> FusionScenario:
    """Simulate the three-drone survey for ``duration_s`` seconds, deterministically from ``seed``.

    ``origin`` (lat_deg, lon_deg, alt_m ellipsoidal) is the ground at the survey centre.
    ``outage`` = (drone_id, start_s, duration_s) with ``outage_mode`` "silent" | "no_fix";
    ``spoof`` = (drone_id, start_s, duration_s, jump_m): the horizontal jump direction is
    drawn from ``seed``. Either may be None. ``faults``: further :class:`Spoof` windows
    (drifts, offsets). Windows must lie inside the run.
    """
    dur = validate.positive_scalar("duration_s", duration_s)
    nm = noise or NoiseModel()
    sp = path or SurveyPath()
    if sp.start_north_m is None:
        n_lanes = np.ceil(sp.speed_mps * dur / (sp.lane_length_m + np.pi * sp.lane_spacing_m / 2.0))
        sp = replace(sp, start_north_m=-0.5 * (n_lanes - 1) * sp.lane_spacing_m)
    forms = dict(DEFAULT_FORMATIONS if formations is None else formations)
    frame = LocalFrame(*origin)
    if set(forms) != set(DRONE_IDS[1:]):
        raise InputError(f"formations must give helpers {DRONE_IDS[1:]}, got {sorted(forms)}")
    if outage_mode not in OUTAGE_MODES:
        raise InputError(f"outage_mode must be one of {OUTAGE_MODES}, got {outage_mode!r}")
    rng_root = np.random.SeedSequence(int(seed))
    rngs = [np.random.default_rng(s) for s in rng_root.spawn(12)]  # 8-10: correlated GNSS errors, 11: common part

    out_w, spoof_w = _fault_windows(outage, outage_mode, spoof, faults, dur, rngs[7])
    spoofs = ((spoof_w,) if spoof_w is not None else ()) + tuple(faults)

    truth_t = np.arange(0.0, dur + 1e-9, 0.1)
    truth_pos, truth_vel = {}, {}
    for d in DRONE_IDS:
        truth_pos[d], truth_vel[d] = truth_at(sp, forms, d, truth_t)
    lat_ = dict(nm.latency_s)

    # Per-drone phases so that the sensors of different drones are not synchronous.
    phases = {"A": 0.0, "B": 0.013, "C": 0.027}
    tabs: dict[str, list[MessageTable]] = {k: [] for k in KINDS}
    biases: dict[str, np.ndarray] = {}
    common = None
    if nm.gnss_common_frac > 0.0:  # (times, error (N, 3) ENU) shared by every receiver
        t_common = sample_times(dur, nm.gnss_rate_hz, 0.0)
        common = (t_common, gauss_markov(rngs[11], t_common, np.array(
            [nm.gnss_gm_h_sigma_m, nm.gnss_gm_h_sigma_m, nm.gnss_gm_v_sigma_m]), nm.gnss_gm_tau_s))
    for i, d in enumerate(DRONE_IDS):
        rng = rngs[i]
        ph = phases[d]
        tab, biases[d] = velocity_table(frame, sp, forms, d, i, dur, nm, ph, rng, lat_["velocity"])
        tabs["velocity"].append(tab)
        tabs["altitude"].append(altitude_table(frame, sp, forms, d, i, dur, nm, ph + 0.005, rng,
                                               lat_["altitude"]))
        # --- GNSS
        tabs["gnss"].append(gnss_table(frame, sp, forms, d, i, dur, nm, ph + 0.05, (rng, rngs[8 + i]), out_w, spoofs,
                                  lat_["gnss"], common))
    for i, d in enumerate(DRONE_IDS[1:], start=1):
        tabs["relative"].append(relative_table(frame, sp, forms, d, i, dur, nm, phases[d] + 0.031,
                                          rngs[3 + i], lat_["relative"]))

    tables = {k: concat_tables(v) for k, v in tabs.items()}
    return FusionScenario(frame=frame, duration_s=dur, seed=int(seed), noise=nm, outage=out_w,
                          spoof=spoof_w, path=sp, formations=forms, truth_t_s=truth_t,
                          truth_enu_m=truth_pos, truth_vel_enu_mps=truth_vel,
                          velocity_bias_mps=biases, _tables=tables, faults=tuple(faults),
                          _order=_arrival_order(tables))


def _fault_windows(outage: tuple[str, float, float] | None, outage_mode: str,
                   spoof: tuple[str, float, float, float] | None, faults: tuple[Spoof, ...], dur: float,
                   rng: np.random.Generator) -> tuple[Outage | None, Spoof | None]:
    """The checked outage and spoof windows (the spoof's jump direction drawn from ``rng``)."""
    out_w = None
    if outage is not None:
        d, t0, ln = outage
        out_w = Outage(_check_id("outage drone", d), validate.finite_scalar("outage start_s", t0),
                       validate.positive_scalar("outage duration_s", ln), outage_mode)
        _check_window("outage", out_w.start_s, out_w.end_s, dur)
    spoof_w = None
    if spoof is not None:
        d, t0, ln, jump = spoof
        az = rng.uniform(0.0, 2 * np.pi)
        jump_m = validate.positive_scalar("spoof jump_m", jump)
        spoof_w = Spoof(_check_id("spoof drone", d), validate.finite_scalar("spoof start_s", t0),
                        validate.positive_scalar("spoof duration_s", ln),
                        np.array([jump_m * np.sin(az), jump_m * np.cos(az), 0.0]))
        _check_window("spoof", spoof_w.start_s, spoof_w.end_s, dur)
    for f in faults:
        _check_id("fault drone", f.drone_id)
        _check_window("fault", f.start_s, f.end_s, dur)
    return out_w, spoof_w


def _arrival_order(tables: dict[str, MessageTable]) -> np.ndarray:
    """(n_events, 2): kind index and row of every message, by arrival (ties: time, kind, drone)."""
    kind_idx = np.concatenate([np.full(tables[k].time_s.size, j) for j, k in enumerate(KINDS)])
    rows = np.concatenate([np.arange(tables[k].time_s.size) for k in KINDS])
    arr = np.concatenate([tables[k].arrival_s for k in KINDS])
    tm = np.concatenate([tables[k].time_s for k in KINDS])
    dr = np.concatenate([tables[k].drone for k in KINDS])
    order = np.lexsort((dr, kind_idx, tm, arr))
    return np.stack([kind_idx[order], rows[order]], axis=1)


def _check_id(name: str, drone_id: str) -> str:
    if drone_id not in DRONE_IDS:
        raise InputError(f"{name} must be one of {DRONE_IDS}, got {drone_id!r}")
    return drone_id


def _check_window(name: str, start_s: float, end_s: float, duration_s: float) -> None:
    if start_s < 0.0 or end_s > duration_s:
        raise InputError(f"{name} window [{start_s}, {end_s}) s must lie inside the run [0, {duration_s}] s")


CORRELATED_NOISE = NoiseModel(gnss_h_sigma_m=0.3, gnss_v_sigma_m=0.5, gnss_gm_h_sigma_m=1.5,
                              gnss_gm_v_sigma_m=2.5, gnss_gm_tau_s=60.0, gnss_outlier_frac=0.02,
                              relative_rate_hz=2.0, relative_range_frac=0.02, relative_bearing_sigma_deg=0.5,
                              relative_min_range_m=20.0, relative_max_range_m=140.0)
CORRELATED_FORMATIONS: dict[str, Formation] = {
    "B": Formation(range_m=80.0, azimuth_deg=240.0, dup_m=12.0, range_wander_m=60.0, azimuth_wander_deg=25.0,
                   periods_s=(157.0, 233.0, 131.0), phases_rad=(0.0, 0.7, 0.3)),
    "C": Formation(range_m=80.0, azimuth_deg=120.0, dup_m=-15.0, range_wander_m=60.0, azimuth_wander_deg=25.0,
                   periods_s=(197.0, 171.0, 113.0), phases_rad=(2.1, 4.0, 1.9)),
}


def correlated_scenario(duration_s: float = 600.0, seed: int = 0, faults: bool = True,
                        return_offset: bool = True) -> FusionScenario:
    """The survey with Gauss-Markov GNSS on every drone (:data:`CORRELATED_NOISE`) and, with
    ``faults`` (needs ``duration_s`` >= 450): A silent 150-240 s, then A's GNSS 30 m off for
    30 s; B spoofed by a 50 m jump 300-330 s; C's GNSS drifting at 0.5 m/s 380-440 s, honest after.
    Jump and drift directions are drawn from ``seed``. ``return_offset=False``: A stays silent
    240-270 s instead of returning 30 m off, every other message the same (a counterfactual
    that tells what the offset GNSS moved from what the estimate would have done anyway)."""
    if not faults:
        return survey_scenario(duration_s, seed, outage=None, spoof=None, noise=CORRELATED_NOISE,
                               formations=CORRELATED_FORMATIONS)
    az = np.random.default_rng(np.random.SeedSequence([int(seed), 15])).uniform(0.0, 2 * np.pi, 2)
    horiz = np.stack([np.sin(az), np.cos(az), np.zeros(2)], axis=1)
    drift = Spoof("C", 380.0, 60.0, np.zeros(3), 0.5 * horiz[1])
    extra = (Spoof("A", 240.0, 30.0, 30.0 * horiz[0]), drift) if return_offset else (drift,)
    return survey_scenario(duration_s, seed, outage=("A", 150.0, 90.0 if return_offset else 120.0),
                           spoof=("B", 300.0, 30.0, 50.0), noise=CORRELATED_NOISE,
                           formations=CORRELATED_FORMATIONS, faults=extra)


STEP_TIMES_S: dict[str, float] = {"A": 100.0, "B": 170.0, "C": 200.0}  # mismatch_scenario's error steps


def mismatch_scenario(duration_s: float, seed: int, noise: NoiseModel, step_m: float = 0.0) -> FusionScenario:
    """The correlated survey's geometry with GNSS errors drawn from ``noise`` (e.g. another
    sigma or correlation time than a fusion engine assumes) and one fault: A silent 150-240 s
    (needs ``duration_s`` >= 240). ``step_m`` > 0: every receiver's error also steps by that
    much horizontally for the rest of the run (a constellation change), at :data:`STEP_TIMES_S`
    (B and C during A's outage), in directions drawn from ``seed``."""
    steps: tuple[Spoof, ...] = ()
    if step_m > 0.0:
        az = np.random.default_rng(np.random.SeedSequence([int(seed), 16])).uniform(0.0, 2 * np.pi, 3)
        steps = tuple(Spoof(d, t0, float(duration_s) - t0, step_m * np.array([np.sin(a), np.cos(a), 0.0]))
                      for (d, t0), a in zip(STEP_TIMES_S.items(), az, strict=True))
    return survey_scenario(duration_s, seed, outage=("A", 150.0, 90.0), spoof=None, noise=noise,
                           formations=CORRELATED_FORMATIONS, faults=steps)
