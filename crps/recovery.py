"""GPS-loss recovery of one drone by two others, end to end on the simulator: what ``skyfix demo`` flies.

Three simulated ArduPilot copters (:mod:`skyfix.datasets.sim`: wind, correlated GNSS errors on every receiver)
each run a :class:`skyfix.crps.service.Service` (the ``skyfix serve`` node: MAVLink over loopback UDP, fusion,
signed swarm messages over the in-process bus, GPS_INPUT injection, the help protocol via
:class:`skyfix.crps.help_loop.HelpLoop`). Each surveys its own strip; one loses its GNSS receiver at a random
moment. Its service holds, asks for help, the others fly to vantage points, point their gimbal cameras
(:class:`skyfix.datasets.sim.world_camera.WorldCamera`, rendered from the simulator's truth) at it, detect and
range it in the pixels and send relative observations; its fusion positions it from them, the injected fix takes
it home (RTL) and it lands. The harness only flies the missions, schedules the faults and scores against the
truth; no observation is computed from the truth. Times are simulated seconds (the swarm's clock).
"""

from __future__ import annotations

import logging
import math
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skyfix import validate
from skyfix.crps.recovery_faults import Faults, LossyLink
from skyfix.crps.recovery_report import HOME_RADIUS_M, Recorder, write_outputs
from skyfix.datasets.gnss_error import INDEPENDENT, MILD, REALISTIC, CommonGnssError, GnssErrorModel
from skyfix.errors import InputError, SkyfixError

log = logging.getLogger(__name__)

IDS = ("d1", "d2", "d3")
LOST = 1                 # index of the drone that loses GNSS (d2, the middle strip)
SPACING_M = 30.0         # between the drones' homes, east
CRUISE_ALT_M = 15.0      # survey height above home
STRIP_HALF_WIDTH_M = 6.0
STRIP_LENGTH_M = 90.0
SURVEY_LOOPS = 2
LOSS_WINDOW_S = (15.0, 45.0)  # the loss comes this long after the survey starts (uniform, from the seed)
TAKEOFF_STALL_S = 20.0   # a drone not at cruise height this long after its take-off command is sent up again
# a loaded machine delays the helpers' observations by seconds (one Python process flies all three drones and
# both cameras): each node's fusion lag follows their arrival delays up to this many times its idle lag (the
# requester's window then costs up to that many times the CPU; an observation later than ~10 s is rare even with
# two test suites on two cores, 5.6 s p90 seen)
MAX_LAG_FACTOR = 4.0
# one process renders and processes both helpers' cameras and runs three services: on a shared machine a frame can
# take seconds of CPU, which a drone's own companion computer would not lose to its neighbours. While a helper's
# frame older than this (simulated s) is still in its pipeline, the simulated world runs at real time at most
# (RecoveryConfig.pace; not below: the autopilots' 1 Hz heartbeats must reach their services within 2 s)
PACE_BEHIND_S = 1.5
PACE_SPEED = 1.0


GNSS_MODELS = {
    # receivers tens of metres apart share most of their error (orbits, clocks, atmosphere), 1.5 m per axis each
    "realistic": REALISTIC,
    "independent": INDEPENDENT,  # the stress case: each receiver its own 1.5 m / 60 s error, nothing shared
    "mild": MILD,                # a good multi-band receiver, open sky, nothing shared
}


