"""``skyfix demo``: the main demonstration on the built-in multi-vehicle simulator.

Three simulated ArduPilot quadcopters on loopback UDP, flown only through MAVLink by
:class:`skyfix.drivers.Vehicle`: survey missions, a GPS outage on one vehicle bridged by
GPS_INPUT injection, a geofence breach answered by RTL, landing. Writes a trajectory
plot (PNG) and the flight log (CSV).

The injected position of the vehicle without GPS comes from :mod:`skyfix.fusion`:
its velocity and the two other vehicles' camera observations of it (measurement-level,
see :class:`FusedPositionSource`), fused with everyone's GNSS by the same
:class:`skyfix.crps.node.Node` that ``skyfix serve`` runs on each drone; the measurement
log is written next to the plot for ``skyfix fusion replay``.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

PLAN = """\
skyfix demo:
  1. starts the built-in MAVLink simulator on loopback (3 ArduPilot quadcopters);
  2. connects to each with skyfix.drivers, sets GPS2_TYPE=14, installs a geofence,
     uploads a survey mission (camera trigger every 10 m), arms, takes off, flies it;
  3. cuts GPS on vehicle 2 mid-mission (SIM_GPS1_ENABLE 0, as in SITL); skyfix.fusion keeps
     it positioned from its velocity and vehicles 1 and 3 observing it (camera range 3 %,
     bearing 0.2 deg, simulated at measurement level), injected as GPS_INPUT at 5 Hz;
  4. vehicle 3 flies east into the geofence: the safety gate switches it to RTL;
  5. every vehicle returns home and lands; vehicle 2 still without GPS;
  6. writes trajectory.png, trajectory.csv, summary.json and fusion.jsonl (the fusion
     measurement log: skyfix fusion replay OUTPUT/fusion.jsonl) to --output.
