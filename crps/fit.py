"""Least-squares fit of the known drone silhouette to the pixels of a small detection.

Moments weight every pixel of the support by its squared distance from the centroid, so
at a few pixels of extent the noise in the blur tails dominates the size. Fitting the
model instead (the :class:`~skyfix.crps.model.DroneModel` placed along the detection's
ray at range ``rho * span``, yaw ``psi``, tilted about both horizontal axes, projected
through the camera at the helper's attitude, rasterized with area coverage and convolved
with the known Gaussian PSF) uses each pixel in proportion to what it says about the size.

Image model in the window: ``I = a * T(rho, tilts, psi, du, dv) + b0 + bu * x + bv * y``.
scipy's ``least_squares`` (MINPACK Levenberg-Marquardt) on all ten parameters from each
start of a yaw grid over the symmetry period; derivatives in rho, tilts and psi by finite
differences of renders, in (du, dv) from the template gradient; the tilts have a Gaussian
prior (a flying drone leans a few degrees). It replaced a hand Gauss-Newton (issue 22):
benchmarks/crps_fit.py runs both on the same frames; on 165 scenes 40-100 m (28 Nov
2026) single frames p95 5.95 % vs 5.91 % (RMS 2.9 vs 3.2 %) at 0.91x the CPU time,
warm-started tracks p95 9.0 % vs 10.9 % at 1.38x the time per fit (one render more per
step: the library evaluates the step it takes), and the Tracker path keeps 51 frames/s
(hand 53; goal 30). Yaw and the sideways tilt are fitted because at a
few pixels both trade against the size: on noise-free renders at 100 m (target tilted
3 deg 1-sigma) the p95 size error was 10.6 % with yaw only weighed on a 4-step grid and
one tilt, 6.2 % with yaw fitted, 4.5 % with both tilts fitted (hand solver). The hypotheses are averaged in log range with their
posterior weights ``exp(-cost / 2 noise^2)``; the size sigma is the least-squares
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
from scipy.optimize import least_squares

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.crps.detection import Detection, to_gray
from skyfix.crps.model import DroneModel, rasterize_convex_parts, shape_table
from skyfix.crps.observation import angular_jacobian
from skyfix.errors import InputError
from skyfix.rotation import R_ENU_FROM_NED, r_ned_from_frd

__all__ = ["FitState", "SilhouetteFit", "SilhouetteFitConfig"]

# Natural scale of the fitted parameters for least_squares' trust region: log range, tilts and
# yaw (deg), shift (px), amplitude and background plane (grey levels of full scale).
_X_SCALE = np.array([0.05, 2.0, 2.0, 5.0, 0.5, 0.5, 0.1, 0.01, 0.01, 0.01])


@dataclass(frozen=True)
class SilhouetteFitConfig:
    """Settings of :class:`SilhouetteFit`."""

    psf_sigma_px: float = 0.7  # Gaussian optical blur of the camera, 1-sigma px (as SilhouetteConfig)
    # Fit detections up to this extent (4 x major RMS, px); larger ones keep their moments.
    # Measured on the benchmark's sky renders (0.5 m quad, 1144 px focal, noise 0.01):
    # single-frame p95 range error fit / moments 1.8 / 4.9 % at 40 m (~13 px), 2.6 / 7.8 %
    # at 55 m, 6.4 / 8.7 % at 70 m; at 25-30 m (19-23 px) the moments win (2.3-3.4 % vs 6 %).
    max_extent_px: float = 14.0
    # Longest side of the supersampled canvas; sets the supersampling (2..max_supersample). A quad seen a few
    # degrees from below shows its rotor discs as slivers under a pixel tall: at 320 px (5 sub-samples a side
    # on a 20 m helper view) noise-free fits 3 deg from below, 12 and 20 m away, read up to 2.1 % off (mean
    # +0.7 %), at 640 px within 0.7 % (mean +0.15 %) (tests/crps/test_crps_fit.py; benchmarks/helper_ranging.py
    # prints the error by elevation).
    canvas_px: int = 640
    max_supersample: int = 8  # sub-samples per pixel side, at most
    yaw_steps: int = 4  # yaw hypotheses over the symmetry period, each fitted and weighted
    iterations: int = 5  # least-squares steps (Jacobians, at most) from a yaw search
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
        for name in ("canvas_px", "max_supersample", "yaw_steps", "iterations", "tracked_iterations"):
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
    """Refine a small silhouette detection by fitting ``model`` (any span; only proportions matter).

    Example:
        A 0.5 m quad 30 m away, 10 deg above a 640 px, 60-degree camera, spans 9 px; the
        fit finds its range within 1 % (noise-free render; 3 % is the stated model error):

        >>> from skyfix.camera import Camera, CameraPose
        >>> from skyfix.crps import SilhouetteConfig, SilhouetteDetector, observe
        >>> from skyfix.datasets.drone_view import TargetPose, render_drone_view
        >>> from skyfix.geo import destination
        >>> cam = Camera.from_fov(640, 480, 60.0)
        >>> helper = CameraPose(47.0, 8.0, 400.0, yaw_deg=0.0, gimbal_pitch_deg=10.0)
        >>> lat, lon = destination(47.0, 8.0, 0.0, 29.544)  # 30 m * cos(10 deg) north, 5.21 m up
        >>> view = render_drone_view(cam, helper, TargetPose(float(lat), float(lon), 405.209, yaw_deg=30.0),
        ...                          DroneModel.quad(0.5), blur_sigma_px=0.7, rng=np.random.default_rng(0))
        >>> [det] = SilhouetteDetector(SilhouetteConfig(psf_sigma_px=0.7))(view.image)
        >>> fitted = SilhouetteFit(cam, config=SilhouetteFitConfig(psf_sigma_px=0.7))(view.image, det, helper)
        >>> fitted.kind, round(view.truth.range_m, 1)
        ('model', 30.0)
        >>> abs(observe(cam, helper, fitted, 0.5).range_m / view.truth.range_m - 1.0) < 0.01
        True
    """

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

    def moments_z(self, fitted: Detection, silhouette: Detection, helper_pose: CameraPose) -> float:
        """How far the fitted size lies from the size the silhouette's moments give, in sigmas.

        The moments' span (major-axis RMS through the model's shape table at the view elevation)
        is off by the yaw/tilt spread of that table (``ratio_std``, a few per cent) plus its
        noise, but never by tens of per cent; a warm-started fit that follows a wrong local
        minimum from frame to frame can drift that far. ``|log(fitted / moments)|`` over the
        combined sigma of both sizes.
        """
        ray, _, jac = angular_jacobian(self.camera, silhouette.centroid_uv)
        bearing = helper_pose.r_enu_from_cam() @ ray
        elevation_deg = math.degrees(math.asin(float(np.clip(-bearing[2] / np.linalg.norm(bearing), -1.0, 1.0))))
        rms_rad = math.sqrt(max(float(np.linalg.eigvalsh(jac @ silhouette.moments_px2 @ jac.T)[-1]), 1e-18))
        k_mean, k_std = (float(x) for x in shape_table(self.model).ratio(abs(elevation_deg)))
        span_px = self._focal * rms_rad / k_mean
        fit_rel = fitted.size_sigma_px / fitted.size_px
        sigma = math.sqrt(silhouette.moments_sigma_rel ** 2 + (k_std / k_mean) ** 2 + fit_rel ** 2)
        return abs(math.log(fitted.size_px / span_px)) / sigma

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
        ss = int(np.clip(cfg.canvas_px // max(shape), 2, cfg.max_supersample))
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
            out = self._solve(geometry, obs, (xs, ys), origin, shape, ss, q, iterations)
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

    def _solve(self, geometry, obs: np.ndarray, plane: tuple[np.ndarray, np.ndarray], origin: np.ndarray,
               shape: tuple[int, int], ss: int, p: np.ndarray,
               iterations: int) -> tuple[float, float, float, float, np.ndarray] | None:
        """Fit ``p`` = (log range, tilt a, tilt b, yaw (deg), shift u, v (px)) from the start ``p``.

        scipy's ``least_squares`` (MINPACK Levenberg-Marquardt) over the six and the amplitude
        and background plane, started from their linear fit to the start's template, at most
        ``iterations`` steps. Returns (cost, log range, its variance, noise^2, fitted ``p``),
        None when the drone does not come out darker than its background.
        """
        problem = _WindowProblem(self, geometry, obs, plane, origin, shape, ss, iterations + 1)
        design = np.column_stack((problem.template(p), problem.base))
        coef, *_ = np.linalg.lstsq(design, obs, rcond=None)
        if coef[0] >= 0:  # a drone darker than its background (the silhouette detector's default)
            return None
        res0 = obs - design @ coef
        n_free = max(obs.size - _X_SCALE.size, 1)
        problem.prior_w = math.sqrt(max(float(res0 @ res0) / n_free, 1e-12)) / self.config.tilt_sigma_deg
        sol = least_squares(problem.fun, np.concatenate((p, coef)), jac=problem.jac, method="lm",
                            x_scale=_X_SCALE, max_nfev=problem.max_nfev)
        x = sol.x
        if x[6] >= 0 or not np.isfinite(x).all():
            return None
        res = sol.fun[:obs.size]
        cost = float(res @ res)
        noise2 = max(cost / n_free, 1e-12)
        try:
            cov = np.linalg.inv(sol.jac.T @ sol.jac)
        except np.linalg.LinAlgError:
            return None
        return cost, float(x[0]), float(cov[0, 0]) * noise2, noise2, x[:6].copy()


class _WindowProblem:
    """Residuals and Jacobian of one window for ``least_squares``.

    ``x`` = (log range, tilt a, tilt b, yaw (deg), shift u, v (px), amplitude, background
    b0, bu, bv); residual = ``a * T + b0 + bu * x + bv * y - window`` (grey levels) and the
    tilt prior's two rows ``tilt * prior_w`` (``prior_w`` = noise / ``tilt_sigma_deg``, so
    the prior weighs as a Gaussian of that sigma against pixels of that noise). Jacobian
    columns: forward differences of renders for range, tilts and yaw, the template gradient
    for the shift, exact for the linear four.
    """

    def __init__(self, fit: SilhouetteFit, geometry, obs: np.ndarray, plane: tuple[np.ndarray, np.ndarray],
                 origin: np.ndarray, shape: tuple[int, int], ss: int, max_nfev: int) -> None:
        self._fit, self._geometry, self.obs = fit, geometry, obs
        self._origin, self._shape, self._ss = origin, shape, ss
        self.base = np.column_stack((np.ones(obs.size), plane[0].ravel(), plane[1].ravel()))
        self.max_nfev = max_nfev
        self.prior_w = 0.0
        self._nfev = 0
        self._last: tuple[bytes, np.ndarray] | None = None  # the last template, by its x[:6]
        self._last_jac: np.ndarray | None = None

    def _render(self, q: np.ndarray, shift: np.ndarray) -> np.ndarray:
        return self._fit._template(self._geometry, q, self._origin - shift, self._shape, self._ss).ravel()

    def template(self, x: np.ndarray) -> np.ndarray:
        """Template (H*W,) at ``x``; the last one is kept (``jac`` follows ``fun`` at the same x)."""
        key = x[:6].tobytes()
        if self._last is None or self._last[0] != key:
            self._last = (key, self._render(x[:4], x[4:6]))
        return self._last[1]

    def fun(self, x: np.ndarray) -> np.ndarray:
        self._nfev += 1
        return np.concatenate((x[6] * self.template(x) + self.base @ x[7:] - self.obs, self.prior_w * x[1:3]))

    def jac(self, x: np.ndarray) -> np.ndarray:
        if self._nfev >= self.max_nfev and self._last_jac is not None:
            # least_squares asks once more after its last step, for its report only: the
            # last Jacobian serves (one tracked step renders 6 templates, not 10); it is the
            # covariance's Jacobian, as the hand Gauss-Newton step's was before issue 22.
            return self._last_jac
        t = self.template(x)
        steps = np.array([1.0 / max(self._fit._focal / math.exp(x[0]), 4.0), 2.0, 2.0, 2.0])
        cols = []
        for k in range(4):
            q = x[:4].copy()
            q[k] += steps[k]
            cols.append(x[6] * (self._render(q, x[4:6]) - t) / steps[k])
        gv, gu = np.gradient(t.reshape(self._shape))
        prior = np.zeros((2, x.size))
        prior[0, 1] = prior[1, 2] = self.prior_w
        self._last_jac = np.vstack((np.column_stack((*cols, -x[6] * gu.ravel(), -x[6] * gv.ravel(), t, self.base)),
                                    prior))
        return self._last_jac