@dataclass
class RecoveryConfig:
    """One recovery run (the faults default off)."""

    seed: int = 0
    speed: float = 2.0                    # simulated seconds per wall second
    output: Path | None = None            # folder for trajectory.png, report.json, the MCAP logs; None: none
    loss_time_s: float | None = None      # GNSS loss, s after the survey starts; None: drawn from the seed
    wind_mps: float = 3.0                 # mean wind speed (direction from the seed), gusts 20 % of it
    gnss: GnssErrorModel = REALISTIC      # every simulated receiver's errors (GNSS_MODELS)
    fusion_common_share: float | None = None  # every node's fusion: receivers' shared error share (None: serve's)
    healthy: bool = False                 # no GNSS loss: the same drone flies RTL at the loss time (baseline)
    fault_response: str = "return_home"
    helper_dropout_s: float | None = None  # the first assigned helper goes silent this long after the loss
    swarm_loss_rate: float = 0.0          # share of swarm datagrams lost, every drone, both ways
    mav_outage_s: float = 0.0             # the lost drone's MAVLink link drops this long, 5 s into its return
    forged_observation: bool = False      # an impostor without the swarm key sends observations of the lost drone
    gnss_return_offset_m: float | None = None  # GNSS comes back this far off (east), 25 s after the loss
    target_leaves_fov: bool = False       # one helper's gimbal looks 90 deg away for 12 s, 10 s after it helps
    helpers_blind_s: float | None = None  # every helper's gimbal looks 90 deg away this long from the loss: none sees it
    lost_vehicle_url: str | None = None   # an external autopilot (ArduPilot SITL) as the lost drone ...
    lost_vehicle_truth_url: str | None = None  # ... a second link to it streaming SIM_STATE (its truth)
    lost_vehicle_home: tuple[float, float, float] | None = None  # ... its home: lat, lon (deg), alt AMSL (m)
    max_after_loss_s: float = 200.0       # the run ends this long after the loss at the latest
    camera_px: tuple[int, int] = (960, 720)
    camera_hfov_deg: float = 50.0
    frame_hz: float = 4.0
    pace: bool = True                     # the simulator slows to real time while a helper's camera is behind

    def __post_init__(self) -> None:
        validate.positive_scalar("speed", self.speed)
        if not 0.0 <= float(self.swarm_loss_rate) < 1.0:
            raise InputError(f"swarm_loss_rate must be in [0, 1), got {self.swarm_loss_rate}")
        if self.loss_time_s is not None and validate.finite_scalar("loss_time_s", self.loss_time_s) < 0:
            raise InputError(f"loss_time_s must be >= 0, got {self.loss_time_s}")
        if validate.finite_scalar("wind_mps", self.wind_mps) < 0:
            raise InputError(f"wind_mps must be >= 0, got {self.wind_mps}")
        if validate.finite_scalar("mav_outage_s", self.mav_outage_s) < 0:
            raise InputError(f"mav_outage_s must be >= 0, got {self.mav_outage_s}")


@dataclass
class RecoveryResult:
    """What a run measured (truth-based scores). ``outcome``: ``home`` (landed <= 3 m from home),
    ``landed_elsewhere``, ``holding`` (airborne at the end), ``lost`` (no run to score)."""

    landing_error_m: float
    loss_to_first_fused_fix_s: float
    max_recovery_error_h_m: float
    min_separation_m: float
    detection_share: float
    timeline: list[tuple[float, str]]
    outcome: str
    files: dict[str, str] = field(default_factory=dict)
    figures: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"landing_error_m": self.landing_error_m, "loss_to_first_fused_fix_s": self.loss_to_first_fused_fix_s,
                "max_recovery_error_h_m": self.max_recovery_error_h_m, "min_separation_m": self.min_separation_m,
                "detection_share": self.detection_share, "outcome": self.outcome,
                "timeline": [[round(t, 2), what] for t, what in self.timeline], "figures": self.figures,
                "files": self.files}


def _wind(cfg: RecoveryConfig, rng: np.random.Generator):
    from skyfix.datasets.sim.wind import WindField

    direction = rng.uniform(0.0, 2.0 * math.pi)
    mean = (cfg.wind_mps * math.sin(direction), cfg.wind_mps * math.cos(direction), 0.0)
    return WindField(mean_enu_mps=mean, gust_sigma_mps=0.2 * cfg.wind_mps, seed=cfg.seed)


