"""From a detection to a range/bearing observation, and from several helpers to a fix.

``observe`` works in the helper's local ENU axes: the bearing is the detection's pixel
ray rotated by the helper camera's attitude; the range comes from the apparent size
(silhouette moments through the drone's shape table, a marker's PnP scale, or a box
width); the covariance is ``sigma_r^2 b b^T`` along the bearing plus
``range^2 (angular covariance)`` across it, where the angular covariance holds the
centroid noise and the helper's attitude uncertainty.

``locate`` fuses observations of one target by several helpers: each gives the
target at ``helper position + offset`` with covariance ``observation + helper
position``; the weighted least-squares solution in a common local frame is the
information-weighted mean, converted back to geodetic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.crps.detection import Detection
from skyfix.crps.model import DroneModel, shape_table
from skyfix.crps.ranging import range_from_size
from skyfix.errors import EstimationError, GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.types import GeoFix, RelativeObservation

# 1-sigma error (deg) of a helper camera's reported pointing, on both axes across the line of sight. The heading is
# the larger part: a drone's compass-referenced heading (plus the gimbal's yaw encoder), which careful magnetometer
# calibration brings to 1-2 deg rms (Tomasch & Winer, Tlera Corp. 2018, "Limits of absolute heading accuracy using
# inexpensive MEMS sensors": 2 deg routinely, 1 deg in many cases, ~4 deg with a plain offset calibration); 1 uT of
# uncompensated field from the motors' currents against a 30 uT horizontal field is already ~1.9 deg.
POINTING_SIGMA_DEG = 2.0

__all__ = ["angular_jacobian", "locate", "observe", "shape_consistent"]


def angular_jacobian(camera: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local pixel -> angle map at raw pixel ``uv`` (2,).

    Returns (ray ``(3,)`` unit, camera frame; tangent basis ``(3, 2)`` perpendicular to the
    ray, camera frame; Jacobian ``(2, 2)`` radians per pixel from (du, dv) to angles along
    that basis). Central differences of +-0.5 px through the full camera model.
    """
    uv = validate.finite_array("uv", uv).reshape(2)
    probes = uv + np.array([[0.0, 0.0], [0.5, 0.0], [-0.5, 0.0], [0.0, 0.5], [0.0, -0.5]])
    rays = camera.pixel_to_ray(probes)
    ray = rays[0]
    e1 = rays[1] - rays[2]
    e1 = e1 - (e1 @ ray) * ray
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ray, e1)
    basis = np.column_stack((e1, e2))
    jac = np.column_stack(((rays[1] - rays[2]) @ basis, (rays[3] - rays[4]) @ basis))
    return ray, basis, jac


def _silhouette_size(detection: Detection, jac: np.ndarray, elevation_deg: float,
                     model: DroneModel) -> tuple[float, float]:
    """(major-axis RMS in radians / shape ratio = angular span, its relative 1-sigma)."""
    ang = jac @ detection.moments_px2 @ jac.T
    rms_rad = math.sqrt(max(float(np.linalg.eigvalsh(ang)[-1]), 0.0))
    k_mean, k_std = (float(x) for x in shape_table(model.scaled_to(1.0)).ratio(abs(elevation_deg)))
    return rms_rad / k_mean, math.hypot(detection.moments_sigma_rel, k_std / k_mean)


def _elevation_deg(camera: Camera, helper_pose: CameraPose, uv: np.ndarray) -> float:
    bearing = helper_pose.r_enu_from_cam() @ camera.pixel_to_ray(uv)[0]
    return math.degrees(math.asin(float(np.clip(-bearing[2] / np.linalg.norm(bearing), -1.0, 1.0))))


def shape_consistent(camera: Camera, helper_pose: CameraPose, detection: Detection,
                     model: DroneModel | None = None, *, max_z: float = 3.5) -> bool:
    """Whether a silhouette's minor/major axis ratio fits a level ``model`` seen along its ray.

    A drone seen from elevation e looks about sin(e) as tall as wide (plus its
    thickness); blobs of another aspect are clutter. The tolerance combines the model's
    spread over yaw and tilt, the measurement noise and a 0.05 floor. Non-silhouette
    detections always pass.
    """
    if detection.kind != "silhouette":
        return True
    elev = _elevation_deg(camera, helper_pose, detection.centroid_uv)
    table = shape_table((model or DroneModel.quad()).scaled_to(1.0))
    mean, std = (float(x) for x in table.aspect(abs(elev)))
    _, _, jac = angular_jacobian(camera, detection.centroid_uv)
    ev = np.maximum(np.linalg.eigvalsh(jac @ detection.moments_px2 @ jac.T), 0.0)
    aspect = math.sqrt(ev[0] / ev[1]) if ev[1] > 0 else 0.0
    sigma = math.sqrt(std ** 2 + (2.0 * detection.moments_sigma_rel) ** 2 + 0.05 ** 2)
    return abs(aspect - mean) <= max_z * sigma


