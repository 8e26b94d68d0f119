"""Least-squares fit of the known drone silhouette to the pixels of a small detection.

Moments weight every pixel of the support by its squared distance from the centroid, so
at a few pixels of extent the noise in the blur tails dominates the size. Fitting the
model instead (the :class:`~skyfix.crps.model.DroneModel` placed along the detection's
ray at range ``rho * span``, yaw ``psi``, tilted about both horizontal axes, projected
through the camera at the helper's attitude, rasterized with area coverage and convolved
with the known Gaussian PSF) uses each pixel in proportion to what it says about the size.

Image model in the window: ``I = a * T(rho, tilts, psi, du, dv) + b0 + bu * x + bv * y``.
Gauss-Newton on all ten parameters from each start of a yaw grid over the symmetry
period; derivatives in rho, tilts and psi by finite differences of renders, in (du, dv)
from the template gradient; the tilts have a Gaussian prior (a flying drone leans a few
degrees). Yaw and the sideways tilt are fitted because at a few pixels both trade against
the size: on noise-free renders at 100 m (target tilted 3 deg 1-sigma) the p95 size error
was 10.6 % with yaw only weighed on a 4-step grid and one tilt, 6.2 % with yaw fitted,
4.5 % with both tilts fitted. The hypotheses are averaged in log range with their
posterior weights ``exp(-cost / 2 noise^2)``; the size sigma is the Gauss-Newton
covariance of log(rho) from the fit residual, and the error that remains without noise
(plus the spread over yaw hypotheses) is reported separately as ``size_model_sigma_rel``
because it does not average out along a track. The result is a
:class:`~skyfix.crps.detection.Detection` of kind ``"model"`` whose ``size_px`` is the
on-axis apparent span, ``focal / rho``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.crps.detection import Detection, to_gray
from skyfix.crps.model import DroneModel, rasterize_convex_parts
from skyfix.errors import InputError
from skyfix.rotation import R_ENU_FROM_NED, r_ned_from_frd

__all__ = ["FitState", "SilhouetteFit", "SilhouetteFitConfig"]


@dataclass(frozen=True)
class SilhouetteFitConfig:
    """Settings of :class:`SilhouetteFit`."""

    psf_sigma_px: float = 0.7  # Gaussian optical blur of the camera, 1-sigma px (as SilhouetteConfig)
    # Fit detections up to this extent (4 x major RMS, px); larger ones keep their moments.
    # Measured on the benchmark's sky renders (0.5 m quad, 1144 px focal, noise 0.01):
    # single-frame p95 range error fit / moments 1.8 / 4.9 % at 40 m (~13 px), 2.6 / 7.8 %
    # at 55 m, 6.4 / 8.7 % at 70 m; at 25-30 m (19-23 px) the moments win (2.3-3.4 % vs 6 %).
    max_extent_px: float = 14.0
    canvas_px: int = 320  # longest side of the supersampled canvas; sets the supersampling (2..8)
    yaw_steps: int = 4  # yaw hypotheses over the symmetry period, each fitted and weighted
    iterations: int = 5  # Gauss-Newton iterations (at most) from a yaw search
    tracked_iterations: int = 1  # ... when started from the previous frame's solution
    tilt_sigma_deg: float = 4.0  # prior 1-sigma of the target's tilt about each horizontal axis, deg
    # Relative size error left without noise (yaw and tilt trade against size at a few
    # pixels, rotors lighter than the frame, motion blur): RMS 2.8 % (target tilted 3 deg
    # 1-sigma) and 3.3 % (level) on noise-free renders at 100 m, less when nearer. It stays
    # fixed along a track, so it goes to Detection.size_model_sigma_rel, not size_sigma_px.
    model_sigma_rel: float = 0.03

    def __post_init__(self) -> None:
        validate.positive_scalar("SilhouetteFitConfig.psf_sigma_px", self.psf_sigma_px)
        validate.positive_scalar("SilhouetteFitConfig.tilt_sigma_deg", self.tilt_sigma_deg)
        validate.positive_scalar("SilhouetteFitConfig.max_extent_px", self.max_extent_px)
        if validate.finite_scalar("SilhouetteFitConfig.model_sigma_rel", self.model_sigma_rel) < 0:
            raise InputError("SilhouetteFitConfig.model_sigma_rel must be >= 0")
        for name in ("canvas_px", "yaw_steps", "iterations", "tracked_iterations"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise InputError(f"SilhouetteFitConfig.{name} must be a positive integer, got {value!r}")


@dataclass(frozen=True)
class FitState:
    """Per-yaw fit parameters of one frame, to start the next frame's fit from (a tracker keeps it).

    ``yaw_deg`` (K,) the fitted yaw of each hypothesis; ``params`` (K, 6) log range per unit
    span, the two tilts and yaw in degrees, shift u, v px of the model from its projection on
    the detection's ray.
    """

    yaw_deg: np.ndarray
    params: np.ndarray


class SilhouetteFit:
    """Refine a small silhouette detection by fitting ``model`` (any span; only proportions matter)."""

    def __init__(self, camera: Camera, model: DroneModel | None = None,
                 config: SilhouetteFitConfig | None = None) -> None:
        if not isinstance(camera, Camera):
            raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
        self.camera = camera
        self.model = (model or DroneModel.quad()).scaled_to(1.0)
        self.config = config if config is not None else SilhouetteFitConfig()
        parts = [p for _, p in self.model.parts()]
        self._points = np.concatenate(parts)  # (N, 3) body FRD, unit span
        self._splits = np.cumsum([len(p) for p in parts])[:-1]
        self._period_deg = 360.0 / self.model.arms
        self._focal = math.sqrt(camera.fx * camera.fy)
        self.last_state: FitState | None = None  # per-yaw solution of the last successful fit

    def applies(self, detection: Detection, slack: float = 1.0) -> bool:
        """Whether ``detection`` is a silhouette no larger than ``slack * max_extent_px``."""
        return detection.kind == "silhouette" and detection.extent_px <= slack * self.config.max_extent_px

    def __call__(self, image: np.ndarray, detection: Detection, helper_pose: CameraPose, *,
                 start: FitState | None = None, slack: float = 1.0) -> Detection:
        """``detection`` re-measured by the model fit; returned unchanged when it does not apply or fails.

        ``start`` (the previous frame's :attr:`last_state`, kept by a tracker) starts each
        yaw hypothesis from last frame's solution and runs ``tracked_iterations`` only;
        ``slack`` > 1 widens ``max_extent_px`` (a tracker's hysteresis).
        """
        self.last_state = None
        if not isinstance(helper_pose, CameraPose):
            raise InputError(f"helper_pose must be a skyfix.camera.CameraPose, got {type(helper_pose).__name__}")
        if not isinstance(detection, Detection):
            raise InputError(f"detection must be a skyfix.crps.Detection, got {type(detection).__name__}")
        if not self.applies(detection, slack):
            return detection
        return self._fit(image, detection, helper_pose, start) or detection

    # -- rendering --------------------------------------------------------------------
    def _setup(self, detection: Detection, helper_pose: CameraPose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(target direction (3,) camera frame, rotation camera-from-NED, tilt axes (2, 3) NED).

        Both tilt axes are horizontal: the first perpendicular to the line of sight
        (tilting about it changes how far the viewer sees onto the rotor plane, which the
        fit must not mistake for a size change), the second along it (the silhouette
        leans sideways, an in-plane rotation when seen near edge-on).
        """
        ray = self.camera.pixel_to_ray(detection.centroid_uv[None, :])[0]
        r_cam_from_ned = helper_pose.r_enu_from_cam().T @ R_ENU_FROM_NED
        los_ned = r_cam_from_ned.T @ ray
        across = np.array([-los_ned[1], los_ned[0], 0.0])
        n = float(np.linalg.norm(across))
        across = across / n if n > 1e-9 else np.array([1.0, 0.0, 0.0])
        along = np.cross(np.array([0.0, 0.0, 1.0]), across)
        return ray, r_cam_from_ned, np.stack((across, along))

    def _template(self, geometry: tuple[np.ndarray, np.ndarray, np.ndarray], q: np.ndarray, origin: np.ndarray,
                  shape: tuple[int, int], ss: int) -> np.ndarray:
        """Blurred coverage (H, W) of the unit model at ``q`` = (log range, tilt a, tilt b, yaw), degrees."""
        ray, r_cam_from_ned, axes = geometry
        tilt, _ = cv2.Rodrigues(axes.T @ np.radians(q[1:3]))
        rot = r_cam_from_ned @ tilt @ r_ned_from_frd(float(q[3]), 0.0, 0.0)
        uv = (self.camera.project(self._points @ rot.T + math.exp(q[0]) * ray) - origin) * ss + (ss - 1) / 2.0
        cover, _ = rasterize_convex_parts(np.split(uv, self._splits), [1.0] * (len(self._splits) + 1),
                                          (shape[0] * ss, shape[1] * ss))
        px = cover.reshape(shape[0], ss, shape[1], ss).mean(axis=(1, 3))
        return cv2.GaussianBlur(px, (0, 0), self.config.psf_sigma_px, borderType=cv2.BORDER_CONSTANT)

    # -- fit --------------------------------------------------------------------------
    def _fit(self, image: np.ndarray, det: Detection, pose: CameraPose,
             start: FitState | None) -> Detection | None:
        cfg = self.config
        extent = det.extent_px
        margin = int(math.ceil(4.0 * cfg.psf_sigma_px + 0.35 * extent + 3))
        cu, cv_ = det.centroid_uv
        h, w = np.shape(image)[:2]
        u0, v0 = int(math.floor(cu - 0.6 * extent)) - margin, int(math.floor(cv_ - 0.6 * extent)) - margin
        u1, v1 = int(math.ceil(cu + 0.6 * extent)) + margin + 1, int(math.ceil(cv_ + 0.6 * extent)) + margin + 1
        if u0 < 0 or v0 < 0 or u1 > w or v1 > h:
            return None
        win = to_gray(np.asarray(image)[v0:v1, u0:u1]).astype(np.float64)
        shape = win.shape
        ss = int(np.clip(cfg.canvas_px // max(shape), 2, 8))
        yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
        xs, ys = (xx - xx.mean()) / shape[1], (yy - yy.mean()) / shape[0]
        obs = win.ravel()
        geometry = self._setup(det, pose)
        # Start: the moment-based range through a flat model's RMS (about 0.224 span).
        rho0 = self._focal * 0.224 / max(det.major_rms_px, 0.3)
        origin = np.array([u0, v0], float)

        # Yaw is rarely resolvable at a few pixels, and a wrong yaw changes the fitted size:
        # fit range, tilt and shift at each yaw of a grid over the symmetry period and average
        # the log range over yaw with the posterior weights exp(-cost / 2 noise^2).
        centre = np.array([cu - u0, cv_ - v0])
        if start is None:
            yaws = np.arange(cfg.yaw_steps) * self._period_deg / cfg.yaw_steps
            starts = []
            for psi in yaws:
                t = self._template(geometry, np.array([math.log(rho0), 0.0, 0.0, psi]), origin, shape, ss)
                m0 = max(float(t.sum()), 1e-12)
                shift = centre - np.array([float((t * xx).sum()), float((t * yy).sum())]) / m0
                starts.append(np.array([math.log(rho0), 0.0, 0.0, float(psi), shift[0], shift[1]]))
            iterations = cfg.iterations
        else:
            # The shift is relative to the model placed on this frame's detection ray, so last
            # frame's solution is a valid start as it is.
            starts = [q.copy() for q in start.params]
            iterations = cfg.tracked_iterations
        results, kept = [], []
        for q in starts:
            out = self._gauss_newton(geometry, obs, (xs, ys), origin, shape, ss, q, iterations,
                                     final_cost=start is None)
            if out is not None:
                results.append(out)
                kept.append(float(out[4][3]))
        if not results:
            return None
        cost = np.array([r[0] for r in results])
        noise2 = min(r[3] for r in results)
        weight = np.exp(-(cost - cost.min()) / (2.0 * noise2))
        weight /= weight.sum()
        log_rho = np.array([r[1] for r in results])
        mean = float(weight @ log_rho)
        var_noise = float(weight @ np.array([r[2] for r in results]))
        # The spread over yaw hypotheses stays while the target keeps its heading: model error.
        var_yaw = float(weight @ (log_rho - mean) ** 2)
        # Hypotheses with negligible posterior weight are not carried to the next frame (a
        # tracker then refits only the plausible yaws); each keeps fitting its yaw freely.
        alive = weight >= 1e-3
        self.last_state = FitState(np.array(kept)[alive], np.array([r[4] for r in results])[alive])
        size_px = self._focal / math.exp(mean)
        return replace(det, kind="model", size_px=size_px, size_sigma_px=size_px * math.sqrt(var_noise),
                       size_model_sigma_rel=math.sqrt(cfg.model_sigma_rel ** 2 + var_yaw))

    def _gauss_newton(self, geometry, obs: np.ndarray, plane: tuple[np.ndarray, np.ndarray], origin: np.ndarray,
                      shape: tuple[int, int], ss: int, p: np.ndarray,
                      iterations: int, final_cost: bool) -> tuple[float, float, float, float, np.ndarray] | None:
        """Fit ``p`` = (log range, tilt a, tilt b, yaw (deg), shift u, v (px)) from the start ``p``.

        Returns (cost, log range, its variance, noise^2, fitted ``p``). ``final_cost``
        renders once more for the cost at the solution; otherwise the cost is the one
        before the last step (close enough when starting from last frame's solution).
        """
        cfg = self.config
        base = np.column_stack((np.ones(obs.size), plane[0].ravel(), plane[1].ravel()))
        steps = np.array([1.0 / max(self._focal / math.exp(p[0]), 4.0), 2.0, 2.0, 2.0])
        tilt_info = cfg.tilt_sigma_deg ** -2
        prior = np.array([0.0, tilt_info, tilt_info, 0.0, 0.0, 0.0])  # per unit noise variance
        clip = np.array([0.2, 5.0, 5.0, 10.0, 1.0, 1.0])
        cov = None

        def linear(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """(design matrix, coefficients, residual) of the amplitude and background plane."""
            a = np.column_stack((t.ravel(), base))
            coef, *_ = np.linalg.lstsq(a, obs, rcond=None)
            return a, coef, obs - a @ coef

        for _ in range(iterations):
            t = self._template(geometry, p[:4], origin - p[4:6], shape, ss)
            a, coef, res = linear(t)
            amp = coef[0]
            if amp >= 0:  # a drone darker than its background (the silhouette detector's default)
                return None
            cols = []
            for k in range(4):
                q = p[:4].copy()
                q[k] += steps[k]
                tk = self._template(geometry, q, origin - p[4:6], shape, ss)
                cols.append((amp * (tk - t) / steps[k]).ravel())
            gv, gu = np.gradient(t)
            jac = np.column_stack((*cols, -amp * gu.ravel(), -amp * gv.ravel(), a))
            noise2 = max(float(res @ res) / max(obs.size - jac.shape[1], 1), 1e-12)
            info = jac.T @ jac
            info[np.arange(6), np.arange(6)] += prior * noise2
            try:
                cov = np.linalg.inv(info)
            except np.linalg.LinAlgError:
                return None
            step = cov @ (jac.T @ res)
            step[:6] -= cov[:6, :6] @ (prior * noise2 * p)
            p = p + np.clip(step[:6], -clip, clip)
            if abs(step[0]) < 1e-4 and np.all(np.abs(step[4:6]) < 1e-3):
                break
        if cov is None or not np.isfinite(p).all():
            return None
        cost = float(res @ res)
        if final_cost:
            _, _, res = linear(self._template(geometry, p[:4], origin - p[4:6], shape, ss))
            cost = float(res @ res)
        return cost, float(p[0]), float(cov[0, 0]) * noise2, noise2, p