def _apply_gnss_model(sim, model: GnssErrorModel, seed: int) -> CommonGnssError | None:
    """Give every simulated receiver the run's error model: the area's common error (one seeded track that
    all of them sample at their own fix times) and its own wandering error, drawn from the model's steady
    state (a receiver switched on minutes before take-off, not one whose error starts at zero). Returns the
    common track (None: nothing shared), for scoring."""
    common = CommonGnssError(seed * 7919 + 11, model.common_sigma_m, model.common_tau_s) \
        if model.common_sigma_m > 0 else None
    with sim.lock:
        for server in sim.servers:
            gps = server.vehicle.gps
            for name in ("bias_sigma_m", "bias_tau_s", "noise_sigma_m", "common"):
                if not hasattr(gps, name):
                    raise NotImplementedError(f"the simulator's GpsReceiver has no {name}")
            gps.bias_sigma_m, gps.bias_tau_s = model.own_sigma_m, model.own_tau_s
            gps.noise_sigma_m, gps.common = model.white_sigma_m, common
            gps.step(20.0 * model.own_tau_s)  # forgets its start: a steady-state draw
    return common


def _sitl_shares(truth, common: CommonGnssError | None, clock: Callable[[], float], cfg: RecoveryConfig):
    """SITL's receiver (perfect by default) given the area's common GNSS error, which the simulated receivers
    share, before take-off (the home it records carries it, as a real drone's would) and kept current (the
    firmware's own glitch offsets, :class:`skyfix.datasets.sitl_gnss.SitlGnssError`). None: nothing shared."""
    from skyfix.datasets.sitl_gnss import SitlGnssError

    if common is None:
        return None
    shared = SitlGnssError(truth.vehicle, common.at, clock, cfg.lost_vehicle_home, speedup=cfg.speed)
    error = shared.apply_now()
    log.info("SITL's receiver shares the area's common GNSS error: (%.2f, %.2f, %.2f) m ENU", *error)
    return shared.start()


def _west_of(cfg: RecoveryConfig) -> tuple[float, float, float]:
    """The simulator's home for an external lost drone at ``cfg.lost_vehicle_home``: one spacing west of it."""
    from skyfix.geo import destination

    if cfg.lost_vehicle_home is None or cfg.lost_vehicle_truth_url is None:
        raise InputError("lost_vehicle_url needs lost_vehicle_home (lat, lon, alt AMSL) and lost_vehicle_truth_url")
    if cfg.mav_outage_s > 0 or cfg.gnss_return_offset_m is not None:
        raise NotImplementedError("mav_outage_s and gnss_return_offset_m are simulator faults, not for an external autopilot")
    lat, lon, alt_amsl = (float(v) for v in cfg.lost_vehicle_home)
    west_lat, west_lon = destination(lat, lon, 270.0, SPACING_M)
    return float(west_lat), float(west_lon), alt_amsl


def _survey(vehicle, frame, home_enu: np.ndarray):
    """A lawnmower over the drone's own strip north of its home, twice round, then home (RTL)."""
    from skyfix.drivers.mission import MissionItem

    e0, n0 = float(home_enu[0]), float(home_enu[1])
    items = [MissionItem.camera_trigger_distance(10.0)]
    for _ in range(SURVEY_LOOPS):
        for de, dn in ((-STRIP_HALF_WIDTH_M, 10.0), (-STRIP_HALF_WIDTH_M, STRIP_LENGTH_M),
                       (STRIP_HALF_WIDTH_M, STRIP_LENGTH_M), (STRIP_HALF_WIDTH_M, 10.0)):
            lat, lon, _ = frame.to_geodetic(e0 + de, n0 + dn, 0.0)
            items.append(MissionItem.waypoint(float(lat), float(lon), CRUISE_ALT_M))
    items.append(MissionItem.rtl())
    return items


