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


def _ground_plane(rec, image) -> tuple[np.ndarray, np.ndarray] | None:
    """(point, unit normal) of the plane through the 3-D points ``image`` observes in ``rec``
    (least squares, refitted without points more than 3 MADs off it), or None with < 10 points."""
    ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
    if len(ids) < 10:
        return None
    xyz = np.array([rec.points3D[i].xyz for i in ids])
    for _ in range(2):
        centre = xyz.mean(axis=0)
        normal = np.linalg.svd(xyz - centre)[2][2]
        off = np.abs((xyz - centre) @ normal)
        xyz = xyz[off <= 3.0 * 1.4826 * np.median(off) + 1e-9]
    return centre, normal if normal[2] > 0 else -normal


def _pose_on_partner_ground(pair_rec, pair_new, pair_partner, main_partner, camera, plane, min_inliers: int):
    """``pair_new``'s cam_from_world in the main model: each point of the two-photo model is
    re-made as the partner's ray (main-model pose) meeting the ground ``plane``, then
    absolute pose (P3P RANSAC + refinement) from ``pair_new``'s observations of them.
    Returns (``pycolmap.Rigid3d``, inliers) or None."""
    import pycolmap

    r_world_from_cam = main_partner.cam_from_world().rotation.matrix().T
    centre = main_partner.projection_center()
    xy_new, xy_partner = [], []
    for point in pair_rec.points3D.values():
        idx = {e.image_id: e.point2D_idx for e in point.track.elements}
        if pair_new.image_id in idx and pair_partner.image_id in idx:
            xy_new.append(pair_new.points2D[idx[pair_new.image_id]].xy)
            xy_partner.append(pair_partner.points2D[idx[pair_partner.image_id]].xy)
    if len(xy_new) < min_inliers:
        return None
    rays = np.hstack((np.asarray(camera.cam_from_img(np.array(xy_partner))), np.ones((len(xy_partner), 1))))
    rays = rays @ r_world_from_cam.T
    along = rays @ plane[1]
    ok = along < -1e-6  # rays going down to the ground
    t = ((plane[0] - centre) @ plane[1]) / np.where(ok, along, -1.0)
    ground = centre + rays * t[:, None]
    found = pycolmap.estimate_and_refine_absolute_pose(np.array(xy_new)[ok], ground[ok], camera)
    if found is None or found["num_inliers"] < min_inliers:
        return None
    return found["cam_from_world"], int(found["num_inliers"])


def _pair_refusal(pair: PairModel, new_p: Photo | None, partner_p: Photo | None, pair_images: dict,
                 main_images: dict, main_georef: ModelGeoref) -> str:
    """Why a two-photo model cannot be placed on its partner's ground ('' when it can)."""
    if new_p is None or partner_p is None or not (new_p.has_gps and partner_p.has_gps):
        return f"{pair.photo}: two-view model needs GPS on both photos"
    if pair.partner not in main_georef.inliers or pair.partner not in main_images:
        return f"{pair.photo}: partner {pair.partner} is not a GPS inlier of model {main_georef.model_index}"
    if set(pair_images) != {pair.photo, pair.partner}:
        return f"{pair.photo}: the two-view model does not pose both photos"
    return ""


def _vertical_limit_m(main_georef: ModelGeoref, max_vertical_m: float,
                      prior_sigma_m: float | None = None) -> tuple[float, str]:
    """The vertical limit and what it is. With GPS priors in the bundle adjustment
    (``prior_sigma_m``, their vertical standard deviation): 3x that sigma, at most
    ``max_vertical_m``. The host's photos were held to their GPS heights there, so their
    residuals measure that pull, not the GPS noise (Seneca: 0.6 m RMS for a GPS the
    adjustment takes as 4 m). Without priors: 3x the vertical RMS of the host model's
    photos against their GPS (this flight's GPS height noise), within [1 m,
    ``max_vertical_m``]; ``max_vertical_m`` with < 3 photos."""
    if prior_sigma_m:
        return min(3.0 * prior_sigma_m, max_vertical_m), "3x the vertical GPS sigma of the bundle adjustment"
    what = f"3x the vertical GPS RMS of model {main_georef.model_index}'s photos"
    host_z = np.array([main_georef.residuals_enu_m[n][2] for n in main_georef.inliers
                       if n in main_georef.residuals_enu_m])
    if len(host_z) < 3:
        return max_vertical_m, "the vertical limit"
    return float(np.clip(3.0 * np.sqrt(np.mean(host_z ** 2)), 1.0, max_vertical_m)), what


