"""Georeferencing: the similarity transform from a reconstruction to the photos' GPS.

The target frame is a skyfix :class:`~skyfix.geo.LocalFrame` (ENU metres) whose origin is
the mean GPS position. The photos' GPS altitudes are AMSL; they are used as the frame's
heights unchanged, so every height the pipeline writes (DSM, point cloud) is AMSL too.
Treating AMSL as ellipsoidal shifts the frame by the geoid undulation, which is constant
to centimetres over a survey, so horizontal positions and relative heights are unaffected.

The transform is found by LO-RANSAC (pycolmap ``estimate_sim3d_robust``) so a few bad GPS
tags do not pull it, then refined by least squares on the inliers. Photos along a single
straight line (or nearly: cross-line spread under a quarter of the length) leave the
roll about that line free or decided by GPS noise; then each camera also contributes a
point below it along its viewing direction, matched to a point straight below its GPS
position (the photos are assumed near nadir) and the report says so.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from skyfix.geo import LocalFrame
from skyfix.mapping.photos import Photo

__all__ = ["ModelGeoref", "georeference", "survey_frame"]

log = logging.getLogger(__name__)


def survey_frame(photos: list[Photo]) -> LocalFrame | None:
    """Local ENU frame at the mean GPS position (AMSL height), or None without GPS."""
    lla = np.array([(p.gps_lat_deg, p.gps_lon_deg, p.gps_alt_amsl_m) for p in photos if p.has_gps])
    if len(lla) == 0:
        return None
    return LocalFrame(*lla.mean(axis=0))


@dataclass
class ModelGeoref:
    """Outcome for one model. Residuals are model camera centre minus GPS, ENU metres."""

    model_index: int
    registered: int
    georeferenced: bool
    reason: str = ""
    scale: float = float("nan")
    rotation_xyzw: list[float] = field(default_factory=list)
    translation_m: list[float] = field(default_factory=list)
    residuals_enu_m: dict[str, list[float]] = field(default_factory=dict)
    inliers: list[str] = field(default_factory=list)
    nadir_assumed: bool = False

    @property
    def rms_m(self) -> float:
        """RMS 3-D residual over every registered photo with GPS (outliers included)."""
        if not self.residuals_enu_m:
            return float("nan")
        r = np.array(list(self.residuals_enu_m.values()))
        return float(np.sqrt((r ** 2).sum(axis=1).mean()))

    @property
    def rms_horizontal_m(self) -> float:
        if not self.residuals_enu_m:
            return float("nan")
        r = np.array(list(self.residuals_enu_m.values()))
        return float(np.sqrt((r[:, :2] ** 2).sum(axis=1).mean()))

    @property
    def inlier_rms_m(self) -> float:
        if not self.inliers:
            return float("nan")
        r = np.array([self.residuals_enu_m[n] for n in self.inliers])
        return float(np.sqrt((r ** 2).sum(axis=1).mean()))

    def to_dict(self) -> dict:
        return {"model": self.model_index, "registered": self.registered, "georeferenced": self.georeferenced,
                "reason": self.reason, "scale": self.scale, "rotation_xyzw": self.rotation_xyzw,
                "translation_m": self.translation_m, "rms_m": self.rms_m,
                "rms_horizontal_m": self.rms_horizontal_m, "inlier_rms_m": self.inlier_rms_m,
                "inliers": len(self.inliers), "outliers": sorted(set(self.residuals_enu_m) - set(self.inliers)),
                "nadir_assumed": self.nadir_assumed, "residuals_enu_m": self.residuals_enu_m}


def _apply(sim, points: np.ndarray) -> np.ndarray:
    """``(N, 3)`` points mapped by a ``pycolmap.Sim3d``."""
    m = np.asarray(sim.matrix())
    return points @ m[:, :3].T + m[:, 3]


def _collinear(points: np.ndarray, ratio: float = 0.25) -> bool:
    """True when the cross-line spread is under ``ratio`` of the along-line spread: a few
    metres of GPS noise then decide the roll about the line (it can even flip the model)."""
    sv = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return sv[0] == 0 or sv[1] / sv[0] < ratio


def georeference(rec, photos: list[Photo], frame: LocalFrame, model_index: int = 0, *,
                 max_error_m: float = 10.0) -> ModelGeoref:
    """Fit the model-to-ENU similarity and apply it to ``rec`` (a ``pycolmap.Reconstruction``,
    transformed in place). Needs 3 registered photos with GPS; otherwise ``rec`` is left
    as it is and the result says why (also when no transform fits 3 photos within
    ``max_error_m``). ``max_error_m``: RANSAC inlier distance.
    """
    import pycolmap

    by_name = {p.name: p for p in photos}
    names, centres, gps = [], [], []
    dirs_model = []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        p = by_name.get(image.name)
        if p is None or not p.has_gps:
            continue
        names.append(image.name)
        centres.append(image.projection_center())
        dirs_model.append(image.viewing_direction())
        gps.append((p.gps_lat_deg, p.gps_lon_deg, p.gps_alt_amsl_m))
    result = ModelGeoref(model_index, rec.num_reg_images(), False)
    if len(names) < 3:
        result.reason = f"only {len(names)} registered photo(s) with GPS (3 needed); model left unreferenced"
        log.warning("model %d: %s", model_index, result.reason)
        return result
    src = np.array(centres)
    tgt = frame.to_enu_points(np.array(gps))
    src_fit, tgt_fit = src, tgt
    if _collinear(tgt):
        # Roll about the line is free: add a point below each camera (near-nadir photos).
        # The point is max_error_m below, so a photo tilted up to ~30 deg stays a RANSAC inlier.
        span_model = np.linalg.norm(src - src.mean(axis=0), axis=1).max()
        span_enu = np.linalg.norm(tgt - tgt.mean(axis=0), axis=1).max()
        depth_enu = float(max_error_m)
        depth_model = depth_enu * span_model / max(span_enu, 1e-9)
        src_fit = np.vstack((src, src + depth_model * np.array(dirs_model)))
        tgt_fit = np.vstack((tgt, tgt + depth_enu * np.array([0.0, 0.0, -1.0])))
        result.nadir_assumed = True
        log.warning("model %d: GPS positions lie on one line; assuming near-nadir photos to fix the roll",
                    model_index)
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = float(max_error_m)
    ransac.random_seed = 0
    found = pycolmap.estimate_sim3d_robust(src_fit, tgt_fit, ransac)
    sim = found["tgt_from_src"] if found else None
    if sim is None or found["num_inliers"] < 3:
        result.reason = (f"no similarity transform fits 3 or more GPS positions within {max_error_m} m; "
                         "model left unreferenced")
        log.warning("model %d: %s", model_index, result.reason)
        return result
    moved = _apply(sim, src_fit)
    inlier_mask = np.linalg.norm(moved - tgt_fit, axis=1) <= max_error_m
    if inlier_mask.sum() >= 3:
        refined = pycolmap.estimate_sim3d(src_fit[inlier_mask], tgt_fit[inlier_mask])
        if refined is not None:
            sim = refined
    rec.transform(sim)
    moved = _apply(sim, src)
    residuals = moved - tgt
    result.georeferenced = True
    result.scale = float(sim.scale)
    result.rotation_xyzw = [float(v) for v in sim.rotation.quat]
    result.translation_m = [float(v) for v in sim.translation]
    result.residuals_enu_m = {n: [float(v) for v in r] for n, r in zip(names, residuals, strict=True)}
    result.inliers = [n for n, r in zip(names, residuals, strict=True) if np.linalg.norm(r) <= max_error_m]
    log.info("model %d georeferenced: %d photos, RMS %.2f m (%d inliers)", model_index, len(names),
             result.rms_m, len(result.inliers))
    return result