class _Run:
    """One run's moving parts; :meth:`fly` runs it, :meth:`close` takes it all down."""

    def __init__(self, cfg: RecoveryConfig, progress: Callable[[str, float], None] | None) -> None:
        from skyfix.crps.model import DroneModel, shape_table
        from skyfix.datasets.sim import Simulator, SimulatorConfig

        self.cfg, self.progress = cfg, progress or (lambda _what, _frac: None)
        self.rng = np.random.default_rng(cfg.seed)
        # the helpers' model fit needs the quad's shape table (seconds, cached): before the clock runs
        shape_table(DroneModel(arms=4, span_m=0.5).scaled_to(1.0))
        self.external = cfg.lost_vehicle_url is not None
        # the simulator's index of each drone (None: the external autopilot)
        self.sim_index = [None if self.external and k == LOST else k - (self.external and k > LOST)
                          for k in range(len(IDS))]
        home, spacing, geoid_m = None, SPACING_M, None
        if self.external:
            home, spacing = _west_of(cfg), 2.0 * SPACING_M  # the helpers either side of the external drone
            # ArduPilot SITL's GPS reports alt_ellipsoid = AMSL (its world has no geoid): the helpers' world takes
            # the same convention, else the lost drone's reported heights sit N (tens of metres) off the helpers'
            geoid_m = 0.0
        self.sim = Simulator(SimulatorConfig(vehicles=len(IDS) - self.external, speed=cfg.speed, seed=cfg.seed,
                                             spacing_m=spacing, home=home, geoid_m=geoid_m, wind=_wind(cfg, self.rng),
                                             params={"GPS_AUTO_SWITCH": 0})).start()  # GPS_PRIMARY picks
        common = _apply_gnss_model(self.sim, cfg.gnss, cfg.seed)
        self.sitl_truth = self.sitl_gnss = None
        if self.external:
            from skyfix.datasets.sitl import SitlTruth

            self.sitl_truth = SitlTruth.connect(cfg.lost_vehicle_truth_url, cfg.lost_vehicle_home[2],
                                                geoid_m=self.sim.geoid_m, speedup=cfg.speed)
            self.sitl_truth.wait(30.0)
            self.sitl_gnss = _sitl_shares(self.sitl_truth, common, self.clock, cfg)
        self.key = secrets.token_bytes(32)
        self.faults = Faults(cfg, self)
        self.recorder = Recorder(self.sim, IDS, LOST, self.truth, common=common)
        self.services, self.threads, self.cameras = [], [], []
        self.t_loss: float | None = None
        self.timeline: list[tuple[float, str]] = []

    def clock(self) -> float:
        return self.sim.time_s

    def truth(self, k: int) -> dict[str, float]:
        """Truth of drone ``k`` (the simulator's, or the external autopilot's SIM_STATE): scoring only."""
        i = self.sim_index[k]
        return self.sitl_truth.truth(self.sim.world) if i is None else self.sim.truth(i)

    def target_key(self, drone_id: str):
        """How a camera's truth names drone ``drone_id``: its simulator index, or the external drone."""
        i = self.sim_index[IDS.index(drone_id)] if drone_id in IDS else None
        return "extra:0" if i is None else i

    def time_of(self, message) -> float:
        """Telemetry time on the swarm's clock: the simulator's autopilot stamps simulated time."""
        t = message.autopilot_time_s
        return t if math.isfinite(t) else self.sim.time_s

    def note(self, what: str) -> None:
        self.timeline.append((self.sim.time_s, what))
        log.info("t=%.1f s %s", self.sim.time_s, what)

    def start_services(self) -> None:
        from skyfix.camera import Camera
        from skyfix.crps.help_loop import HelpSetup
        from skyfix.crps.helper_eye import EyeConfig
        from skyfix.crps.service import Service, ServiceConfig
        from skyfix.crps.transport import Endpoints, InProcessBus
        from skyfix.datasets.sim.world_camera import WorldCamera
        from skyfix.datasets.sitl import SitlClock

        cfg = self.cfg
        self.bus = InProcessBus()
        camera = Camera.from_fov(*cfg.camera_px, cfg.camera_hfov_deg)
        extra = None if self.sitl_truth is None else (lambda: [self.sitl_truth.target_pose()])
        lag_s = 2.0 * max(1.0, cfg.speed / 1.5)  # a frame's wall latency on an idle machine x speed
        for i, drone_id in enumerate(IDS):
            j = self.sim_index[i]
            if j is None:  # the external autopilot: asks for help, has no simulated camera
                # its boot clock is another epoch: its stamps are moved onto the simulator's clock
                cam, setup, url, time_of = None, HelpSetup(fault_response=cfg.fault_response), cfg.lost_vehicle_url, \
                    SitlClock(self.clock, cfg.speed)
            else:
                cam = WorldCamera(self.sim, j, camera, seed=cfg.seed * 10 + i, extra_targets=extra)
                eye = EyeConfig(frame_hz=cfg.frame_hz, speed=cfg.speed, target_span_m=cam.model.span_m, target_arms=cam.model.arms)
                setup = HelpSetup(fault_response=cfg.fault_response, camera=cam, eye=eye,
                                  on_frame=self.recorder.frame_scorer(i, cam, self.target_key))
                url, time_of = self.faults.mavlink_url(i, self.sim.url(j)), self.time_of
            # the simulator reports its true velocity (+ noise), not an estimator's echo of the injected fix
            echo = ({} if j is None else {"injected_velocity_sigma_mps": None}) | (
                {} if cfg.fusion_common_share is None else {"gnss_common_share": cfg.fusion_common_share})
            self.cameras.append(cam)
            scfg = ServiceConfig(drone_id, url, Endpoints((), ()), self.key, roster=IDS, inject=True,
                                 estimate_hz=5.0 * cfg.speed, inject_hz=5.0 * cfg.speed, help=setup, **echo,
                                 lag_s=lag_s, max_lag_s=MAX_LAG_FACTOR * lag_s,
                                 clock=self.clock, time_of=time_of,
                                 log_path=None if cfg.output is None else Path(cfg.output) / f"{drone_id}.mcap")
            link = LossyLink(self.bus.attach("skyfix", drone_id), cfg.swarm_loss_rate,
                             cfg.seed * 1000 + i)
            service = Service(scfg, transport=link)
            self.services.append(service)
            thread = threading.Thread(target=service.run, daemon=True, name=f"skyfix-recovery-{drone_id}")
            thread.start()
            self.threads.append(thread)

    def _cameras_behind(self) -> bool:
        """Whether a helper's camera pipeline holds a frame grabbed more than PACE_BEHIND_S (simulated) ago."""
        now = self.sim.time_s
        for s in self.services:
            eye = s.help.eye if s.help is not None else None
            since = None if eye is None else eye.busy_since_s
            if since is not None and now - since > PACE_BEHIND_S:
                return True
        return False

    def wait(self, what: str, until: Callable[[], bool], sim_timeout_s: float, *, required: bool = True) -> None:
        """Wait (recording) until ``until()``; after ``sim_timeout_s`` simulated a SkyfixError, or (not
        ``required``) a plain return."""
        t_end = self.sim.time_s + sim_timeout_s
        while not until():
            if self.sim.time_s > t_end:
                if not required:
                    return
                raise SkyfixError(f"recovery run: timed out waiting for {what}")
            self.tick()
            time.sleep(0.05)

    def tick(self) -> None:
        self.recorder.sample(self.services)
        self.faults.tick()

    def take_off(self) -> None:
        def ready() -> bool:
            return all(s.vehicle is not None and s.vehicle.state.home is not None and s.help is not None
                       and s.vehicle.state.gps is not None and s.vehicle.state.gps.fix_type >= 3
                       for s in self.services)

        self.wait("every drone's service up (MAVLink, fusion, help)", ready, 60.0)
        from skyfix.datasets.sitl import arm_when_ready

        frame = self.sim.world
        self.recorder.homes_now()
        for k, s in enumerate(self.services):
            s.vehicle.upload_mission(_survey(s.vehicle, frame, self.recorder.home_enu[k]))
        for s in self.services:
            s.vehicle.set_mode("GUIDED")
            arm_when_ready(s.vehicle, 60.0 / self.cfg.speed + 30.0)  # a real autopilot's EKF settles first
            s.vehicle.takeoff(CRUISE_ALT_M, wait=False)
        self.note("all three drones take off")
        sent = [self.sim.time_s]

        def up() -> bool:
            if all(_climbed(s) for s in self.services):
                return True
            if self.sim.time_s - sent[0] > TAKEOFF_STALL_S:
                sent[0] = self.sim.time_s
                for s in self.services:
                    if not _climbed(s) and s.help is not None and not s.help.recovering:
                        self._climb(s)
            return False

        self.wait("take-off", up, 120.0)
        for s in self.services:
            s.vehicle.start_mission()
        self.note("surveys start")

    def _climb(self, service) -> None:
        """A take-off that stalled (a GNSS rejection during the climb held the drone, BRAKE, and it stays there
        once GNSS is trusted again): GUIDED, up to cruise height where it is. On a thread: commands wait for ACKs."""
        pos = service.vehicle.state.position
        if pos is None:
            return
        vehicle = service.vehicle
        self.note(f"{service.cfg.drone_id}'s take-off stalled at {pos.alt_rel_m:.1f} m: sent up again")

        def go() -> None:
            try:
                vehicle.set_mode("GUIDED")
                vehicle.goto(pos.lat_deg, pos.lon_deg, CRUISE_ALT_M)
            except SkyfixError as exc:
                log.warning("%s: take-off again failed: %s", service.cfg.drone_id, exc)

        threading.Thread(target=go, daemon=True, name="skyfix-recovery-climb").start()

    def fly(self) -> RecoveryResult:
        cfg = self.cfg
        self.progress("starting services", 0.0)
        if cfg.pace and not self.external:  # firmware in the loop (SITL) keeps its own clock
            self.sim.pace = (self._cameras_behind, min(cfg.speed, PACE_SPEED))
        if self.sitl_gnss is not None:
            e, n, u = self.sitl_gnss.applied_enu_m
            self.note(f"SITL's receiver carries the area's common GNSS error, ENU ({e:.2f}, {n:.2f}, {u:.2f}) m")
        self.start_services()
        self.take_off()
        t_survey = self.sim.time_s
        delay = cfg.loss_time_s if cfg.loss_time_s is not None else float(self.rng.uniform(*LOSS_WINDOW_S))
        self.progress("surveying", 0.1)
        self.wait("the loss time", lambda: self.sim.time_s >= t_survey + delay, delay + 10.0)
        self.t_loss = self.sim.time_s
        lost = self.services[LOST]
        if cfg.healthy:
            lost.vehicle.rtl()
            self.note(f"{IDS[LOST]} returns home on its own GNSS (baseline)")
        else:
            self.faults.lose_gnss(LOST, self.t_loss)
            self.note(f"{IDS[LOST]} loses its GNSS receiver")
        self.recorder.t_loss = self.t_loss
        self.progress("recovering", 0.3)

        def landed() -> bool:
            st = lost.vehicle.state if lost.vehicle is not None else None
            done = st is not None and not st.armed and self.truth(LOST)["alt_rel_m"] < 0.3
            frac = min(1.0, (self.sim.time_s - self.t_loss) / 90.0)
            self.progress("recovering", 0.3 + 0.65 * frac)
            return done or self.sim.time_s - self.t_loss > cfg.max_after_loss_s

        self.wait("the lost drone to land", landed, cfg.max_after_loss_s + 10.0)
        self.let_helpers_go()
        return self.result()

    def let_helpers_go(self, sim_timeout_s: float = 10.0) -> None:
        """After the landing, give the release a moment to reach the helpers (a few swarm messages): the run
        ends once none is still helping, or after ``sim_timeout_s`` simulated (then the timeline shows it)."""
        helpers = [s for i, s in enumerate(self.services) if i != LOST and s.help is not None]
        self.wait("the helpers' release", lambda: all(s.help.helping is None for s in helpers), sim_timeout_s,
                  required=False)

    def result(self) -> RecoveryResult:
        rec = self.recorder
        timeline = sorted(self.timeline + [(t, f"{s.cfg.drone_id}: {what}") for s in self.services
                                           if s.help is not None for t, what in s.help.events])
        landing_m = rec.landing_error_m()
        st = self.services[LOST].vehicle.state if self.services[LOST].vehicle is not None else None
        airborne = st is None or st.armed
        outcome = "holding" if airborne else ("home" if landing_m <= HOME_RADIUS_M else "landed_elsewhere")
        figures = {**rec.figures(), **self.faults.figures()}
        lost = self.services[LOST]
        figures["forged_rejected"] = float(lost.codec.dropped.get("forged", 0))
        # inputs the lost drone's fusion refused (mostly observations older than its lag: late under load)
        figures["lost_inputs_refused"] = float(lost.node.n_refused) if lost.node is not None else math.nan
        figures["service_faults"] = float(sum(s.faults for s in self.services))  # exceptions survived: 0 when sound
        # the largest fusion lag the lost drone's node took on (its observations' arrival delays, crps.arrival_lag)
        figures["lost_fusion_lag_max_s"] = lost.node.arrival_lag.largest_s if lost.node is not None else math.nan
        if lost.help is not None:
            events = lost.help.agent.requester.protocol.events
            figures["helpers_replaced"] = float(sum(what.startswith("dropped") for _, what, _ in events))
        figures["gnss_trusted_again_t_s"] = rec.gnss_trusted_again_s(figures["gnss_back_t_s"])
        if self.faults.outage is not None:  # no GPS_INPUT reaches the autopilot then: the error is not flown on
            start, end = self.faults.outage
            # until the observations of the drop's end have arrived (as late as the node's lag grew for them)
            # the error the drop left cannot be corrected
            late_s = lost.node.arrival_lag.largest_s if lost.node is not None else lost.cfg.lag_s
            around = rec.error_around(start, end + late_s)
            figures.update({f"mav_outage_{k}": v for k, v in around.items()})
        eyes = [s.help.eye for s in self.services if s.help is not None and s.help.eye is not None]
        figures["helper_frames_dropped"] = float(sum(e.frames_dropped for e in eyes))  # skipped, never queued
        figures["sim_paced_s"] = self.sim.paced_s  # simulated s run slower while a helper's camera was behind
        latency = [x for e in eyes for x in e.latency_s]  # exposure -> observation ready, simulated s
        figures["helper_obs_latency_p90_s"] = float(np.percentile(latency, 90)) if latency else math.nan
        return RecoveryResult(landing_m, rec.first_fused_fix_s(), rec.max_recovery_error_m(), rec.min_separation_m(),
                              rec.detection_share(), timeline, outcome, figures=figures)

    def close(self) -> None:
        for s in self.services:
            s.stop.set()
        for t in self.threads:
            t.join(timeout=10.0)
        self.faults.close()
        if self.sitl_gnss is not None:
            self.sitl_gnss.close()
        if self.sitl_truth is not None:
            self.sitl_truth.close()
        self.sim.stop()


