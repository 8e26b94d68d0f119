"""A helper drone's camera in the simulator: a stabilised 2-axis gimbal whose frames are rendered
from the simulator's truth.

Each frame shows what the real camera would: every other vehicle as a
:class:`skyfix.crps.model.DroneModel` silhouette at its TRUE position and attitude, seen from
the helper's TRUE position through the gimbal's TRUE attitude, over textured terrain with sky
above (clouds fixed in the world). The helper's estimated position never enters the picture.
Then the sensor: lens vignetting, defocus (Gaussian PSF drawn per camera), motion blur from the
gimbal's angular rate during the exposure, auto-exposure that follows the scene with a lag
(exposure time and analogue gain; gain amplifies the noise), shot and read noise, 8-bit
quantisation with saturation.

The gimbal follows earth-frame commands (:meth:`WorldCamera.point`: yaw clockwise from north,
pitch up positive) like a real one: a first-order lag with a rate limit and pitch stops. It
REPORTS its attitude with a bias fixed per flight (heading reference, pitch encoder) and
per-frame noise, and leaves a small roll it does not report. A frame reaches the caller
``latency_s`` after its exposure: it is stamped with the exposure time; vehicle positions are
taken back to that time along their true velocity (centimetres at these latencies) and the
gimbal's attitude is read from its recorded history.

:class:`CameraFrame` carries only what a real camera delivers (pixels, exposure time, reported
attitude, intrinsics). :attr:`WorldCamera.last_truth` keeps the truth of the last frame for
scoring (e.g. whether the target was in view), never for measuring.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.crps.model import DroneModel
from skyfix.datasets.drone_view import DroneTruth, TargetPose, render_drones, terrain_background
from skyfix.datasets.render import GroundTexture, motion_blur_kernel
from skyfix.datasets.thermal_scene import forest_texture
from skyfix.errors import InputError
from skyfix.geo import LocalFrame

__all__ = ["CameraFrame", "FrameTruth", "GimbalConfig", "GimbalFault", "SensorConfig", "WorldCamera",
           "cloud_map", "world_texture"]


@dataclass(frozen=True)
class GimbalConfig:
    """The stabilised gimbal: dynamics (deg, deg/s, s) and what its attitude report gets wrong (deg, 1-sigma)."""

    max_rate_dps: float = 120.0      # slew-rate limit per axis
    tau_s: float = 0.15              # first-order lag of the attitude loop
    pitch_min_deg: float = -90.0     # mechanical stops
    pitch_max_deg: float = 30.0
    # heading reference error of the helper's compass-referenced AHRS and gimbal yaw encoder, fixed per flight:
    # 1-2 deg rms after careful magnetometer calibration (Tomasch & Winer, Tlera Corp. 2018); 0.3 before 2026-11-30
    yaw_bias_sigma_deg: float = 1.5
    pitch_bias_sigma_deg: float = 0.15  # pitch encoder / level error, fixed per flight
    noise_sigma_deg: float = 0.05    # per-report noise on each axis
    roll_sigma_deg: float = 0.1      # residual roll of the stabilisation, not reported (fixed per flight)

    @property
    def pointing_sigma_deg(self) -> float:
        """1-sigma error of the reported pointing per axis (bias and noise; yaw, the larger)."""
        return math.hypot(max(self.yaw_bias_sigma_deg, self.pitch_bias_sigma_deg), self.noise_sigma_deg)


@dataclass(frozen=True)
class SensorConfig:
    """The image sensor and lens (image units: 1 = full scale; times s)."""

    read_noise: float = 0.004        # read noise 1-sigma at unit gain
    shot_noise: float = 2.5e-4       # shot-noise variance per unit signal at unit gain
    defocus_sigma_px: tuple[float, float] = (0.6, 0.85)  # Gaussian PSF 1-sigma drawn per camera in this range
    vignetting: float = 0.2          # gain 1 - vignetting * (r / r_corner)^2
    ae_target: float = 0.45          # auto-exposure: centre-weighted mean level it steers to
    ae_tau_s: float = 0.6            # auto-exposure time constant
    flicker: float = 0.01            # per-frame relative exposure jitter
    base_exposure_s: float = 1e-3    # exposure time at unit scene gain
    max_exposure_s: float = 1.0 / 60.0  # longer would blur: analogue gain takes over beyond
    min_exposure_s: float = 1.0 / 8000.0


@dataclass(frozen=True)
class GimbalFault:
    """The gimbal looks ``yaw_offset_deg`` away from its command for ``start_s <= t < start_s + duration_s``
    (simulation time), e.g. a loose mount or a stabilisation fault: the target leaves the view. It still
    reports the attitude it actually has."""

    start_s: float
    duration_s: float
    yaw_offset_deg: float = 90.0

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.start_s + self.duration_s


@dataclass(frozen=True)
class CameraFrame:
    """One frame as the camera delivers it: ``image`` uint8 ``(H, W)``; ``t_s`` simulation time of the
    exposure; ``yaw_deg``/``pitch_deg`` the gimbal's REPORTED earth-frame attitude at exposure (yaw
    clockwise from north, pitch up positive; roll level); ``camera`` the intrinsics."""

    image: np.ndarray
    t_s: float
    yaw_deg: float
    pitch_deg: float
    camera: Camera

    def pose(self, lat_deg: float, lon_deg: float, alt_m: float) -> CameraPose:
        """The camera pose for a helper position (WGS84 degrees, ellipsoidal metres: the helper's own
        estimate) and the reported gimbal attitude."""
        return CameraPose(lat_deg, lon_deg, alt_m, yaw_deg=self.yaw_deg, gimbal_pitch_deg=self.pitch_deg,
                          stabilized=True)


@dataclass(frozen=True)
class FrameTruth:
    """Truth of one delivered frame (for scoring only): the true camera pose, the gimbal's true rates
    (deg/s, yaw then pitch), the exposure time (s), the motion-blur length (px), the image size
    (width, height) and, per other vehicle (simulator index, or ``"extra:<k>"``), its
    :class:`DroneTruth` (None: behind the camera or outside the view)."""

    t_s: float
    pose: CameraPose
    rate_dps: tuple[float, float]
    exposure_s: float
    blur_px: float
    size_px: tuple[int, int]
    vehicles: dict[int | str, DroneTruth | None] = field(default_factory=dict)

    def in_view(self, key: int | str) -> bool:
        """Whether vehicle ``key``'s centre is inside the image (it may still be too small to detect)."""
        t = self.vehicles.get(key)
        if t is None or t.bbox_px is None:
            return False
        u, v = t.centroid_uv
        return -0.5 <= u <= self.size_px[0] - 0.5 and -0.5 <= v <= self.size_px[1] - 0.5