"""

N_VEHICLES = 3
GPS_LOST_VEHICLE = 1  # index of the vehicle that loses GPS (system id 2)
FENCE_VEHICLE = 2  # index of the vehicle that breaches the fence (system id 3)
CRUISE_ALT_M = 15.0
FENCE_HALF_WIDTH_M = 70.0  # square fence, metres from the centre of the survey area


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="run the main demo on the built-in simulator",
                              description=PLAN, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--output", default="skyfix-demo", help="output folder (default skyfix-demo)")
    p.add_argument("--speed", type=float, default=6.0,
                   help="simulated seconds per wall second (default 6; the flight is ~3 min simulated)")
    p.set_defaults(func=run)


@dataclass
class DemoResult:
    """What the demo measured; ``ok`` when every check passed."""

    checks: dict[str, bool] = field(default_factory=dict)
    figures: dict[str, float] = field(default_factory=dict)
    files: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return bool(self.checks) and all(self.checks.values())


class FusedPositionSource:
    """The fleet's :class:`skyfix.crps.node.Node` next to the simulator; supplies the GPS-less vehicle's position.

    At 10 Hz of simulated time it feeds the node with what a companion computer would
    have: each vehicle's telemetry (raw GNSS from GPS_RAW_INT, skipped for a vehicle while
    skyfix injects its position, which the receiver report would only echo; velocity from
    GLOBAL_POSITION_INT), plus the helpers' camera observations of the GPS-less vehicle.
    The demo renders no images, so the observations are measurement-level
    (:mod:`skyfix.datasets.observations`: true offset, 3 % range and 0.2 deg bearing
    noise, the covariance skyfix.crps reports). Heights: ellipsoidal from the drivers (the
    simulator reports AMSL with the EGM96 geoid, as autopilots do; the injector converts back). Every input goes to the measurement log
    ``log_path`` (with truth) for ``skyfix fusion replay``. Call it (``source()``) for the
    newest fused GeoFix, moved to the present with the fused velocity.
    """

    def __init__(self, sim, vehicles, target_index: int, injecting: list[bool], log_path: Path,
                 seed: int = 0) -> None:
        from skyfix.crps.node import Node
        from skyfix.fusion import FusionConfig
        from skyfix.fusion.log import MeasurementLog

        frame = sim.world
        self.sim, self.vehicles, self.target_index, self.injecting = sim, vehicles, target_index, injecting
        # At N x real time a 0.1 s scheduling hiccup of this thread (GIL, a loaded machine) is N/10 s of
        # simulated silence: scale the loss time-outs so hiccups are not mistaken for sensor loss.
        k = max(1.0, sim.config.speed / 4.0)
        cfg = FusionConfig(gnss_timeout_s=0.7 * k, velocity_timeout_s=1.0 * k, altitude_timeout_s=1.0 * k,
                           relative_timeout_s=2.0 * k)
        self.target_id = str(vehicles[target_index].system_id)
        self.node = Node(self.target_id, (frame.lat0_deg, frame.lon0_deg, frame.alt0_m), lag_s=2.0 * k,
                         config=cfg, make_sink=lambda header: MeasurementLog(
                             log_path, header, fsync_s=cfg.log_fsync_s))
        self.errors_m: list[float] = []      # fused horizontal error of the target while injecting
        self.nees: list[float] = []
        self._rng = np.random.default_rng(seed)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="skyfix-demo-fusion")

    def start(self) -> FusedPositionSource:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.node.close()

    def __call__(self):
        """The newest fused fix, moved to the present simulated time with the fused velocity."""
        return self.node.fix(self.target_id, self.sim.time_s, time_stamp_s=time.time())

    def _run(self) -> None:
        from skyfix.datasets.observations import relative_observation
        from skyfix.errors import SkyfixError

        next_t = self.sim.time_s
        while not self._stop.is_set():
            t = self.sim.time_s
            if t < next_t:
                time.sleep(0.002)
                continue
            next_t = t + 0.1
            truth = [self.sim.truth(i) for i in range(len(self.vehicles))]
            try:
                for i, v in enumerate(self.vehicles):
                    self.node.add_telemetry(str(v.system_id), v.state, lambda m, t=t: self._sim_time_of(t, m),
                                            use_gnss=not self.injecting[i])
                target = truth[self.target_index]
                t_obs = target["time_s"]  # the simulator may step between truth reads: align helpers to it
                p_tgt = _enu(target)
                if target["alt_rel_m"] > 2.0:
                    for i, v in enumerate(self.vehicles):
                        if i != self.target_index and truth[i]["alt_rel_m"] > 2.0:
                            p_obs = _enu(truth[i]) + _vel(truth[i]) * (t_obs - truth[i]["time_s"])
                            self.node.add_relative(relative_observation(
                                self.sim.world, str(v.system_id), self.target_id, t_obs, p_obs, p_tgt, self._rng))
                estimates = self.node.update((self.target_id,))
                for i, v in enumerate(self.vehicles):
                    self.node.record_truth(str(v.system_id), t, truth[i]["lat_deg"], truth[i]["lon_deg"],
                                           truth[i]["alt_m"])
                self._score(estimates, target)
            except SkyfixError as exc:  # a bad message is logged and dropped; the loop goes on
                log.warning("fusion: %s", exc)

    def _sim_time_of(self, t_sim: float, message) -> float:
        """Measurement time of a telemetry message: its own autopilot time stamp (the simulator's
        autopilot clock is simulated time since start), else its reception time mapped to
        simulated time (the driver stamps with time.time(); the simulator runs ``speed`` x faster)."""
        if math.isfinite(message.autopilot_time_s):
            return message.autopilot_time_s
        return t_sim - max(0.0, time.time() - message.time_s) * self.sim.config.speed

    def _score(self, estimates, target_truth: dict) -> None:
        """Error and NEES of the target's estimate against the truth while it flies on injection."""
        est = next((e for e in estimates if e.drone_id == self.target_id), None)
        if est is None or not self.injecting[self.target_index]:
            return
        truth_then = _enu(target_truth) + _vel(target_truth) * (est.time_s - target_truth["time_s"])
        err = est.enu_m - truth_then
        self.errors_m.append(float(np.hypot(err[0], err[1])))
        self.nees.append(float(err @ np.linalg.solve(est.cov_enu_m2, err)))


def _enu(truth: dict) -> np.ndarray:
    return np.array([truth["east_m"], truth["north_m"], truth["up_m"]])