def _climbed(service) -> bool:
    pos = service.vehicle.state.position if service.vehicle is not None else None
    return pos is not None and pos.alt_rel_m > CRUISE_ALT_M - 1.0


def run_recovery(cfg: RecoveryConfig, progress: Callable[[str, float], None] | None = None) -> RecoveryResult:
    """Fly one recovery run; ``progress(stage, fraction)`` is called as it goes. Writes the files into
    ``cfg.output`` when given (``result.files`` names them)."""
    if cfg.output is not None:
        out = Path(cfg.output)
        if out.exists() and not out.is_dir():
            raise InputError(f"output {out} exists and is not a folder")
        out.mkdir(parents=True, exist_ok=True)
        for name in [f"{d}.mcap" for d in IDS] + ["trajectory.csv", "trajectory.png", "report.json"]:
            (out / name).unlink(missing_ok=True)  # this run's own files from an earlier run (logs never append)
    t0 = time.monotonic()
    run = _Run(cfg, progress)
    try:
        result = run.fly()
    finally:
        run.close()
    result.figures["wall_s"] = time.monotonic() - t0
    result.figures["loss_time_s"] = run.t_loss if run.t_loss is not None else math.nan
    if cfg.output is not None:
        result.files = write_outputs(Path(cfg.output), run.recorder, result, [f"{d}.mcap" for d in IDS])
    if progress is not None:
        progress("done", 1.0)
    return result
