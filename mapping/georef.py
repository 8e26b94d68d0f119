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
from skyfix.mapping.sfm import PairModel

__all__ = ["ModelGeoref", "attach_pair", "georeference", "survey_frame"]

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
    two_view: dict = field(default_factory=dict)
    gps_lag: dict = field(default_factory=dict)

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
                "nadir_assumed": self.nadir_assumed, "residuals_enu_m": self.residuals_enu_m,
                "two_view": self.two_view, "gps_lag": self.gps_lag}


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
                 max_error_m: float = 10.0, velocities: dict[str, np.ndarray] | None = None) -> ModelGeoref:
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
    if velocities and not result.nadir_assumed:
        tgt, inlier_mask = _remove_lag(result, names, src, tgt, inlier_mask, velocities)
        tgt_fit = tgt
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


def _remove_lag(result: ModelGeoref, names: list[str], src: np.ndarray, tgt: np.ndarray, inliers: np.ndarray,
                velocities: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Tags moved by the estimated GPS lag (when accepted) and the inlier mask; fills ``gps_lag``."""
    from skyfix.mapping.gps_lag import estimate_lag

    has_v = np.array([n in velocities for n in names]) & inliers
    if has_v.sum() < 6:
        return tgt, inliers
    vel = np.array([velocities.get(n, np.zeros(3)) for n in names])
    fit = estimate_lag(src[has_v], tgt[has_v], vel[has_v])
    result.gps_lag = {"lag_s": fit.lag_s, "rms_without_m": fit.rms_without_m, "rms_with_m": fit.rms_with_m,
                      "applied": fit.accepted, "photos": int(has_v.sum())}
    return (tgt + fit.lag_s * vel if fit.accepted else tgt), inliers


def _enu(frame: LocalFrame, photo: Photo) -> np.ndarray:
    return frame.to_enu_points(np.array([[photo.gps_lat_deg, photo.gps_lon_deg, photo.gps_alt_amsl_m]]))[0]


def _median_depth(rec, image) -> float:
    """Median depth (model units) of the 3-D points ``image`` observes in ``rec``; NaN if none."""
    ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
    if not ids:
        return float("nan")
    xyz = np.array([rec.points3D[i].xyz for i in ids])
    m = np.asarray(image.cam_from_world().matrix())
    return float(np.median(xyz @ m[2, :3] + m[2, 3]))


def attach_pair(pair_rec, main_rec, main_georef: ModelGeoref, pair: PairModel, photos: list[Photo],
                frame: LocalFrame, model_index: int, *, max_offset_m: float = 5.0,
                gps_shift_enu: dict[str, np.ndarray] | None = None) -> ModelGeoref:
    """Place ``pair.photo`` with its two-photo model ``pair_rec`` anchored on ``pair.partner``.

    The similarity takes the partner's rotation and centre from the georeferenced
    ``main_rec`` (so the partner's pose agrees with the main model exactly) and its scale
    from the ground: the median depth of the points the partner sees in the main model
    (metres) over that in the two-photo model. The photo's own GPS is not used to place it,
    so it is an independent check: the photo counts as placed only when the partner is a
    GPS inlier of the main model and the photo's centre lies within ``max_offset_m`` of
    its GPS position (moved by ``gps_shift_enu``, the GPS lag correction, when given).
    ``pair_rec`` is transformed in place and the
    partner deregistered from it (it stays in the main model), leaving one posed photo.
    """
    import pycolmap

    by_name = {p.name: p for p in photos}
    result = ModelGeoref(model_index, 1, False)
    result.two_view = {"photo": pair.photo, "partner": pair.partner, "inliers": pair.inliers}
    new_p, partner_p = by_name.get(pair.photo), by_name.get(pair.partner)
    pair_images = {im.name: im for im in pair_rec.images.values() if im.has_pose}
    main_images = {im.name: im for im in main_rec.images.values() if im.has_pose}
    if new_p is None or partner_p is None or not (new_p.has_gps and partner_p.has_gps):
        result.reason = f"{pair.photo}: two-view model needs GPS on both photos"
    elif pair.partner not in main_georef.inliers or pair.partner not in main_images:
        result.reason = f"{pair.photo}: partner {pair.partner} is not a GPS inlier of model {main_georef.model_index}"
    elif set(pair_images) != {pair.photo, pair.partner}:
        result.reason = f"{pair.photo}: the two-view model does not pose both photos"
    if result.reason:
        log.warning("model %d: %s", model_index, result.reason)
        return result
    shift = gps_shift_enu or {}
    gps_new = _enu(frame, new_p) + shift.get(new_p.name, 0.0)
    gps_partner = _enu(frame, partner_p) + shift.get(partner_p.name, 0.0)
    pair_new, pair_partner = pair_images[pair.photo], pair_images[pair.partner]
    depth_main_m = _median_depth(main_rec, main_images[pair.partner])
    depth_pair = _median_depth(pair_rec, pair_partner)
    if not (depth_main_m > 0 and depth_pair > 0):
        result.reason = f"{pair.photo}: no ground depth under {pair.partner} to scale its two-view model"
        log.warning("model %d: %s", model_index, result.reason)
        return result
    # world_main_from_pair: rotation R_main^T R_pair (both cam_from_world), partner centre kept.
    r_main = main_images[pair.partner].cam_from_world().rotation.matrix()
    r_pair = pair_partner.cam_from_world().rotation.matrix()
    rotation = r_main.T @ r_pair
    scale = depth_main_m / depth_pair
    translation = main_images[pair.partner].projection_center() - scale * rotation @ pair_partner.projection_center()
    sim = pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), translation)
    moved = _apply(sim, pair_new.projection_center()[None, :])[0]
    offset = moved - gps_new
    baseline_m = scale * np.linalg.norm(pair_new.projection_center() - pair_partner.projection_center())
    result.two_view.update({"baseline_m": float(baseline_m), "baseline_gps_m": float(np.linalg.norm(gps_new - gps_partner)),
                            "offset_m": float(np.linalg.norm(offset))})
    if np.linalg.norm(offset) > max_offset_m:
        result.reason = (f"{pair.photo}: two-view model with {pair.partner} puts it {np.linalg.norm(offset):.1f} m "
                         f"from its GPS (more than {max_offset_m} m); not placed")
        log.warning("model %d: %s", model_index, result.reason)
        return result
    pair_rec.transform(sim)
    pair_rec.deregister_frame(pair_partner.frame_id)
    result.georeferenced = True
    result.reason = f"registered via two-view model with {pair.partner} ({pair.inliers} inliers)"
    result.scale = float(sim.scale)
    result.rotation_xyzw = [float(v) for v in sim.rotation.quat]
    result.translation_m = [float(v) for v in sim.translation]
    result.residuals_enu_m = {pair.photo: [float(v) for v in offset]}
    result.inliers = [pair.photo]
    log.info("model %d: %s, %.2f m from GPS", model_index, result.reason, np.linalg.norm(offset))
    return result