def _vel(truth: dict) -> np.ndarray:
    return np.array([truth["vel_east_mps"], truth["vel_north_mps"], truth["vel_up_mps"]])


class _Recorder:
    """Samples truth and reported state of every vehicle at 10 Hz of wall time."""

    def __init__(self, sim, vehicles, injecting: list[bool]) -> None:
        self.sim, self.vehicles, self.injecting = sim, vehicles, injecting
        self.rows: list[dict] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="skyfix-demo-recorder")

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        frame = self.sim.world
        while not self._stop.wait(0.1):
            for i, v in enumerate(self.vehicles):
                t = self.sim.truth(i)
                st = v.state
                p = st.position
                if p is not None:
                    e, n, _ = frame.to_enu(p.lat_deg, p.lon_deg, p.alt_amsl_m)
                    rep_e, rep_n = float(e), float(n)
                else:
                    rep_e = rep_n = math.nan
                self.rows.append({
                    "sim_time_s": round(t["time_s"], 3), "system_id": v.system_id,
                    "true_lat_deg": t["lat_deg"], "true_lon_deg": t["lon_deg"],
                    "true_alt_rel_m": round(t["alt_rel_m"], 3),
                    "true_east_m": round(t["east_m"], 3), "true_north_m": round(t["north_m"], 3),
                    "reported_east_m": round(rep_e, 3), "reported_north_m": round(rep_n, 3),
                    "reported_alt_rel_m": round(p.alt_rel_m, 3) if p else math.nan,
                    "mode": st.mode, "armed": int(st.armed),
                    "gps_fix_type": st.gps.fix_type if st.gps else -1,
                    "gps_input": int(self.injecting[i]),
                })


def _mission(vehicle, frame):
    """A lawnmower leg per vehicle from its home: 60 m north, 10 m east, 55 m south."""
    from skyfix.drivers.mission import MissionItem

    home = vehicle.state.home
    e0, n0, _ = (float(x) for x in frame.to_enu(home.lat_deg, home.lon_deg, home.alt_amsl_m))
    pts_en = [(e0, n0 + 60.0), (e0 + 10.0, n0 + 60.0), (e0 + 10.0, n0 + 5.0)]
    items = [MissionItem.camera_trigger_distance(10.0)]
    for e, n in pts_en:
        lat, lon, _ = frame.to_geodetic(e, n, 0.0)
        items.append(MissionItem.waypoint(float(lat), float(lon), CRUISE_ALT_M))
    return items


