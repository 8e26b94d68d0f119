"""Gate detections by where the help request says the target is.

A helper answering a help request knows the target's last position with its
covariance (a :class:`skyfix.types.GeoFix`). Projected into the helper's image, that
position and its uncertainty form a pixel ellipse; only detections inside it are kept.
This is an option for directed search: it cuts false detections in proportion to the
area of the ellipse, and finds nothing when the prior is wrong.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose, world_to_pixel
from skyfix.crps.detection import Detection
from skyfix.crps.observation import POINTING_SIGMA_DEG
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.types import GeoFix

__all__ = ["PriorWindow", "prior_gate", "prior_window"]

CHI2_2DOF_99 = 9.210340371976182  # 99 % quantile of chi-square with 2 degrees of freedom


class PriorWindow:
    """The prior position projected into one image: centre ``uv_px`` (2,) and covariance ``cov_px2`` (2, 2)."""

    def __init__(self, uv_px: np.ndarray, cov_px2: np.ndarray, gate_chi2: float) -> None:
        self.uv_px = uv_px
        self.cov_px2 = cov_px2
        self.gate_chi2 = gate_chi2
        self._info = np.linalg.inv(cov_px2)

    def contains(self, uv_px: np.ndarray, extra_cov_px2: np.ndarray | None = None) -> bool:
        """Whether pixel ``uv_px`` (2,) lies inside the gate (``extra_cov_px2`` widens it, e.g. the target size)."""
        d = np.asarray(uv_px, float).reshape(2) - self.uv_px
        info = self._info if extra_cov_px2 is None else np.linalg.inv(self.cov_px2 + extra_cov_px2)
        return float(d @ info @ d) <= self.gate_chi2

    def roi(self, width: int, height: int) -> tuple[int, int, int, int] | None:
        """Bounding box (u0, v0, u1, v1) of the gate ellipse clipped to the image, None if outside."""
        half = np.sqrt(np.diag(self.cov_px2) * self.gate_chi2)
        u0, v0 = (int(math.floor(x)) for x in self.uv_px - half)
        u1, v1 = (int(math.ceil(x)) + 1 for x in self.uv_px + half)
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, width), min(v1, height)
        return (u0, v0, u1, v1) if u1 - u0 >= 8 and v1 - v0 >= 8 else None


def prior_window(camera: Camera, helper_pose: CameraPose, prior: GeoFix, *, attitude_sigma_deg: float = POINTING_SIGMA_DEG,
                 helper_cov_enu_m2: np.ndarray | None = None, gate_chi2: float = CHI2_2DOF_99) -> PriorWindow:
    """Project ``prior`` (target position and ENU covariance) into ``camera`` at ``helper_pose``.

    The pixel covariance is J (prior + helper position covariance) J^T, J the projection
    Jacobian by central differences of 0.1 m, plus the helper's pointing error
    ``attitude_sigma_deg`` converted to pixels. Raises :class:`GeometryError` when the
    prior is behind the camera.
    """
    if not isinstance(prior, GeoFix):
        raise InputError(f"prior must be a skyfix.types.GeoFix, got {type(prior).__name__}")
    att = math.radians(validate.finite_scalar("attitude_sigma_deg", attitude_sigma_deg))
    if att < 0:
        raise InputError(f"attitude_sigma_deg must be >= 0, got {attitude_sigma_deg}")
    gate = validate.positive_scalar("gate_chi2", gate_chi2)
    frame = LocalFrame(prior.lat_deg, prior.lon_deg, prior.alt_m)
    cov = prior.cov_enu_m2 + (validate.covariance("helper_cov_enu_m2", helper_cov_enu_m2, 3)
                              if helper_cov_enu_m2 is not None else 0.0)
    h = 0.1
    probes = np.vstack((np.zeros(3), np.eye(3) * h, -np.eye(3) * h))
    uv = world_to_pixel(camera, helper_pose, frame, probes)
    if not np.isfinite(uv).all():
        raise GeometryError("the prior target position is behind the helper camera")
    jac = (uv[1:4] - uv[4:7]).T / (2.0 * h)  # (2, 3) pixels per metre
    focal = math.sqrt(camera.fx * camera.fy)
    cov_px = jac @ cov @ jac.T + np.eye(2) * (focal * att) ** 2 + np.eye(2) * 1e-6
    return PriorWindow(uv[0], 0.5 * (cov_px + cov_px.T), gate)


def prior_gate(window: PriorWindow, detections: Sequence[Detection]) -> list[Detection]:
    """The detections whose centroid lies inside ``window`` (gate widened by each one's extent)."""
    out = []
    for d in detections:
        if not isinstance(d, Detection):
            raise InputError(f"detections must hold skyfix.crps.Detection, got {type(d).__name__}")
        if window.contains(d.centroid_uv, np.eye(2) * (0.5 * d.extent_px) ** 2 + d.centroid_cov_px2):
            out.append(d)
    return out