def attach_pair(pair_rec, main_rec, main_georef: ModelGeoref, pair: PairModel, photos: list[Photo],
                frame: LocalFrame, model_index: int, *, max_offset_m: float = 5.0, max_vertical_m: float = 12.0,
                min_inliers: int = 30, gps_shift_enu: dict[str, np.ndarray] | None = None,
                prior_sigma_vertical_m: float | None = None) -> ModelGeoref:
    """Place ``pair.photo`` from its two-photo model ``pair_rec`` on the partner's ground.

    The partner's pose and its ground come from the georeferenced ``main_rec``: a plane
    through the main model's points the partner sees. Each point of the two-photo model is
    re-made where the partner's ray meets that plane, and the photo's pose is the absolute
    pose (RANSAC, at least ``min_inliers`` inliers) from its observations of them, so the
    scale and the baseline's direction are metric (a homography's decomposition over flat
    ground leaves the baseline's tilt loose: on Seneca it put IMG_0460 9.8 m off).
    The photo's own GPS is not used to place it and checks it: the partner must be a GPS
    inlier of the main model and the photo's centre within ``max_offset_m`` of its GPS
    horizontally and vertically within 3x the vertical RMS of the main model's photos
    against their own GPS (this flight's GPS height noise; at most ``max_vertical_m``, at
    least 1 m), or, when the main model was adjusted with GPS priors of vertical sigma
    ``prior_sigma_vertical_m``, within 3x that sigma (see :func:`_vertical_limit_m`); the
    GPS moved by ``gps_shift_enu`` (the GPS lag correction) when given.
    ``pair_rec`` is moved in place by the similarity that gives the photo that pose (its
    scale from the baseline) and the partner is deregistered from it, leaving one photo.
    """
    import pycolmap

    by_name = {p.name: p for p in photos}
    result = ModelGeoref(model_index, 1, False)
    result.two_view = {"photo": pair.photo, "partner": pair.partner, "inliers": pair.inliers}
    new_p, partner_p = by_name.get(pair.photo), by_name.get(pair.partner)
    pair_images = {im.name: im for im in pair_rec.images.values() if im.has_pose}
    main_images = {im.name: im for im in main_rec.images.values() if im.has_pose}
    result.reason = _pair_refusal(pair, new_p, partner_p, pair_images, main_images, main_georef)
    if result.reason:
        log.warning("model %d: %s", model_index, result.reason)
        return result
    pair_new, pair_partner, main_partner = pair_images[pair.photo], pair_images[pair.partner], main_images[pair.partner]
    plane = _ground_plane(main_rec, main_partner)
    placed = None if plane is None else _pose_on_partner_ground(
        pair_rec, pair_new, pair_partner, main_partner, main_rec.cameras[main_partner.camera_id], plane, min_inliers)
    if placed is None:
        result.reason = f"{pair.photo}: fewer than {min_inliers} of its points on the ground under {pair.partner}"
        log.warning("model %d: %s", model_index, result.reason)
        return result
    pose, inliers = placed
    shift = gps_shift_enu or {}
    gps_new = _enu(frame, new_p) + shift.get(new_p.name, 0.0)
    gps_partner = _enu(frame, partner_p) + shift.get(partner_p.name, 0.0)
    # world_main_from_pair: the photo's rotation and centre as placed, scale from the baseline.
    r_pair, r_pose = pair_new.cam_from_world().rotation.matrix(), pose.rotation.matrix()
    centre_new = -r_pose.T @ pose.translation
    rotation = r_pose.T @ r_pair
    scale = float(np.linalg.norm(centre_new - main_partner.projection_center())
                  / np.linalg.norm(pair_new.projection_center() - pair_partner.projection_center()))
    sim = pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation),
                         centre_new - scale * rotation @ pair_new.projection_center())
    offset = centre_new - gps_new
    horizontal_m, vertical_m = float(np.linalg.norm(offset[:2])), float(abs(offset[2]))
    max_vertical_m, limit_what = _vertical_limit_m(main_georef, max_vertical_m, prior_sigma_vertical_m)
    result.two_view.update({"baseline_m": float(np.linalg.norm(centre_new - main_partner.projection_center())),
                            "baseline_gps_m": float(np.linalg.norm(gps_new - gps_partner)),
                            "offset_m": float(np.linalg.norm(offset)), "offset_horizontal_m": horizontal_m,
                            "offset_vertical_m": float(offset[2]), "pose_inliers": inliers})
    if horizontal_m > max_offset_m or vertical_m > max_vertical_m:
        result.reason = (f"{pair.photo}: placed from {pair.partner} {horizontal_m:.1f} m horizontally and "
                         f"{vertical_m:.1f} m vertically from its GPS (limits {max_offset_m:g} m, "
                         f"{max_vertical_m:.1f} m: {limit_what}); not placed")
        log.warning("model %d: %s", model_index, result.reason)
        return result
    pair_rec.transform(sim)
    pair_rec.deregister_frame(pair_partner.frame_id)
    result.georeferenced = True
    result.reason = f"registered via two-view model with {pair.partner} ({pair.inliers} inliers, {inliers} on its ground)"
    result.scale = float(sim.scale)
    result.rotation_xyzw = [float(v) for v in sim.rotation.quat]
    result.translation_m = [float(v) for v in sim.translation]
    result.residuals_enu_m = {pair.photo: [float(v) for v in offset]}
    result.inliers = [pair.photo]
    log.info("model %d: %s, %.2f m from GPS", model_index, result.reason, np.linalg.norm(offset))
    return result
