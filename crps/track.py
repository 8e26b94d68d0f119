"""Follow one target across frames: predict, search a region of interest, gate, smooth size.

The tracker keeps an alpha-beta filter on the centroid (pixels, pixels/s) and a
two-state Kalman filter (value, rate) on the logarithm of the apparent size, whose
measurement noise is each detection's own relative size sigma: far, noisy targets are
averaged over many frames, near ones follow quickly. Each frame it searches only a
window around the prediction (fast), accepts the detection nearest the prediction inside
the gate, and falls back to a full-frame search after ``max_misses`` frames without one.
The returned detection carries the filtered size and its filtered sigma; averaging
cannot remove a bias that stays fixed while the target keeps its heading (the drone
model's yaw spread), which :func:`~skyfix.crps.observe` adds separately.

With a :class:`~skyfix.crps.fit.SilhouetteFit` and the helper pose passed to
:meth:`Tracker.update`, small silhouettes are re-measured by the model fit, each frame
started from the previous frame's solution (one Gauss-Newton step per yaw hypothesis).

With a :class:`~skyfix.crps.ground.GroundMotionFilter` (the path for terrain backgrounds),
detections are checked against the ground's motion before gating, so the track does not
start on an object lying on the ground, and is dropped if a later check finds it there;
once confirmed over a few frames the check runs every ``ground_recheck_frames`` frames
(it costs a homography refinement). ``update`` then needs the helper pose of every frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from skyfix import validate
from skyfix.camera import CameraPose
from skyfix.crps.detection import Detection, Detector
from skyfix.crps.fit import FitState, SilhouetteFit
from skyfix.crps.ground import GroundMotionFilter
from skyfix.errors import InputError

__all__ = ["Tracker", "TrackerConfig"]


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of :class:`Tracker`."""

    gate_px: float = 25.0  # accept detections within this distance of the prediction, plus one target extent
    roi_scale: float = 2.5  # search window half-size = roi_scale * extent + gate_px
    alpha: float = 0.6  # position gain of the alpha-beta filter
    beta: float = 0.2  # velocity gain
    size_accel_sigma: float = 0.1  # random walk of the log-size rate, 1/s^2 (range-rate changes)
    size_rate_sigma: float = 0.05  # prior 1-sigma of the log-size rate, 1/s (closing speed / range)
    max_misses: int = 5  # consecutive misses before the track is dropped
    # With a ground filter: once the tracked detection has passed the ground check in
    # ``ground_confirm_frames`` consecutive frames, the check runs only every
    # ``ground_recheck_frames`` frames (the filter still stores every frame); a track the
    # check finds on the ground is dropped at once. 1 checks every frame.
    ground_confirm_frames: int = 3
    ground_recheck_frames: int = 10
    # A fit warm-started from the last frame whose size lies more than this many sigmas from the
    # moments' size (SilhouetteFit.moments_z) is redone from the yaw search, and the size filter
    # restarts from it: a tracked fit can follow a wrong solution from frame to frame (e.g. a target that
    # turns: benchmarks/helper_ranging.py's "fit, no guard" line; tests/crps/test_crps_track_refit.py).
    # inf (default): no check. The helper eye sets 2.5 (EyeConfig.refit_z); the check costs ~10 % of a
    # tracked frame at 100 m (benchmarks/ranging.py --quick: 28.5 frames/s with it, 31.2 without; goal 30)
    refit_z: float = math.inf

    def __post_init__(self) -> None:
        for name in ("gate_px", "roi_scale"):
            validate.positive_scalar(f"TrackerConfig.{name}", getattr(self, name))
        validate.positive_scalar("TrackerConfig.size_accel_sigma", self.size_accel_sigma)
        validate.positive_scalar("TrackerConfig.size_rate_sigma", self.size_rate_sigma)
        if not self.refit_z > 0:  # inf: never refit
            raise InputError(f"TrackerConfig.refit_z must be > 0, got {self.refit_z}")
        for name in ("alpha", "beta"):
            value = validate.finite_scalar(f"TrackerConfig.{name}", getattr(self, name))
            if not 0.0 < value <= 1.0:
                raise InputError(f"TrackerConfig.{name} must be in (0, 1], got {value}")
        for name in ("max_misses", "ground_confirm_frames", "ground_recheck_frames"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise InputError(f"TrackerConfig.{name} must be a positive integer, got {value!r}")


class Tracker:
    """Track one target with any :class:`~skyfix.crps.detection.Detector`.

    Example:
        A quad 30 m away crossing the view at 5 m/s (0.5 m per 0.1 s frame, 9.2 px): after
        the first frame's full search each frame is searched near the prediction only, and
        the track stays on the rendered truth:

        >>> from skyfix.camera import Camera
        >>> from skyfix.crps import DroneModel, SilhouetteConfig, SilhouetteDetector
        >>> from skyfix.datasets.drone_view import TargetPose, render_drone_view
        >>> from skyfix.geo import destination
        >>> cam = Camera.from_fov(640, 480, 60.0)
        >>> helper = CameraPose(47.0, 8.0, 400.0, yaw_deg=0.0, gimbal_pitch_deg=10.0)
        >>> tracker = Tracker(SilhouetteDetector(SilhouetteConfig(psf_sigma_px=0.7)))
        >>> for k in range(3):
        ...     lat, lon = destination(47.0, 8.0, 0.0, 29.544)  # 30 m away, 10 deg up
        ...     lat, lon = destination(float(lat), float(lon), 90.0, 0.5 * k)
        ...     view = render_drone_view(cam, helper, TargetPose(float(lat), float(lon), 405.209, yaw_deg=30.0),
        ...                              DroneModel.quad(0.5), blur_sigma_px=0.7, rng=np.random.default_rng(k))
        ...     det = tracker.update(view.image, 0.1 * k)
        ...     print(k, det.kind, bool(np.allclose(det.centroid_uv, view.truth.centroid_uv, atol=0.2)))
        0 silhouette True
        1 silhouette True
        2 silhouette True
    """

    def __init__(self, detector: Detector, config: TrackerConfig | None = None,
                 fit: SilhouetteFit | None = None, ground: GroundMotionFilter | None = None) -> None:
        """``fit`` re-measures small silhouettes by the model fit when ``update`` gets the helper pose;
        ``ground`` drops detections that move with the ground (``update`` must then get the pose)."""
        if not callable(detector):
            raise InputError(f"detector must be callable (the Detector protocol), got {type(detector).__name__}")
        if fit is not None and not isinstance(fit, SilhouetteFit):
            raise InputError(f"fit must be a skyfix.crps.SilhouetteFit, got {type(fit).__name__}")
        if ground is not None and not isinstance(ground, GroundMotionFilter):
            raise InputError(f"ground must be a skyfix.crps.GroundMotionFilter, got {type(ground).__name__}")
        self.detector = detector
        self.ground = ground
        self.config = config if config is not None else TrackerConfig()
        self.fit = fit
        self.ground_checked = False  # whether the last update ran the ground check
        self.refits = 0  # warm-started fits redone from the yaw search (TrackerConfig.refit_z)
        self.reset()

    def reset(self) -> None:
        """Forget the track; the next frame is searched in full."""
        self._uv: np.ndarray | None = None
        self._vel = np.zeros(2)
        self._size = np.zeros(2)  # log extent, its rate (1/s)
        self._size_cov = np.eye(2)
        self._time_s = 0.0
        self._kind = ""
        self._verified = 0  # consecutive ground checks the tracked detection passed
        self._since_check = 0  # frames since the last ground check
        self._fit_state: FitState | None = None
        self.misses = 0

    @property
    def tracking(self) -> bool:
        """True while a track exists (the next search is a region of interest)."""
        return self._uv is not None

    def roi(self, width: int, height: int, time_s: float) -> tuple[int, int, int, int] | None:
        """Search window (u0, v0, u1, v1) predicted for ``time_s``, or None for a full-frame search."""
        if self._uv is None:
            return None
        dt = time_s - self._time_s
        pred = self._uv + self._vel * dt
        extent = math.exp(self._size[0] + self._size[1] * dt)
        half = self.config.roi_scale * extent + self.config.gate_px * (1 + self.misses)
        u0, v0 = int(pred[0] - half), int(pred[1] - half)
        u1, v1 = int(math.ceil(pred[0] + half)) + 1, int(math.ceil(pred[1] + half)) + 1
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, width), min(v1, height)
        if u1 - u0 < 16 or v1 - v0 < 16:
            return None
        return u0, v0, u1, v1

    def update(self, image: np.ndarray, time_s: float, helper_pose: CameraPose | None = None) -> Detection | None:
        """Process one frame; the accepted detection with a smoothed size, or None.

        With ``helper_pose`` (the helper camera's pose for this frame) and a ``fit``, small
        silhouettes are re-measured by the model fit, started from the last frame's attitude.
        """
        t = validate.finite_scalar("time_s", time_s)
        h, w = np.shape(image)[:2]
        roi = self.roi(w, h, t)
        found = self.detector(image, roi)
        checked = False
        self.ground_checked = False
        if self.ground is not None:
            if helper_pose is None:
                raise InputError("Tracker.update needs helper_pose when the tracker has a ground filter")
            cfg = self.config
            checked = (self._uv is None or self._verified < cfg.ground_confirm_frames
                       or self._since_check + 1 >= cfg.ground_recheck_frames)
            self.ground_checked = checked
            if checked:
                unfiltered = found
                found = self.ground(image, helper_pose, found, t)
                self._since_check = 0
                if self._uv is not None and self._on_ground(unfiltered, t):
                    self.reset()  # the track sits on the ground: drop it
                    return None
            else:
                self.ground(image, helper_pose, [], t)  # keep the frame for later checks
                self._since_check += 1
        if self._uv is None:
            if not found:
                return None
            chosen = max(found, key=lambda d: d.score)
            best = self._refine(image, chosen, helper_pose)
            self._start(best, t)
            self._verified = int(checked and self._passed(chosen))
            return replace(best, time_s=t)
        dt = t - self._time_s
        if dt <= 0:
            raise InputError(f"time_s must increase from frame to frame: {t} after {self._time_s}")
        pred = self._uv + self._vel * dt
        f = np.array([[1.0, dt], [0.0, 1.0]])
        q = self.config.size_accel_sigma ** 2 * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
        size_pred = f @ self._size
        size_cov = f @ self._size_cov @ f.T + q
        gate = self.config.gate_px * (1 + self.misses) + math.exp(size_pred[0])
        near = [d for d in found if np.linalg.norm(d.centroid_uv - pred) <= gate]
        if not near:
            self.misses += 1
            if self.misses >= self.config.max_misses:
                self.reset()
            return None
        chosen = min(near, key=lambda d: float(np.linalg.norm(d.centroid_uv - pred)))
        if checked:
            self._verified = self._verified + 1 if self._passed(chosen) else 0
        det = self._refine(image, chosen, helper_pose)
        cfg = self.config
        if det.kind != self._kind:
            # Sizes of different kinds measure different things (4 x RMS, apparent span):
            # the size filter restarts from this detection.
            self._size = np.array([math.log(max(det.extent_px, 1e-6)), 0.0])
            self._size_cov = np.diag([_size_sigma_rel(det) ** 2, cfg.size_rate_sigma ** 2])
            self._kind = det.kind
            size_pred, size_cov = self._size, self._size_cov
        resid = det.centroid_uv - pred
        self._uv = pred + cfg.alpha * resid
        self._vel = self._vel + cfg.beta * resid / dt
        r = _size_sigma_rel(det) ** 2
        gain = size_cov[:, 0] / (size_cov[0, 0] + r)
        # Innovation on the second moment (extent^2), which the detector measures without
        # bias, expressed relative to the prediction; the log of a noisy size is biased low.
        ratio = det.extent_px / math.exp(size_pred[0])
        # Fitted sizes are unbiased themselves; moment sizes through their square.
        innovation = 0.5 * (ratio ** 2 - 1.0) if det.kind == "silhouette" else ratio - 1.0
        self._size = size_pred + gain * innovation
        self._size_cov = size_cov - np.outer(gain, size_cov[0, :])
        self._time_s = t
        self.misses = 0
        return _with_size(det, math.exp(self._size[0]), math.sqrt(self._size_cov[0, 0]), t)

    def _passed(self, det: Detection) -> bool:
        """Whether this frame's ground check kept ``det`` for a reason (not ground, or in the sky)."""
        return any(c.detection is det and c.verdict in ("target", "sky") for c in self.ground.last_checks)

    def _on_ground(self, unfiltered: list[Detection], t: float) -> bool:
        """Whether the ground check judged the detection the track would take this frame to be ground."""
        dt = t - self._time_s
        pred = self._uv + self._vel * dt
        gate = self.config.gate_px * (1 + self.misses) + math.exp(self._size[0] + self._size[1] * dt)
        near = [d for d in unfiltered if np.linalg.norm(d.centroid_uv - pred) <= gate]
        if not near:
            return False
        taken = min(near, key=lambda d: float(np.linalg.norm(d.centroid_uv - pred)))
        return any(c.detection is taken and c.verdict == "ground" for c in self.ground.last_checks)

    def _refine(self, image: np.ndarray, det: Detection, helper_pose: CameraPose | None) -> Detection:
        # Hysteresis: a fitted track keeps fitting up to 1.25 x the size limit, so that noise
        # on the extent does not flip the kind (which restarts the size filter).
        slack = 1.25 if self._kind == "model" else 1.0
        if self.fit is None or helper_pose is None or not self.fit.applies(det, slack):
            return det
        warm = self._fit_state
        out = self.fit(image, det, helper_pose, start=warm, slack=slack)
        if (warm is not None and out.kind == "model" and math.isfinite(self.config.refit_z)
                and self.fit.moments_z(out, det, helper_pose) > self.config.refit_z):
            out = self.fit(image, det, helper_pose, slack=slack)
            self._kind = ""  # the size filter restarts from the fresh fit
            self.refits += 1
        self._fit_state = self.fit.last_state
        return out

    def _start(self, det: Detection, t: float) -> None:
        self._uv = det.centroid_uv.copy()
        self._vel = np.zeros(2)
        self._size = np.array([math.log(max(det.extent_px, 1e-6)), 0.0])
        self._size_cov = np.diag([_size_sigma_rel(det) ** 2, self.config.size_rate_sigma ** 2])
        self._kind = det.kind
        self._time_s = t
        self.misses = 0


def _size_sigma_rel(det: Detection) -> float:
    """Relative 1-sigma of a detection's apparent size (floored at 0.1 %)."""
    rel = det.moments_sigma_rel if det.kind == "silhouette" else det.size_sigma_px / det.size_px
    return max(float(rel), 1e-3)


def _with_size(det: Detection, extent_px: float, sigma_rel: float, time_s: float) -> Detection:
    """``det`` rescaled so that its extent is ``extent_px`` with relative sigma ``sigma_rel``."""
    factor = extent_px / det.extent_px
    if det.kind == "silhouette":
        return replace(det, moments_px2=det.moments_px2 * factor ** 2, moments_sigma_rel=sigma_rel, time_s=time_s)
    size = det.size_px * factor
    return replace(det, size_px=size, size_sigma_px=size * sigma_rel, time_s=time_s)