@functools.lru_cache(maxsize=4)
def world_texture(world: LocalFrame, seed: int = 0, size_px: int = 2048, metres_per_px: float = 1.0) -> GroundTexture:
    """Forest-like ground (grey levels about 0.2-0.45) on the ground plane of ``world``, centred on its origin."""
    tex = np.clip(0.32 + 0.06 * forest_texture(size_px, metres_per_px, seed), 0.05, 0.9).astype(np.float32)
    return GroundTexture(tex, metres_per_px, world)


@functools.lru_cache(maxsize=4)
def cloud_map(seed: int = 0) -> np.ndarray:
    """Unit-variance clouds over elevation (90 rows) x azimuth (360 columns), 1 deg cells, wrapping in azimuth."""
    rng = np.random.default_rng(seed)
    tiled = np.tile(rng.standard_normal((90, 360)).astype(np.float32), (1, 3))  # blur across the 0/360 seam
    wide = np.ascontiguousarray(cv2.GaussianBlur(tiled, (0, 0), 4.0)[:, 360:720])
    wide /= wide.std() + 1e-12
    wide.setflags(write=False)
    return wide


def _wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


class _Gimbal:
    """Earth-frame yaw/pitch following commands with a lag and a rate limit; remembers its recent attitude."""

    def __init__(self, cfg: GimbalConfig, t_s: float, yaw_deg: float, pitch_deg: float,
                 fault: GimbalFault | None) -> None:
        self.cfg, self.fault = cfg, fault
        self.t_s, self.yaw, self.pitch = t_s, yaw_deg % 360.0, pitch_deg
        self.cmd = (self.yaw, self.pitch)
        self.rate = (0.0, 0.0)
        self.history: deque[tuple[float, float, float, float, float]] = deque(maxlen=400)
        self.history.append((t_s, self.yaw, self.pitch, 0.0, 0.0))

    def command(self, yaw_deg: float, pitch_deg: float) -> None:
        self.cmd = (yaw_deg % 360.0, min(max(pitch_deg, self.cfg.pitch_min_deg), self.cfg.pitch_max_deg))

    def advance(self, t_s: float, step_s: float = 0.01) -> None:
        """Integrate up to ``t_s`` in steps of at most ``step_s``; after a long gap (> 4 s) it has settled."""
        dt_total = t_s - self.t_s
        if dt_total <= 0.0:
            return
        n = max(1, math.ceil(dt_total / step_s))
        if n > 400:
            self.t_s, n = t_s - 400 * step_s, 400
        h = (t_s - self.t_s) / n
        cfg = self.cfg
        for _ in range(n):
            t = self.t_s + h
            offset = self.fault.yaw_offset_deg if self.fault is not None and self.fault.active(t) else 0.0
            r_yaw = _wrap_deg(self.cmd[0] + offset - self.yaw) / cfg.tau_s
            r_pitch = (self.cmd[1] - self.pitch) / cfg.tau_s
            r_yaw = min(max(r_yaw, -cfg.max_rate_dps), cfg.max_rate_dps)
            r_pitch = min(max(r_pitch, -cfg.max_rate_dps), cfg.max_rate_dps)
            self.yaw = (self.yaw + r_yaw * h) % 360.0
            self.pitch = min(max(self.pitch + r_pitch * h, cfg.pitch_min_deg), cfg.pitch_max_deg)
            self.t_s, self.rate = t, (r_yaw, r_pitch)
            self.history.append((t, self.yaw, self.pitch, r_yaw, r_pitch))

    def at(self, t_s: float) -> tuple[float, float, float, float]:
        """(yaw, pitch, yaw rate, pitch rate) at a past time ``t_s`` (the nearest recorded step)."""
        best = min(self.history, key=lambda rec: abs(rec[0] - t_s))
        return best[1], best[2], best[3], best[4]