def _plot(rows: list[dict], fence_en: np.ndarray, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 8))
    ax.fill(fence_en[:, 0], fence_en[:, 1], color="0.93", zorder=0)
    ax.plot(*np.vstack([fence_en, fence_en[:1]]).T, "k--", lw=1, label="geofence")
    colours = ["tab:blue", "tab:orange", "tab:green"]
    for sid in sorted({r["system_id"] for r in rows}):
        rr = [r for r in rows if r["system_id"] == sid]
        e = np.array([r["true_east_m"] for r in rr])
        n = np.array([r["true_north_m"] for r in rr])
        inj = np.array([r["gps_input"] for r in rr], bool)
        c = colours[(sid - 1) % len(colours)]
        ax.plot(e, n, "-", color=c, lw=1.5, label=f"vehicle {sid} (truth)")
        if inj.any():
            ax.plot(e[inj], n[inj], ".", color="red", ms=3, label=f"vehicle {sid} flying on GPS_INPUT")
            re_ = np.array([r["reported_east_m"] for r in rr])[inj]
            rn = np.array([r["reported_north_m"] for r in rr])[inj]
            ax.plot(re_, rn, ":", color="0.3", lw=1, label=f"vehicle {sid} autopilot estimate")
        rtl = [i for i, r in enumerate(rr) if r["mode"] == "RTL"]
        if rtl:
            ax.plot(e[rtl[0]], n[rtl[0]], "X", color=c, ms=10)
        ax.plot(e[0], n[0], "^", color=c, ms=9)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_title("skyfix demo: survey, GPS outage bridged by GPS_INPUT, fence breach -> RTL\n"
                 "(^ start, X RTL begins)")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_demo(output: Path, *, speed: float = 6.0, progress: bool = True) -> DemoResult:
    """Fly the demo and write its files into ``output``; returns the checks and figures."""
    from tqdm import tqdm

    from skyfix.datasets.sim import Simulator, SimulatorConfig
    from skyfix.drivers.safety import Geofence, SafetyGate
    from skyfix.drivers.vehicle import Vehicle

    output.mkdir(parents=True, exist_ok=True)
    result = DemoResult()
    steps = ["start simulator", "connect + configure", "upload missions", "arm + take off",
             "survey, GPS cut on vehicle 2", "fence breach by vehicle 3", "return + land", "write files"]
    bar = tqdm(total=len(steps), desc="skyfix demo", disable=not progress, unit="step")
    injecting = [False] * N_VEHICLES
    sim = Simulator(SimulatorConfig(vehicles=N_VEHICLES, speed=speed, seed=7)).start()
    vehicles: list[Vehicle] = []
    recorder = None
    injector = None
    fused = None
    try:
        bar.update(1)
        frame = sim.world
        for i in range(N_VEHICLES):
            vehicles.append(Vehicle.connect(sim.url(i), timeout_s=5.0))
        for v in vehicles:
            v.wait_until(lambda s: s.home is not None and s.gps is not None, 10.0, what="home and GPS")
            v.set_param("GPS2_TYPE", 14)  # a MAV GPS instance for GPS_INPUT, real receiver stays primary
        # fence: a square around the survey area (centre 10 m north-east of vehicle 2's home)
        centre_e, centre_n = 5.0 * (N_VEHICLES - 1) / 2 + 5.0, 30.0
        h = FENCE_HALF_WIDTH_M
        fence_en = np.array([[centre_e - h, centre_n - h], [centre_e + h, centre_n - h],
                             [centre_e + h, centre_n + h], [centre_e - h, centre_n + h]])
        fence_ll = frame.to_geodetic_points(np.column_stack([fence_en, np.zeros(4)]))[:, :2]
        gate = SafetyGate(Geofence([fence_ll], max_alt_rel_m=40.0), max_speed_mps=12.0, action="rtl")
        for v in vehicles:
            v.set_safety(gate)
        recorder = _Recorder(sim, vehicles, injecting)
        recorder.start()
        fusion_log = output / "fusion.jsonl"
        if fusion_log.exists():
            fusion_log.unlink()  # the demo's own log from an earlier run in the same folder
        fused = FusedPositionSource(sim, vehicles, GPS_LOST_VEHICLE, injecting, fusion_log).start()
        bar.update(1)

        upload_s = [v.upload_mission(_mission(v, frame)).elapsed_s for v in vehicles]
        result.figures["mission_upload_max_s"] = max(upload_s)
        bar.update(1)

        for v in vehicles:
            v.set_mode("GUIDED")
            v.arm()
        for v in vehicles:
            v.takeoff(CRUISE_ALT_M, wait=False)
        for v in vehicles:
            v.wait_until(lambda s: s.position is not None and s.position.alt_rel_m > CRUISE_ALT_M - 0.5,
                         60.0, what="take-off altitude")
        for v in vehicles:
            v.start_mission()
        bar.update(1)

        lost = vehicles[GPS_LOST_VEHICLE]
        lost.wait_until(lambda s: s.mission_seq >= 3, 60.0, what="vehicle 2 on its second leg")
        injector = lost.start_gps_injection(fused, rate_hz=5.0 * speed)  # 5 Hz of simulated time
        injecting[GPS_LOST_VEHICLE] = True
        lost.set_param("SIM_GPS1_ENABLE", 0)
        t_cut = sim.time_s
        log.info("GPS cut on vehicle %d at t=%.1f s; injecting GPS_INPUT", lost.system_id, t_cut)
        for v in vehicles:
            v.wait_until(lambda s, v=v: _reached_last(v), 120.0, what="mission complete")
        result.checks["vehicle 2 kept flying its mission without GPS"] = lost.state.mode == "AUTO" \
            and lost.state.gps.fix_type <= 1
        bar.update(1)

        breacher = vehicles[FENCE_VEHICLE]
        breacher.set_mode("GUIDED")
        breacher.velocity(0.0, 6.0, 0.0)
        breacher.wait_until(lambda s: s.mode == "RTL", 60.0, what="RTL after the fence breach")
        latency_s, reason = breacher.safety_log[-1]
        result.figures["fence_breach_action_latency_ms"] = latency_s * 1e3
        result.checks["fence breach -> RTL by the safety gate"] = "outside the geofence" in reason
        bar.update(1)

        for v in vehicles:
            if v is not breacher:
                v.rtl()
        for v in vehicles:
            v.wait_until(lambda s: not s.armed, 180.0, what="landed and disarmed")
        injector.stop()
        injecting[GPS_LOST_VEHICLE] = False
        for i, v in enumerate(vehicles):
            t = sim.truth(i)
            home_e, home_n = sim.vehicle(i).home_enu_m[:2]
            miss = float(np.hypot(t["east_m"] - home_e, t["north_m"] - home_n))
            result.figures[f"vehicle_{v.system_id}_landing_error_m"] = miss
            result.checks[f"vehicle {v.system_id} landed within 3 m of home, disarmed"] = \
                miss < 3.0 and t["alt_rel_m"] < 0.2 and not v.state.armed
        result.figures["gps_outage_s"] = sim.time_s - t_cut
        result.figures["gps_input_messages"] = injector.sent
        if fused.errors_m:
            result.figures["fused_position_error_rms_m"] = float(np.sqrt(np.mean(np.square(fused.errors_m))))
            result.figures["fused_position_error_max_m"] = float(np.max(fused.errors_m))
            result.figures["fused_position_mean_nees_3dof"] = float(np.mean(fused.nees))
        result.checks["fused position of vehicle 2 without GPS within 2 m RMS"] = \
            bool(fused.errors_m) and result.figures["fused_position_error_rms_m"] < 2.0
        result.figures["camera_triggers"] = sum(e.kind == "camera_trigger" for v in vehicles for e in v.events)
        bar.update(1)
    finally:
        if recorder is not None:
            recorder.stop()
        if injector is not None:
            injector.stop()
        if fused is not None:
            fused.stop()
        for v in vehicles:
            v.close()
        sim.stop()

    rows = recorder.rows if recorder else []
    lost_rows = [r for r in rows if r["system_id"] == GPS_LOST_VEHICLE + 1 and r["gps_input"]
                 and r["true_alt_rel_m"] > 1.0]
    if lost_rows:
        errs = [math.hypot(r["reported_east_m"] - r["true_east_m"], r["reported_north_m"] - r["true_north_m"])
                for r in lost_rows]
        result.figures["gps_input_estimate_error_rms_m"] = float(np.sqrt(np.mean(np.square(errs))))
    csv_path, png_path, json_path = output / "trajectory.csv", output / "trajectory.png", output / "summary.json"
    with open(csv_path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["sim_time_s"])
        writer.writeheader()
        writer.writerows(rows)
    _plot(rows, fence_en, png_path)
    result.files = [str(csv_path), str(png_path), str(json_path), str(output / "fusion.jsonl")]
    json_path.write_text(json.dumps({"checks": result.checks, "figures": result.figures,
                                     "injected_position_source": "skyfix.fusion: velocity + helpers' observations "
                                                                 "(measurement-level camera ranging model)",
                                     "files": result.files}, indent=2))
    bar.update(1)
    bar.close()
    return result


def _reached_last(v) -> bool:
    return any(e.kind == "mission_item_reached" and e.data.get("seq") == 4 for e in list(v.events))


def run(args: argparse.Namespace) -> int:
    from skyfix import validate

    speed = validate.positive_scalar("--speed", args.speed)
    t0 = time.monotonic()
    result = run_demo(Path(args.output), speed=speed, progress=not getattr(args, "quiet", False))
    out = sys.stdout
    for name, passed in result.checks.items():
        out.write(f"  [{'ok' if passed else 'FAILED'}] {name}\n")
    for name, value in result.figures.items():
        out.write(f"  {name} = {value:.3f}\n" if isinstance(value, float) else f"  {name} = {value}\n")
    out.write(f"wrote {', '.join(result.files)} in {time.monotonic() - t0:.1f} s\n")
    return 0 if result.ok else 1