def observe(camera: Camera, helper_pose: CameraPose, detection: Detection, target_size_m: float, *,
            model: DroneModel | None = None, observer_id: str = "", target_id: str | None = None,
            time_s: float | None = None, attitude_sigma_deg: float = POINTING_SIGMA_DEG,
            observer_cov_enu_m2: np.ndarray | None = None) -> RelativeObservation:
    """Range, bearing and covariance of ``detection`` seen by ``camera`` at ``helper_pose``.

    ``target_size_m``: the span (rotor tip to tip) for silhouettes and boxes, the marker
    side for markers. ``model`` gives the airframe proportions for silhouettes (default a
    quad). ``attitude_sigma_deg`` is the helper camera's 1-sigma pointing error
    (attitude plus gimbal), applied on both axes across the line of sight.
    ``observer_cov_enu_m2`` (3, 3) the helper's own position covariance, kept on the
    observation for :func:`locate`. ``time_s`` defaults to the detection's time and
    ``target_id`` to ``"marker:<id>"`` for markers.

    Example:
        A 0.5 m marker 27.7 px wide at the centre of a 640 px, 60-degree camera (focal
        554 px) that looks east is 10 m east; 0.28 px of size noise is 1 % of the range:

        >>> from skyfix.camera import Camera, CameraPose
        >>> cam = Camera.from_fov(640, 480, 60.0)
        >>> det = Detection(np.array([319.5, 239.5]), np.eye(2) * 0.01, (306, 226, 333, 253), 1.0,
        ...                 kind="marker", size_px=27.71, size_sigma_px=0.28, marker_id=3)
        >>> obs = observe(cam, CameraPose(47.0, 8.0, 400.0, yaw_deg=90.0, gimbal_pitch_deg=0.0), det, 0.5)
        >>> round(obs.range_m, 2), obs.bearing_unit_enu.round(3).tolist(), obs.target_id
        (10.0, [1.0, 0.0, 0.0], 'marker:3')
        >>> round(float(np.sqrt(obs.cov_enu_m2[0, 0])), 2)  # range 1-sigma, m
        0.1
    """
    if not isinstance(camera, Camera):
        raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
    if not isinstance(helper_pose, CameraPose):
        raise InputError(f"helper_pose must be a skyfix.camera.CameraPose, got {type(helper_pose).__name__}")
    if not isinstance(detection, Detection):
        raise InputError(f"detection must be a skyfix.crps.Detection, got {type(detection).__name__}")
    size_m = validate.positive_scalar("target_size_m", target_size_m)
    att_sigma = math.radians(validate.finite_scalar("attitude_sigma_deg", attitude_sigma_deg))
    if att_sigma < 0:
        raise InputError(f"attitude_sigma_deg must be >= 0, got {attitude_sigma_deg}")
    if not camera.in_image(detection.centroid_uv)[0]:
        raise GeometryError(f"detection centroid {detection.centroid_uv.tolist()} is outside the "
                            f"{camera.width}x{camera.height} image")
    ray, basis, jac = angular_jacobian(camera, detection.centroid_uv)
    r_enu_from_cam = helper_pose.r_enu_from_cam()
    bearing = r_enu_from_cam @ ray
    bearing /= np.linalg.norm(bearing)
    elevation_deg = math.degrees(math.asin(float(np.clip(-bearing[2], -1.0, 1.0))))
    focal = math.sqrt(camera.fx * camera.fy)

    if detection.kind == "silhouette":
        span_rad, rel = _silhouette_size(detection, jac, elevation_deg, model or DroneModel.quad(size_m))
        size_px, size_sigma = focal * span_rad, focal * span_rad * rel
    elif detection.kind in ("marker", "model"):
        size_px = detection.size_px
        size_sigma = math.hypot(detection.size_sigma_px, detection.size_model_sigma_rel * size_px)
    else:  # a raw box width: pixels along u at the centroid, turned into on-axis pixels
        px_to_rad = float(np.linalg.norm(jac[:, 0]))
        size_px = detection.size_px * px_to_rad * focal
        size_sigma = detection.size_sigma_px * px_to_rad * focal
    range_m, range_sigma = (float(x) for x in range_from_size(size_px, size_m, focal, size_sigma))

    ang_cov = jac @ detection.centroid_cov_px2 @ jac.T + np.eye(2) * att_sigma ** 2
    across = r_enu_from_cam @ basis
    cov = range_sigma ** 2 * np.outer(bearing, bearing) + range_m ** 2 * (across @ ang_cov @ across.T)
    cov = 0.5 * (cov + cov.T)
    if target_id is None:
        target_id = f"marker:{detection.marker_id}" if detection.marker_id is not None else ""
    return RelativeObservation(
        observer_id=str(observer_id), target_id=str(target_id),
        time_s=detection.time_s if time_s is None else time_s,
        bearing_unit_enu=bearing, range_m=range_m, cov_enu_m2=cov,
        observer_lat_deg=helper_pose.lat_deg, observer_lon_deg=helper_pose.lon_deg, observer_alt_m=helper_pose.alt_m,
        observer_cov_enu_m2=observer_cov_enu_m2)


