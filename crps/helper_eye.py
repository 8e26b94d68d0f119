"""A helper's camera in GPS-loss recovery: point the gimbal, detect and range the target, observe.

While its drone helps, :class:`HelperEye` grabs frames from a gimbal camera (``camera()``
returns a frame with ``image`` uint8 (H, W), ``t_s`` exposure time on the swarm's clock,
``yaw_deg``/``pitch_deg`` the stabilised gimbal's earth-frame attitude as the gimbal reports
it, ``camera`` its :class:`skyfix.camera.Camera`; ``camera.point(yaw_deg, pitch_deg)`` aims
it) on a worker thread and processes the pixels as a real camera's: the helper's own fused
pose at the exposure, a search window from the target's last fix (:func:`prior_window`),
the silhouette tracker with the model fit, the aspect check, and :func:`observe` with the
helper's own position covariance. Observations wait in a queue for the service's main loop,
which signs and publishes them (:meth:`take`). Nothing here reads any truth.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from skyfix import geo
from skyfix.camera import Camera, CameraPose
from skyfix.crps.detection import Detection
from skyfix.crps.fit import SilhouetteFit, SilhouetteFitConfig
from skyfix.crps.model import DroneModel, shape_table
from skyfix.crps.observation import POINTING_SIGMA_DEG, locate, observe, shape_consistent
from skyfix.crps.prior import PriorWindow, prior_gate, prior_window
from skyfix.crps.silhouette import SilhouetteDetector
from skyfix.crps.track import Tracker, TrackerConfig
from skyfix.errors import SkyfixError
from skyfix.types import GeoFix, RelativeObservation

log = logging.getLogger(__name__)

OBS_QUEUE = 64
FRAMES_KEPT = 10_000  # the newest frames' outcomes (a service runs for hours)


@dataclass(frozen=True)
class EyeConfig:
    """Helper camera processing (rates on the swarm's clock)."""

    frame_hz: float = 5.0              # frames taken while helping, per second of the swarm's clock
    speed: float = 1.0                 # swarm-clock seconds per wall second (a simulator run faster)
    target_span_m: float = 0.5         # rotor tip to tip of the drone helped
    target_arms: int = 4
    attitude_sigma_deg: float = POINTING_SIGMA_DEG  # 1-sigma pointing error of the reported gimbal attitude
    prior_sigma_m: float = 2.0         # added to the prior's sigma: the target moves, the fix lags
    min_elevation_deg: float = 1.5     # look only above the horizon: the silhouette detector wants sky behind
    sighting_fresh_s: float = 2.0      # the gimbal follows this eye's own last sighting while it is this recent
    # the model fit (SilhouetteFit) measures silhouettes up to this extent (4 x major RMS, px); larger ones keep
    # their moments. A helper sees the target 10-60 m away, 15-50 px with a 1000 px focal: there the moments'
    # size follows the target's yaw (a bias of +-3 % fixed along a track, which fusion cannot average away) and
    # the fit, which fits the yaw, does not (benchmarks/helper_ranging.py)
    fit_max_extent_px: float = 64.0
    refit_z: float = 2.5  # a tracked fit this many sigmas from the moments' size is redone (TrackerConfig.refit_z)


class _GatedDetector:
    """The silhouette detector searching inside the prior window, keeping what falls in its gate."""

    def __init__(self) -> None:
        self.base = SilhouetteDetector()
        self.window: PriorWindow | None = None

    def __call__(self, image: np.ndarray, roi=None) -> list[Detection]:
        window = self.window
        if roi is None and window is not None:
            roi = window.roi(image.shape[1], image.shape[0])
            if roi is None:
                return []  # the prior is outside this image
        found = self.base(image, roi)
        return found if window is None else prior_gate(window, found)


class HelperEye:
    """The camera pipeline of helper ``drone_id``; ``own_fix(t_s)`` is its fused GeoFix at ``t_s``
    (with covariance) or None; ``clock()`` the swarm's clock."""

    def __init__(self, camera, drone_id: str, own_fix: Callable[[float], GeoFix | None],
                 clock: Callable[[], float], cfg: EyeConfig | None = None,
                 on_frame: Callable[[object, str, bool], None] | None = None, *, run: bool = True) -> None:
        """``on_frame(frame, target_id, detected)`` after every processed frame (a harness scores with it;
        ``detected`` None: the frame was not searched, e.g. the target below the horizon or no own pose);
        ``run`` False: no worker thread (call :meth:`observe_frame` yourself)."""
        self.camera, self.drone_id, self.own_fix, self.clock = camera, str(drone_id), own_fix, clock
        self.on_frame = on_frame
        self.cfg = cfg or EyeConfig()
        self.model = DroneModel(arms=self.cfg.target_arms, span_m=self.cfg.target_span_m)
        self.frames: deque[tuple[float, str, bool]] = deque(maxlen=FRAMES_KEPT)  # (t_s, target, detected)
        self.frames_dropped = 0  # frame slots skipped while a frame was being processed (while helping)
        self.latency_s: deque[float] = deque(maxlen=FRAMES_KEPT)  # exposure -> observation queued, clock s
        self.observations: queue.Queue[RelativeObservation] = queue.Queue(OBS_QUEUE)
        self._target: tuple[str, GeoFix] | None = None
        self._lock = threading.Lock()
        self._detector = _GatedDetector()
        self._tracker: Tracker | None = None
        self._tracker_camera: Camera | None = None
        self._fresh = False
        self._sighting: tuple[str, GeoFix] | None = None  # (target, where this eye last saw it)
        self.last_searched = False  # whether observe_frame's last frame was searched for the target
        self.busy_since_s: float | None = None  # clock() when the frame being processed was grabbed (None: idle)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"skyfix-eye-{drone_id}")
        if run:
            self._thread.start()

    def point(self, yaw_deg: float, pitch_deg: float) -> None:
        """Aim the gimbal: earth-frame yaw (deg from north, clockwise) and pitch (deg, negative down)."""
        self.camera.point(float(yaw_deg), float(pitch_deg))

    def set_target(self, target_id: str | None, prior: GeoFix | None = None) -> None:
        """Look for ``target_id`` around ``prior`` (its last fix); None stops looking."""
        with self._lock:
            changed = self._target is None or target_id is None or self._target[0] != target_id
            self._target = None if target_id is None or prior is None else (str(target_id), prior)
            if changed:
                self._sighting = None
        if changed:
            self._fresh = True  # a new target: the worker starts a new track at its next frame

    def sighting(self, target_id: str, now_s: float) -> GeoFix | None:
        """Where this eye last saw ``target_id`` (its own observation: own fused position plus the ranged
        offset, WGS84), if within ``sighting_fresh_s`` of ``now_s``; else None."""
        with self._lock:
            seen = self._sighting
        if seen is None or seen[0] != str(target_id) or now_s - seen[1].time_s > self.cfg.sighting_fresh_s:
            return None
        return seen[1]

    def take(self) -> list[RelativeObservation]:
        """The observations made since the last call."""
        out = []
        while True:
            try:
                out.append(self.observations.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=3.0)

    # -- worker ---------------------------------------------------------------------------------
    def _run(self) -> None:
        # the fit's shape table takes seconds to build: before the first frame, not while the target waits
        shape_table(self.model.scaled_to(1.0))
        period_wall_s = 1.0 / (self.cfg.frame_hz * self.cfg.speed)
        due_wall_s = time.monotonic()
        while not self._stop.is_set():
            behind_s = time.monotonic() - due_wall_s
            if behind_s < 0.0:
                if self._stop.wait(-behind_s):
                    return
                behind_s = 0.0
            # a fixed frame rate: slots that passed while the last frame was processed are skipped, never
            # queued, so the next frame processed is the newest one (the pipeline never falls behind)
            missed = int(behind_s // period_wall_s)
            due_wall_s += (missed + 1) * period_wall_s
            with self._lock:
                target = self._target
            if target is None:
                continue
            self.frames_dropped += missed
            self._process(target)

    def _process(self, target: tuple[str, GeoFix]) -> None:
        """Grab the newest frame, observe the target in it, queue the observation."""
        self.busy_since_s = self.clock()
        try:
            frame = self.camera()
            if frame is None:
                return
            obs = self.observe_frame(frame, *target)
            self.frames.append((frame.t_s, target[0], obs is not None))
            if self.on_frame is not None:
                self.on_frame(frame, target[0], obs is not None if self.last_searched else None)
            if obs is None:
                return
            self.latency_s.append(self.clock() - frame.t_s)
            try:
                self.observations.put_nowait(obs)
            except queue.Full:  # the main loop stalled: the oldest observation is worth least
                self.observations.get_nowait()
                self.observations.put_nowait(obs)
        except SkyfixError as exc:  # an unusable frame or pose: logged, the next frame is tried
            log.warning("helper %s camera: %s", self.drone_id, exc)
        except Exception:  # noqa: BLE001 - a camera thread must outlive a bug in one frame
            log.exception("helper %s camera frame failed", self.drone_id)
        finally:
            self.busy_since_s = None

    def _sight(self, target_id: str, obs: RelativeObservation) -> None:
        """Keep where this eye saw the target: the gimbal follows its own track, not only the requester's fix
        (a fix a few metres off at 30 m range puts the target at the frame's edge, then outside it)."""
        if not obs.has_observer_position:
            return
        seen = locate([obs])
        with self._lock:
            self._sighting = (target_id, seen)  # sighting() answers for this target only

    def _pose(self, frame) -> tuple[CameraPose, GeoFix] | None:
        own = self.own_fix(frame.t_s)
        if own is None:
            return None
        pose = CameraPose(own.lat_deg, own.lon_deg, own.alt_m, yaw_deg=float(frame.yaw_deg),
                          gimbal_pitch_deg=float(frame.pitch_deg), stabilized=True)  # earth-frame gimbal
        return pose, own

    def observe_frame(self, frame, target_id: str, prior: GeoFix) -> RelativeObservation | None:
        """The observation of ``target_id`` (last known at ``prior``) in ``frame``, or None when not found.
        Frames must come in time order (the tracker's state carries over)."""
        self.last_searched = False
        posed = self._pose(frame)
        if posed is None:
            return None
        pose, own = posed
        if _elevation_deg(own, prior) < self.cfg.min_elevation_deg:
            return None  # the target against the ground: clutter a single silhouette cannot be told from
        self.last_searched = True
        camera = frame.camera
        tracker = self._tracker  # only this (worker) thread replaces it
        if tracker is None or self._fresh or self._tracker_camera is not camera:
            self._fresh = False
            fit = SilhouetteFit(camera, self.model, SilhouetteFitConfig(max_extent_px=self.cfg.fit_max_extent_px))
            tracker = self._tracker = Tracker(self._detector, TrackerConfig(refit_z=self.cfg.refit_z), fit=fit)
            self._tracker_camera = camera
        floor = np.eye(3) * self.cfg.prior_sigma_m ** 2
        widened = GeoFix(prior.lat_deg, prior.lon_deg, prior.alt_m, prior.cov_enu_m2 + floor,
                         prior.time_s, prior.source_id)
        try:
            self._detector.window = prior_window(camera, pose, widened, attitude_sigma_deg=self.cfg.attitude_sigma_deg,
                                                 helper_cov_enu_m2=own.cov_enu_m2)
        except SkyfixError:  # the prior is behind the camera: nothing to look for in this frame
            return None
        det = tracker.update(frame.image, frame.t_s, pose)
        if det is None and tracker.tracking:
            # the gimbal turned between frames and the target jumped out of the tracker's gate: the prior
            # (a world position, not a pixel) still places it, so search its window afresh
            tracker.reset()
            det = tracker.update(frame.image, frame.t_s, pose)
        if det is None or not shape_consistent(camera, pose, det, self.model):
            return None
        obs = observe(camera, pose, det, self.cfg.target_span_m, model=self.model, observer_id=self.drone_id,
                      target_id=target_id, time_s=frame.t_s, attitude_sigma_deg=self.cfg.attitude_sigma_deg,
                      observer_cov_enu_m2=own.cov_enu_m2)
        if not math.isfinite(obs.range_m) or obs.range_m <= 0:
            return None
        self._sight(target_id, obs)
        return obs


def _elevation_deg(own: GeoFix, target: GeoFix) -> float:
    """Elevation of ``target`` seen from ``own`` above the local horizontal, degrees."""
    _, dist_m = geo.inverse(own.lat_deg, own.lon_deg, target.lat_deg, target.lon_deg)
    return math.degrees(math.atan2(target.alt_m - own.alt_m, max(float(dist_m), 1e-3)))