class WorldCamera:
    """Camera of vehicle ``index`` of ``sim`` on a stabilised gimbal; call it for the next frame.

    ``camera`` the intrinsics (lens distortion included); ``seed`` draws this camera's biases,
    defocus and noise; ``latency_s`` from exposure to delivery; ``model`` the airframe drawn for
    every other vehicle (use its ``span_m`` for ranging); ``gimbal_fault`` makes the gimbal look
    away for a while; ``extra_targets`` returns the true poses of vehicles the simulator does not
    fly (e.g. an external autopilot's SIM_STATE), drawn as they are at delivery time;
    ``terrain_seed`` the ground texture (default: the simulator's seed, so all helpers see one world).
    Thread-safe: :meth:`point` and calls may come from different threads.
    """

    def __init__(self, sim, index: int, camera: Camera, *, seed: int, latency_s: float = 0.05,
                 model: DroneModel | None = None, gimbal: GimbalConfig | None = None,
                 sensor: SensorConfig | None = None, gimbal_fault: GimbalFault | None = None,
                 extra_targets: Callable[[], Sequence[TargetPose]] | None = None,
                 terrain_seed: int | None = None, supersample: int = 4) -> None:
        if not isinstance(camera, Camera):
            raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
        n = len(sim.servers)
        if not isinstance(index, int) or not 0 <= index < n:
            raise InputError(f"index must be a vehicle index 0..{n - 1}, got {index!r}")
        self.latency_s = validate.finite_scalar("latency_s", latency_s)
        if not 0.0 <= self.latency_s <= 2.0:
            raise InputError(f"latency_s must be in [0, 2] s, got {latency_s}")
        self.sim, self.index, self.camera = sim, index, camera
        self.model = model or DroneModel.quad()
        self.gimbal_cfg, self.sensor = gimbal or GimbalConfig(), sensor or SensorConfig()
        self.extra_targets, self.supersample = extra_targets, supersample
        self._rng = np.random.default_rng(seed)
        g = self.gimbal_cfg
        self._bias_deg = (g.yaw_bias_sigma_deg * self._rng.standard_normal(),
                          g.pitch_bias_sigma_deg * self._rng.standard_normal())
        self._roll_deg = g.roll_sigma_deg * self._rng.standard_normal()
        self.defocus_sigma_px = float(self._rng.uniform(*self.sensor.defocus_sigma_px))
        self._texture = world_texture(sim.world, sim.config.seed if terrain_seed is None else terrain_seed)
        self._clouds = cloud_map(sim.config.seed if terrain_seed is None else terrain_seed)
        truth = sim.truth(index)
        self._gimbal = _Gimbal(g, truth["time_s"], truth["yaw_deg"], 0.0, gimbal_fault)
        self._lock = threading.Lock()         # gimbal state
        self._render_lock = threading.Lock()  # noise generator, auto-exposure state, logs
        self._gain: float | None = None  # auto-exposure scene gain (signal per unit radiance)
        self._gain_t_s = 0.0
        self.last_truth: FrameTruth | None = None
        #: per delivered frame: (exposure time s, keys of the vehicles whose centre was in the image)
        self.in_view_log: list[tuple[float, tuple[int | str, ...]]] = []
        self.n_frames = 0

    def point(self, yaw_deg: float, pitch_deg: float) -> None:
        """Command the gimbal: earth-frame yaw (deg clockwise from north) and pitch (deg, up positive)."""
        yaw = validate.finite_scalar("yaw_deg", yaw_deg)
        pitch = validate.finite_scalar("pitch_deg", pitch_deg)
        t_s = self.sim.time_s
        with self._lock:
            self._gimbal.advance(t_s)
            self._gimbal.command(yaw, pitch)

    def set_gimbal_fault(self, fault: GimbalFault | None) -> None:
        """Schedule (or clear, with None) a gimbal fault during the flight (times: simulation seconds)."""
        if fault is not None and not isinstance(fault, GimbalFault):
            raise InputError(f"fault must be a GimbalFault or None, got {type(fault).__name__}")
        t_s = self.sim.time_s
        with self._lock:
            self._gimbal.advance(t_s)
            self._gimbal.fault = fault

    def __call__(self) -> CameraFrame | None:
        """The frame exposed ``latency_s`` ago, delivered now (None before the exposure time exists)."""
        with self.sim.lock:
            t_now = self.sim.time_s
            truths = [self.sim.truth(i) for i in range(len(self.sim.servers))]
        t_exp = t_now - self.latency_s
        with self._lock:  # the gimbal only: point() is never kept waiting by a render
            self._gimbal.advance(t_now)
            if t_exp < self._gimbal.history[0][0]:
                return None
            yaw, pitch, r_yaw, r_pitch = self._gimbal.at(t_exp)
        with self._render_lock:
            return self._frame(t_exp, truths, yaw, pitch, (r_yaw, r_pitch))

    # ------------------------------------------------------------------ rendering
    def _positions_at(self, truths: list[dict], dt_back_s: float) -> list[tuple[float, float, float]]:
        """(lat, lon, ellipsoidal alt) of every vehicle ``dt_back_s`` before its truth, along its velocity."""
        enu = np.array([[t["east_m"] - t["vel_east_mps"] * dt_back_s, t["north_m"] - t["vel_north_mps"] * dt_back_s,
                         t["up_m"] - t["vel_up_mps"] * dt_back_s] for t in truths])
        lat, lon, alt = self.sim.world.to_geodetic(enu[:, 0], enu[:, 1], enu[:, 2])
        return list(zip(np.atleast_1d(lat).tolist(), np.atleast_1d(lon).tolist(), np.atleast_1d(alt).tolist(),
                        strict=True))

    def _frame(self, t_exp: float, truths: list[dict], yaw: float, pitch: float,
               rate_dps: tuple[float, float]) -> CameraFrame:
        positions = self._positions_at(truths, self.latency_s)
        lat, lon, alt = positions[self.index]
        pose = CameraPose(lat, lon, alt, yaw_deg=yaw, gimbal_pitch_deg=pitch, gimbal_roll_deg=self._roll_deg,
                          stabilized=True)
        keys: list[int | str] = [i for i in range(len(truths)) if i != self.index]
        targets = [TargetPose(*positions[i], yaw_deg=truths[i]["yaw_deg"], pitch_deg=truths[i]["pitch_deg"],
                              roll_deg=truths[i]["roll_deg"]) for i in keys]
        if self.extra_targets is not None:
            extra = list(self.extra_targets())
            keys += [f"extra:{k}" for k in range(len(extra))]
            targets += extra
        radiance = terrain_background(self._texture, self.camera, pose, self._rng, cloud_map=self._clouds)
        drawn = render_drones(radiance, self.camera, pose, targets, self.model, supersample=self.supersample,
                              rng=self._rng)
        image, exposure_s, blur_px = self._expose(radiance, t_exp, rate_dps, pitch)
        self.last_truth = FrameTruth(t_exp, pose, rate_dps, exposure_s, blur_px,
                                     (self.camera.width, self.camera.height), dict(zip(keys, drawn, strict=True)))
        self.in_view_log.append((t_exp, tuple(k for k in keys if self.last_truth.in_view(k))))
        self.n_frames += 1
        g = self.gimbal_cfg
        noise = g.noise_sigma_deg * self._rng.standard_normal(2)
        return CameraFrame(image, t_exp, float((yaw + self._bias_deg[0] + noise[0]) % 360.0),
                           float(pitch + self._bias_deg[1] + noise[1]), self.camera)

    def _expose(self, radiance: np.ndarray, t_s: float, rate_dps: tuple[float, float],
                pitch_deg: float) -> tuple[np.ndarray, float, float]:
        """Lens, auto-exposure, blur, noise and quantisation: uint8 image, exposure time (s), blur length (px)."""
        s = self.sensor
        radiance *= _vignette(self.camera, s.vignetting)
        metered = _centre_weighted_mean(radiance)
        wanted = s.ae_target / max(metered, 1e-3)
        if self._gain is None:
            self._gain = wanted
        else:  # the loop converges with time constant ae_tau_s, in log exposure
            alpha = 1.0 - math.exp(-max(t_s - self._gain_t_s, 0.0) / s.ae_tau_s)
            self._gain *= (wanted / self._gain) ** alpha
        self._gain_t_s = t_s
        gain = self._gain * (1.0 + s.flicker * float(self._rng.standard_normal()))
        exposure_s = min(max(gain * s.base_exposure_s, s.min_exposure_s), s.max_exposure_s)
        analog = gain * s.base_exposure_s / exposure_s  # > 1 once the exposure time is at its limit
        signal = radiance * np.float32(gain)
        signal = cv2.GaussianBlur(signal, (0, 0), self.defocus_sigma_px)
        # image motion during the exposure: the gimbal's angular rate times the focal length
        w_yaw = math.radians(rate_dps[0]) * math.cos(math.radians(pitch_deg))
        w_pitch = math.radians(rate_dps[1])
        blur_px = math.hypot(w_yaw * self.camera.fx, w_pitch * self.camera.fy) * exposure_s
        if blur_px > 0.5:
            angle = math.degrees(math.atan2(-w_pitch * self.camera.fy, w_yaw * self.camera.fx))
            signal = cv2.filter2D(signal, -1, motion_blur_kernel(blur_px, angle))
        sigma = np.sqrt(np.maximum(signal, 0.0) * np.float32(s.shot_noise * analog)
                        + np.float32((s.read_noise * analog) ** 2))
        signal += sigma * self._rng.standard_normal(signal.shape, dtype=np.float32)
        image = np.clip(signal * 255.0 + 0.5, 0.0, 255.0).astype(np.uint8)
        return image, exposure_s, blur_px


@functools.lru_cache(maxsize=8)
def _vignette(camera: Camera, strength: float) -> np.ndarray:
    """Gain ``1 - strength * (r / r_corner)^2`` per pixel, float32 ``(H, W)``, read-only."""
    vv, uu = np.mgrid[0:camera.height, 0:camera.width].astype(np.float32)
    r2 = ((uu - camera.cx) ** 2 + (vv - camera.cy) ** 2) / (camera.cx ** 2 + camera.cy ** 2)
    gain = (1.0 - strength * r2).astype(np.float32)
    gain.setflags(write=False)
    return gain


def _centre_weighted_mean(img: np.ndarray) -> float:
    """Mean level weighting the central half of the image three times the rest (a camera's metering)."""
    h, w = img.shape
    small = cv2.resize(img, (max(w // 8, 1), max(h // 8, 1)), interpolation=cv2.INTER_AREA)
    sh, sw = small.shape
    centre = small[sh // 4: sh - sh // 4, sw // 4: sw - sw // 4]
    return float((small.sum() + 2.0 * centre.sum()) / (small.size + 2.0 * centre.size))