def locate(observations: Sequence[RelativeObservation], frame: LocalFrame | None = None) -> GeoFix:
    """Fuse observations of one target by one or more helpers into a geodetic fix.

    Every observation must carry its observer's position; its ``observer_cov_enu_m2``
    (zero if absent) is added to the observation covariance. Weighted least squares in
    ``frame`` (default: ENU at the first observer); the fix covariance is returned in ENU
    axes at the fix. Time is the mean observation time; ``source_id`` is
    ``"crps:<target_id>"``. Raises :class:`EstimationError` if the covariances are singular.

    Example:
        Two helpers see the same marker 10 m away, one from the west and one from the
        south: each axis is measured by one helper's range (1-sigma 0.10 m) and the other's
        bearing (the default 2 deg of pointing error is 0.35 m at 10 m), together 0.097 m:

        >>> from skyfix.camera import Camera, CameraPose
        >>> from skyfix.geo import destination
        >>> cam = Camera.from_fov(640, 480, 60.0)
        >>> det = Detection(np.array([319.5, 239.5]), np.eye(2) * 0.01, (306, 226, 333, 253), 1.0,
        ...                 kind="marker", size_px=27.71, size_sigma_px=0.28, marker_id=3)
        >>> lat, lon = destination(47.0, 8.0, 90.0, 10.0)  # the marker, 10 m east of the first helper
        >>> lat2, lon2 = destination(float(lat), float(lon), 180.0, 10.0)
        >>> west = observe(cam, CameraPose(47.0, 8.0, 400.0, yaw_deg=90.0, gimbal_pitch_deg=0.0), det, 0.5)
        >>> south = observe(cam, CameraPose(float(lat2), float(lon2), 400.0, yaw_deg=0.0, gimbal_pitch_deg=0.0),
        ...                 det, 0.5)
        >>> fix = locate([west, south])
        >>> enu_m = LocalFrame(float(lat), float(lon), 400.0).to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)
        >>> [round(float(x), 2) + 0.0 for x in enu_m], fix.source_id
        ([0.0, 0.0, 0.0], 'crps:marker:3')
        >>> round(fix.sigma_horizontal_m, 3)
        0.097
    """
    obs = list(observations)
    if not obs:
        raise InputError("locate needs at least one RelativeObservation, got none")
    for i, o in enumerate(obs):
        if not isinstance(o, RelativeObservation):
            raise InputError(f"observations[{i}] must be a RelativeObservation, got {type(o).__name__}")
        if not o.has_observer_position:
            raise InputError(f"observations[{i}] (observer {o.observer_id!r}) has no observer position")
    targets = {o.target_id for o in obs}
    if len(targets) > 1:
        raise InputError(f"locate fuses observations of one target; got target ids {sorted(targets)}")
    if frame is None:
        frame = LocalFrame(obs[0].observer_lat_deg, obs[0].observer_lon_deg, obs[0].observer_alt_m)
    info = np.zeros((3, 3))
    vec = np.zeros(3)
    for o in obs:
        rot = frame.enu_rotation_at(o.observer_lat_deg, o.observer_lon_deg)
        origin = np.array([float(c) for c in frame.to_enu(o.observer_lat_deg, o.observer_lon_deg,
                                                           o.observer_alt_m)])
        cov_local = o.cov_enu_m2 + (o.observer_cov_enu_m2 if o.observer_cov_enu_m2 is not None else 0.0)
        cov = rot @ cov_local @ rot.T
        try:
            w = np.linalg.inv(cov)
        except np.linalg.LinAlgError:
            raise EstimationError(f"observation by {o.observer_id!r} has a singular covariance") from None
        info += w
        vec += w @ (origin + rot @ o.offset_enu_m)
    try:
        cov_fix = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        raise EstimationError("the observations do not constrain the target position") from None
    pos = cov_fix @ vec
    lat, lon, alt = (float(c) for c in frame.to_geodetic(pos[0], pos[1], pos[2]))
    rot_fix = frame.enu_rotation_at(lat, lon)
    cov_at_fix = rot_fix.T @ cov_fix @ rot_fix
    cov_at_fix = 0.5 * (cov_at_fix + cov_at_fix.T)
    return GeoFix(lat, lon, alt, cov_at_fix, time_s=float(np.mean([o.time_s for o in obs])),
                  source_id=f"crps:{obs[0].target_id}")
