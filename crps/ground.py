"""Reject detections that sit on the ground, using the helper's motion over a sequence.

A compact dark object on the ground (a rock, a bush, a car) looks like a small drone in
one frame; no single-frame test separates them. Across frames they differ: the ground is
a plane, so between two helper poses it moves by a homography, and everything on it
cancels once the earlier frame is warped by that homography. A drone is nearer than the
ground along its ray (parallax) and usually moving, so it does not cancel.

Per frame, :class:`GroundMotionFilter` takes the image, the helper's
:class:`~skyfix.camera.CameraPose` and the detections, and

1. predicts, for each earlier frame kept (up to ``history_s``), the ground-plane
   homography current -> earlier from the two poses (pixels cast onto the plane at
   ``ground_alt_m`` and projected into the earlier camera, exact for a camera without
   lens distortion), and refines it on the images (``cv2.findTransformECC`` on a reduced
   copy), because attitude errors of a few tenths of a degree move the ground by pixels;
2. for each detection, picks the most recent earlier frame in which a static target at
   the range its size implies would have moved, relative to the ground behind it, by more
   than the detection's window (otherwise the oldest frame: a moving target still shows);
3. warps that frame's window onto the current one and measures the fraction of the
   detection's contrast that the warped ground does not explain
   (``residual_fraction``: about 0 for an object on the ground, about 1 for a drone);
   detections below ``min_residual_fraction`` are ground and are dropped.

Detections whose ray does not reach the ground (sky) are kept. Physics limits: a target
that neither moves nor has parallax (helper hovering, target hovering) cancels like the
ground and is dropped; objects standing off the plane (trees, masts) have parallax and
are kept like a drone. Without an earlier frame nothing can be decided
(``keep_undecided``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.crps.detection import Detection, to_gray
from skyfix.crps.model import DroneModel
from skyfix.crps.observation import observe
from skyfix.errors import InputError
from skyfix.geo import LocalFrame

_BAND_PX = 10  # width of the ground band around a detection's window that checks the registration, px

__all__ = ["GroundCheck", "GroundMotionConfig", "GroundMotionFilter"]


@dataclass(frozen=True)
class GroundMotionConfig:
    """Settings of :class:`GroundMotionFilter`."""

    history_s: float = 1.0  # how far back earlier frames are kept, s
    min_spacing_s: float = 0.09  # earlier frames are kept at least this far apart, s
    # Contrast of a detection not explained by the warped earlier frame, as a fraction of
    # its own contrast, below which it is ground. Registration error (~0.1 px) and
    # resampling leave ~0.1 on a ground object; a drone that moved off its window leaves ~1.
    min_residual_fraction: float = 0.5
    psf_sigma_px: float = 0.7  # camera blur 1-sigma, px: sets the window margin
    ecc_scale: float = 0.25  # image scale at which the homography is refined
    ecc_iterations: int = 25  # ECC iterations per pyramid level (at most)
    max_refine_px: float = 80.0  # larger corrections of the pose-predicted homography are refused, px
    max_ground_range_m: float = 3000.0  # rays reaching the ground farther than this count as sky, m
    keep_undecided: bool = False  # keep detections that cannot be checked (first frame, window off-image)

    def __post_init__(self) -> None:
        for name in ("history_s", "min_spacing_s", "psf_sigma_px", "max_refine_px", "max_ground_range_m"):
            validate.positive_scalar(f"GroundMotionConfig.{name}", getattr(self, name))
        for name in ("min_residual_fraction", "ecc_scale"):
            value = validate.finite_scalar(f"GroundMotionConfig.{name}", getattr(self, name))
            if not 0.0 < value <= 1.0:
                raise InputError(f"GroundMotionConfig.{name} must be in (0, 1], got {value}")
        if not isinstance(self.ecc_iterations, int) or self.ecc_iterations < 1:
            raise InputError(f"GroundMotionConfig.ecc_iterations must be a positive integer, got "
                             f"{self.ecc_iterations!r}")


@dataclass(frozen=True)
class GroundCheck:
    """What the filter found for one detection.

    ``verdict``: ``"target"`` (kept: does not match the ground), ``"ground"`` (dropped),
    ``"sky"`` (kept: its ray misses the ground), ``"undecided"`` (no usable earlier frame).
    ``residual_fraction`` (NaN unless checked), ``parallax_px`` the predicted motion of a
    static target at the size range relative to the ground behind it, ``dt_s`` the age of
    the earlier frame used.
    """

    detection: Detection
    verdict: str
    residual_fraction: float = float("nan")
    parallax_px: float = float("nan")
    dt_s: float = float("nan")


@dataclass
class _Frame:
    time_s: float
    pose: CameraPose
    gray: np.ndarray  # (H, W) float32
    small: np.ndarray  # (h, w) float32 at ecc_scale


class GroundMotionFilter:
    """Drop detections that move with the ground plane at ``ground_alt_m`` (WGS84 ellipsoidal metres).

    ``target_size_m`` (and ``model``) give each detection's range, from which its expected
    parallax is predicted. Call once per frame, in time order, with every frame of the
    sequence (also frames without detections: they become the earlier frames). It keeps
    up to ``history_s / min_spacing_s + 1`` grey frames (about 100 MB at 1920x1080 with the
    defaults).
    """

    def __init__(self, camera: Camera, ground_alt_m: float, target_size_m: float, *,
                 model: DroneModel | None = None, config: GroundMotionConfig | None = None) -> None:
        if not isinstance(camera, Camera):
            raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
        self.camera = camera
        self.ground_alt_m = validate.finite_scalar("ground_alt_m", ground_alt_m)
        self.target_size_m = validate.positive_scalar("target_size_m", target_size_m)
        self.model = model
        self.config = config if config is not None else GroundMotionConfig()
        self.last_checks: list[GroundCheck] = []
        self.reset()

    def reset(self) -> None:
        """Forget the earlier frames (e.g. after a gap in the sequence)."""
        self._history: deque[_Frame] = deque()
        self._frame: LocalFrame | None = None
        self._time_s = -math.inf

    # -- public -----------------------------------------------------------------------
    def __call__(self, image: np.ndarray, helper_pose: CameraPose, detections: list[Detection],
                 time_s: float) -> list[Detection]:
        """The detections of this frame that are not on the ground; stores the frame for later ones."""
        if not isinstance(helper_pose, CameraPose):
            raise InputError(f"helper_pose must be a skyfix.camera.CameraPose, got {type(helper_pose).__name__}")
        t = validate.finite_scalar("time_s", time_s)
        if t <= self._time_s:
            raise InputError(f"time_s must increase from frame to frame: {t} after {self._time_s}")
        gray = to_gray(image)
        if gray.shape != (self.camera.height, self.camera.width):
            raise InputError(f"image must be {self.camera.width}x{self.camera.height} (the camera), got "
                             f"{gray.shape[1]}x{gray.shape[0]}")
        for i, d in enumerate(detections):
            if not isinstance(d, Detection):
                raise InputError(f"detections[{i}] must be a skyfix.crps.Detection, got {type(d).__name__}")
        self._anchor(helper_pose)
        s = self.config.ecc_scale
        small = cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else gray
        current = _Frame(t, helper_pose, gray, small)
        homographies: dict[int, np.ndarray | None] = {}
        self.last_checks = [self._check(current, d, homographies) for d in detections]
        self._remember(current)
        keep = ("target", "sky", "undecided") if self.config.keep_undecided else ("target", "sky")
        return [c.detection for c in self.last_checks if c.verdict in keep]

    # -- geometry ---------------------------------------------------------------------
    def _anchor(self, pose: CameraPose) -> None:
        """Tangent plane of the ground near the helper; re-anchored after 2 km (plane sag < 0.3 m)."""
        if self._frame is not None:
            east, north, _ = (float(x) for x in self._frame.to_enu(pose.lat_deg, pose.lon_deg, self.ground_alt_m))
            if math.hypot(east, north) < 2000.0:
                return
            self.reset()
        self._frame = LocalFrame(pose.lat_deg, pose.lon_deg, self.ground_alt_m)

    def _on_ground(self, pose: CameraPose, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ground points (N, 3), ray (N, 3), distance (N,), NaN where the ray misses) in the anchor frame."""
        cam, rot = pose.in_frame(self._frame)
        rays = self.camera.pixel_to_ray(uv) @ rot.T
        down = rays[:, 2] < -1e-9
        dist = np.where(down, cam[2] / np.where(down, -rays[:, 2], 1.0), np.nan)
        dist = np.where(dist <= self.config.max_ground_range_m, dist, np.nan)
        return cam + dist[:, None] * rays, rays, dist

    def _project(self, pose: CameraPose, pts: np.ndarray) -> np.ndarray:
        cam, rot = pose.in_frame(self._frame)
        return self.camera.project((pts - cam) @ rot)

    def _predicted_homography(self, cur: _Frame, past: _Frame) -> np.ndarray | None:
        """Ground homography current -> past pixels from the two poses (None if the ground is barely seen)."""
        uu, vv = np.meshgrid(np.linspace(0, self.camera.width - 1, 12), np.linspace(0, self.camera.height - 1, 8))
        uv = np.stack((uu.ravel(), vv.ravel()), axis=1)
        pts, _, dist = self._on_ground(cur.pose, uv)
        ok = np.isfinite(dist)
        if ok.sum() < 12:
            return None
        uv_past = self._project(past.pose, pts[ok])
        good = np.isfinite(uv_past).all(axis=1)
        if good.sum() < 12:
            return None
        hom, _ = cv2.findHomography(uv[ok][good], uv_past[good], 0)
        return hom

    def _homography(self, cur: _Frame, past: _Frame) -> np.ndarray | None:
        """Predicted ground homography refined on the reduced images; None when it cannot be formed.

        Coarse to fine: half of ``ecc_scale`` (pose errors of tens of pixels), then ``ecc_scale``.
        """
        pred = self._predicted_homography(cur, past)
        if pred is None:
            return None
        cfg = self.config
        warp = pred
        for level, (cur_img, past_img) in enumerate(((_half(cur.small), _half(past.small)), (cur.small, past.small))):
            s = cfg.ecc_scale / (2.0 if level == 0 else 1.0)
            scale = np.diag([s, s, 1.0])
            start = (scale @ warp @ np.linalg.inv(scale)).astype(np.float32)
            start /= start[2, 2]
            h, w = cur_img.shape
            # Only ground pixels take part (rays above the horizon see sky, which has no parallax).
            vv, uu = np.mgrid[0:h, 0:w]
            uv = np.stack(((uu.ravel() + 0.5) / s - 0.5, (vv.ravel() + 0.5) / s - 0.5), axis=1)
            mask = np.isfinite(self._on_ground(cur.pose, uv)[2]).reshape(h, w)
            if mask.mean() < 0.05:
                return None
            try:
                _, refined = cv2.findTransformECC(cur_img, past_img, start, cv2.MOTION_HOMOGRAPHY,
                                                  (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
                                                   cfg.ecc_iterations if level == 0 else max(cfg.ecc_iterations // 3, 1), 1e-4 if level == 0 else 1e-5),
                                                  mask.astype(np.uint8), 3 if level == 0 else 5)
            except cv2.error:
                return pred
            warp = np.linalg.inv(scale) @ refined.astype(np.float64) @ scale
        probe = np.array([[[0.0, 0.0], [self.camera.width - 1.0, 0.0], [0.0, self.camera.height - 1.0],
                           [self.camera.width - 1.0, self.camera.height - 1.0],
                           [self.camera.width / 2.0, self.camera.height / 2.0]]])
        moved = np.abs(cv2.perspectiveTransform(probe, warp) - cv2.perspectiveTransform(probe, pred))
        if not np.isfinite(moved).all() or moved.max() > cfg.max_refine_px:
            return pred
        return warp / warp[2, 2]

    # -- the check --------------------------------------------------------------------
    def _window(self, det: Detection) -> tuple[int, int, int, int, int]:
        """(u0, v0, u1, v1, ring) of the measurement window around ``det``, end-exclusive."""
        size = max(det.bbox_px[2] - det.bbox_px[0], det.bbox_px[3] - det.bbox_px[1], det.extent_px)
        margin = int(math.ceil(3.0 * self.config.psf_sigma_px + 3 + 0.25 * size))
        cu, cv_ = det.centroid_uv
        half = int(math.ceil(0.5 * size)) + margin
        return int(cu) - half, int(cv_) - half, int(cu) + half + 1, int(cv_) + half + 1, 3

    def _check(self, cur: _Frame, det: Detection, homographies: dict[int, np.ndarray | None]) -> GroundCheck:
        ground_pt, ray, dist = self._on_ground(cur.pose, det.centroid_uv[None, :])
        if not np.isfinite(dist[0]):
            return GroundCheck(det, "sky")
        u0, v0, u1, v1, ring = self._window(det)
        h, w = cur.gray.shape
        if u0 < 0 or v0 < 0 or u1 > w or v1 > h or not self._history:
            return GroundCheck(det, "undecided")
        try:
            range_m = observe(self.camera, cur.pose, det, self.target_size_m, model=self.model).range_m
        except InputError:
            return GroundCheck(det, "undecided")
        cam, _ = cur.pose.in_frame(self._frame)
        target_pt = cam + min(range_m, float(dist[0])) * ray[0]
        need_px = float(u1 - u0)  # a static target moves off its own window
        past_frames = list(self._history)
        parallax = []
        for past in past_frames:
            a, b = self._project(past.pose, np.stack((target_pt, ground_pt[0])))
            parallax.append(float(np.linalg.norm(a - b)) if np.isfinite(a).all() and np.isfinite(b).all() else 0.0)
        # Most recent frame with enough parallax; otherwise the oldest first (most time for the target to move).
        order = [i for i in range(len(past_frames) - 1, -1, -1) if parallax[i] >= need_px]
        order += [i for i in range(len(past_frames)) if parallax[i] < need_px]
        # The window plus a band around it in which the ground alone must match (registration check).
        pad = _BAND_PX
        b0, c0, b1, c1 = u0 - pad, v0 - pad, u1 + pad, v1 + pad
        if b0 < 0 or c0 < 0 or b1 > w or c1 > h:
            return GroundCheck(det, "undecided")
        vv, uu = np.mgrid[c0:c1, b0:b1].astype(np.float32)
        pts = np.stack((uu.ravel(), vv.ravel()), axis=1)[None].astype(np.float64)
        cur_big = cur.gray[c0:c1, b0:b1]
        band = np.ones(cur_big.shape, bool)
        band[pad:-pad, pad:-pad] = False
        noise = _noise_sigma(cur_big)
        for i in order:
            if i not in homographies:
                homographies[i] = self._homography(cur, past_frames[i])
            hom = homographies[i]
            if hom is None:
                continue
            mapped = cv2.perspectiveTransform(pts, hom)[0].reshape(c1 - c0, b1 - b0, 2).astype(np.float32)
            if (mapped[..., 0].min() < 0 or mapped[..., 1].min() < 0 or mapped[..., 0].max() > w - 1
                    or mapped[..., 1].max() > h - 1):
                continue
            past_big = cv2.remap(past_frames[i].gray, mapped[..., 0], mapped[..., 1], cv2.INTER_LINEAR)
            if not _registered(cur_big[band], past_big[band], noise):
                continue
            frac = _residual_fraction(cur_big[pad:-pad, pad:-pad], past_big[pad:-pad, pad:-pad], ring)
            verdict = "target" if frac >= self.config.min_residual_fraction else "ground"
            return GroundCheck(det, verdict, frac, parallax[i], cur.time_s - past_frames[i].time_s)
        return GroundCheck(det, "undecided")

    def _remember(self, frame: _Frame) -> None:
        cfg = self.config
        while self._history and frame.time_s - self._history[0].time_s > cfg.history_s:
            self._history.popleft()
        if not self._history or frame.time_s - self._history[-1].time_s >= cfg.min_spacing_s:
            self._history.append(frame)
        self._time_s = frame.time_s


def _noise_sigma(img: np.ndarray) -> float:
    """Sensor-noise 1-sigma from horizontal second differences (MAD); texture raises it."""
    d2 = img[:, 2:] - 2.0 * img[:, 1:-1] + img[:, :-2]
    return max(1.4826 * float(np.median(np.abs(d2))) / math.sqrt(6.0), 1e-6)


def _registered(cur: np.ndarray, past: np.ndarray, noise: float) -> bool:
    """Whether the ground band around a detection matches between the frames.

    Registered ground leaves the difference at the noise level (sqrt 2 of one frame's,
    plus resampling); a failed registration leaves it at the texture's own spread.
    A drone seen in the earlier frame inside the band is a minority (medians).
    """
    diff = cur.astype(np.float64) - past
    spread_diff = 1.4826 * float(np.median(np.abs(diff - np.median(diff))))
    spread_tex = 1.4826 * float(np.median(np.abs(cur - np.median(cur))))
    return spread_diff <= max(0.25 * spread_tex, 2.0 * noise)


def _half(img: np.ndarray) -> np.ndarray:
    return cv2.resize(img, (max(img.shape[1] // 2, 1), max(img.shape[0] // 2, 1)), interpolation=cv2.INTER_AREA)


def _contrast(win: np.ndarray, ring: int) -> np.ndarray:
    """``win`` minus a plane fitted (robustly) to its outer ``ring`` pixels, float64."""
    win = win.astype(np.float64)
    hh, ww = win.shape
    vv, uu = np.mgrid[0:hh, 0:ww]
    on_ring = (uu < ring) | (vv < ring) | (uu >= ww - ring) | (vv >= hh - ring)
    a = np.column_stack((np.ones(int(on_ring.sum())), uu[on_ring], vv[on_ring]))
    vals = win[on_ring]
    coef, *_ = np.linalg.lstsq(a, vals, rcond=None)
    res = vals - a @ coef
    keep = np.abs(res) <= 3.0 * max(1.4826 * float(np.median(np.abs(res))), 1e-6)
    if keep.sum() >= 8:
        coef, *_ = np.linalg.lstsq(a[keep], vals[keep], rcond=None)
    return win - (coef[0] + coef[1] * uu + coef[2] * vv)


def _residual_fraction(cur_win: np.ndarray, past_win: np.ndarray, ring: int) -> float:
    """Fraction of the current window's object contrast left after subtracting the warped earlier window.

    Each window's contrast is taken against its own background plane; the fraction is
    the contrast-weighted mean of (current - earlier) over current, in the object's polarity.
    """
    c_cur = _contrast(cur_win, ring)[ring:-ring, ring:-ring]
    c_past = _contrast(past_win, ring)[ring:-ring, ring:-ring]
    sign = -1.0 if c_cur.sum() < 0 else 1.0
    weight = np.maximum(sign * c_cur, 0.0)
    denom = float((weight * sign * c_cur).sum())
    if denom <= 0.0:
        return 0.0
    return float((weight * sign * (c_cur - c_past)).sum()) / denom
