"""Render a drone (multirotor silhouette and/or a textured plate) into a helper camera's view.

The target is a :class:`skyfix.crps.model.DroneModel` (convex parts: body, arms, motors,
rotor disks) at a geodetic position with an attitude; the helper camera is a
:class:`~skyfix.camera.Camera` at a :class:`~skyfix.camera.CameraPose`. Parts are
projected through the exact camera model (distortion included) and filled with
sub-pixel precision on a supersampled canvas around the target only, so a 1920x1080
frame costs little more than its background. Backgrounds: a procedural sky (gradient
plus soft clouds), terrain rendered by :func:`skyfix.datasets.render.render_ground`
(sky above the horizon), or any image the caller provides.

Optional effects in order: partial occlusion, Gaussian blur (optics), linear motion
blur, additive Gaussian noise. :class:`DroneTruth` gives the exact range, bearing and
footprint of every frame.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.crps.model import DroneModel, rasterize_convex_parts
from skyfix.datasets.render import GroundTexture, motion_blur_kernel, render_ground
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.rotation import R_ENU_FROM_NED, r_ned_from_frd

__all__ = ["DroneTruth", "DroneView", "Plate", "TargetPose", "render_drone_view", "render_drones",
           "sky_background",
           "terrain_background"]

#: Grey level of each kind of part relative to ``drone_gray`` (props read lighter).
_PART_SHADE = {"body": 0.9, "arm": 1.0, "motor": 0.85, "rotor": 1.1}


@dataclass(frozen=True)
class TargetPose:
    """Target position (WGS84 degrees, ellipsoidal metres) and attitude (Z-Y-X degrees, NED)."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "lat_deg", float(validate.latitude("TargetPose.lat_deg", self.lat_deg)))
        object.__setattr__(self, "lon_deg", float(validate.longitude("TargetPose.lon_deg", self.lon_deg)))
        for name in ("alt_m", "yaw_deg", "pitch_deg", "roll_deg"):
            object.__setattr__(self, name, validate.finite_scalar(f"TargetPose.{name}", getattr(self, name)))


@dataclass(frozen=True, eq=False)
class Plate:
    """A flat textured rectangle carried by the target (e.g. a fiducial marker).

    ``image`` ``(H, W)`` grey levels in [0, 1] (uint8 is scaled by 1/255); ``width_m`` the
    physical width of the image (height follows the aspect ratio); ``center_body_m`` the
    plate centre in body FRD metres; ``r_body_from_plate`` the rotation taking plate axes
    (x along image columns, y along image rows, z into the plate, so the textured face
    looks along -z) into body FRD. The default plate lies on top of the airframe.
    """

    image: np.ndarray
    width_m: float
    center_body_m: tuple[float, float, float] = (0.0, 0.0, -0.03)
    r_body_from_plate: np.ndarray = field(default_factory=lambda: np.array(
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.ndim != 2 or min(img.shape) < 2:
            raise InputError(f"Plate.image must be a (H, W) grey image, got shape {img.shape}")
        img = img.astype(np.float32) / (255.0 if img.dtype == np.uint8 else 1.0)
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "width_m", validate.positive_scalar("Plate.width_m", self.width_m))
        rot = validate.finite_array("Plate.r_body_from_plate", self.r_body_from_plate)
        if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9):
            raise InputError("Plate.r_body_from_plate must be a 3x3 rotation matrix")
        object.__setattr__(self, "r_body_from_plate", rot)

    def corners_body_m(self) -> np.ndarray:
        """Plate corners ``(4, 3)`` in body FRD: image top-left, top-right, bottom-right, bottom-left."""
        h, w = self.image.shape
        hw, hh = self.width_m / 2.0, self.width_m * h / w / 2.0
        local = np.array([[-hw, -hh, 0.0], [hw, -hh, 0.0], [hw, hh, 0.0], [-hw, hh, 0.0]])
        return local @ self.r_body_from_plate.T + np.asarray(self.center_body_m, float)


@dataclass(frozen=True)
class DroneTruth:
    """Exact ground truth of one rendered frame.

    ``target_enu_m`` target origin in the helper's ENU frame (origin at the helper
    camera), ``range_m`` its distance, ``bearing_unit_enu`` unit vector helper -> target in
    ENU at the helper, ``centroid_uv`` the target origin's raw pixel, ``elevation_deg``
    the angle of the line of sight below the target's horizontal (positive: seen from
    above), ``bbox_px`` (u0, v0, u1, v1) of the drawn target (None if nothing was drawn),
    ``visible_fraction`` drawn area after occlusion / before, ``coverage`` the target's
    per-pixel coverage inside ``bbox_px`` (after occlusion, before blur).
    """

    target_enu_m: np.ndarray
    range_m: float
    bearing_unit_enu: np.ndarray
    centroid_uv: np.ndarray
    elevation_deg: float
    bbox_px: tuple[int, int, int, int] | None
    visible_fraction: float
    coverage: np.ndarray | None = None


@dataclass(frozen=True)
class DroneView:
    """A rendered frame: ``image`` float32 ``(H, W)`` grey levels (about 0..1) and its truth."""

    image: np.ndarray
    truth: DroneTruth


def _smooth_noise(shape: tuple[int, int], cells: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """Low-frequency noise of unit-ish amplitude: a coarse random grid resized with bicubic."""
    coarse = rng.standard_normal((cells[0] + 3, cells[1] + 3)).astype(np.float32)
    big = cv2.resize(coarse, (shape[1] + 3 * shape[1] // cells[1], shape[0] + 3 * shape[0] // cells[0]),
                     interpolation=cv2.INTER_CUBIC)
    return big[shape[0] // cells[0]: shape[0] // cells[0] + shape[0],
               shape[1] // cells[1]: shape[1] // cells[1] + shape[1]]


def sky_background(camera: Camera, helper_pose: CameraPose, rng: np.random.Generator | None = None, *,
                   zenith: float = 0.55, horizon: float = 0.85, clouds: float = 0.06,
                   cloud_cells: int = 8, cloud_map: np.ndarray | None = None) -> np.ndarray:
    """A sky seen by ``camera``: brightness from ``zenith`` to ``horizon`` by ray elevation,
    times soft clouds of relative amplitude ``clouds``; float32 ``(H, W)``.

    Clouds: random per call (``cloud_cells`` across the image, from ``rng``), or fixed in the
    world with ``cloud_map``, a unit-variance ``(90, 360)`` map sampled by ray elevation
    (row, 1 deg, 0 at the horizon) and azimuth (column, 1 deg from north, wrapping), so
    successive frames of a moving camera see the same clouds. The gradient and a mapped
    cloud layer are evaluated on a 1/8 grid and resized (the sky is smooth).
    """
    rng = rng if rng is not None else np.random.default_rng()
    gh, gw = max(2, camera.height // 8), max(2, camera.width // 8)
    u = np.linspace(-0.5, camera.width - 0.5, gw)
    v = np.linspace(-0.5, camera.height - 0.5, gh)
    uu, vv = np.meshgrid(u, v)
    rays = camera.pixel_to_ray(np.stack((uu.ravel(), vv.ravel()), axis=1)) @ helper_pose.r_enu_from_cam().T
    up = np.clip(rays[:, 2], 0.0, 1.0).reshape(gh, gw)
    grid = (horizon + (zenith - horizon) * np.sqrt(up)).astype(np.float32)
    if clouds > 0 and cloud_map is not None:
        el = np.degrees(np.arcsin(up)).astype(np.float32)
        az = (np.degrees(np.arctan2(rays[:, 0], rays[:, 1])).reshape(gh, gw) % 360.0).astype(np.float32)
        layer = cv2.remap(np.asarray(cloud_map, np.float32), az, el, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        grid = grid * (1.0 + clouds * layer)
    sky = cv2.resize(grid, (camera.width, camera.height), interpolation=cv2.INTER_LINEAR)
    if clouds > 0 and cloud_map is None:
        cells = (max(1, cloud_cells * camera.height // camera.width), cloud_cells)
        sky = sky * (1.0 + clouds * _smooth_noise(sky.shape, cells, rng))
    return sky


def terrain_background(texture: GroundTexture, camera: Camera, helper_pose: CameraPose,
                       rng: np.random.Generator | None = None, **sky_kwargs) -> np.ndarray:
    """Terrain from :func:`render_ground` below the horizon, :func:`sky_background` above; float32 (H, W).

    ``texture.image`` should be grey levels in [0, 1].
    """
    ground = render_ground(texture, camera, helper_pose)
    img = ground.image if ground.image.ndim == 2 else ground.image.mean(axis=2)
    if ground.mask.all():
        return img.astype(np.float32)
    sky = sky_background(camera, helper_pose, rng, **sky_kwargs)
    return np.where(ground.mask, img, sky).astype(np.float32)


def _occlusion_mask(cover: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Half-plane (random direction) hiding ``fraction`` of the covered canvas samples."""
    vv, uu = np.nonzero(cover > 0)
    angle = rng.uniform(0.0, 2.0 * math.pi)
    n = np.array([math.cos(angle), math.sin(angle)])
    proj = uu * n[0] + vv * n[1]
    thr = np.quantile(proj, 1.0 - fraction)
    gv, gu = np.mgrid[0:cover.shape[0], 0:cover.shape[1]]
    return (gu * n[0] + gv * n[1]) > thr


def _composite(image: np.ndarray, camera: Camera, shapes: list[np.ndarray], values: list[float],
               plate: Plate | None, plate_cam: np.ndarray | None, all_cam: np.ndarray, supersample: int,
               frac: float, occluder_gray: float | None, rng: np.random.Generator,
               ) -> tuple[tuple[int, int, int, int] | None, float, np.ndarray | None]:
    """Fill the target's parts (camera-frame vertices) on a supersampled canvas and blend it into
    ``image`` in place; returns (bbox, visible fraction, per-pixel coverage)."""
    all_uv = camera.project(all_cam)
    u0 = max(int(math.floor(all_uv[:, 0].min())) - 2, 0)
    v0 = max(int(math.floor(all_uv[:, 1].min())) - 2, 0)
    u1 = min(int(math.ceil(all_uv[:, 0].max())) + 3, camera.width)
    v1 = min(int(math.ceil(all_uv[:, 1].max())) + 3, camera.height)
    bbox = None
    visible = 0.0
    coverage_out = None
    if u1 > u0 and v1 > v0:
        s = supersample
        shape = ((v1 - v0) * s, (u1 - u0) * s)

        def to_canvas(uv: np.ndarray) -> np.ndarray:
            return (uv - np.array([u0, v0]) + 0.5) * s - 0.5

        cover = np.zeros(shape, np.float32)
        value = np.zeros(shape, np.float32)
        if shapes:
            cover, value = rasterize_convex_parts([to_canvas(camera.project(p)) for p in shapes], values,
                                                  shape, depth=[float(p[:, 2].mean()) for p in shapes])
        if plate_cam is not None:
            normal = np.cross(plate_cam[1] - plate_cam[0], plate_cam[3] - plate_cam[0])
            if float(normal @ plate_cam.mean(axis=0)) > 0.0:  # textured face towards the camera
                h, w = plate.image.shape
                src = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]], np.float32)
                dst = to_canvas(camera.project(plate_cam)).astype(np.float32)
                hom = cv2.getPerspectiveTransform(src, dst)
                tex = cv2.warpPerspective(plate.image, hom, (shape[1], shape[0]), flags=cv2.INTER_LINEAR,
                                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
                pmask = cv2.warpPerspective(np.ones_like(plate.image), hom, (shape[1], shape[0]),
                                            flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                                            borderValue=0.0)
                value = np.where(pmask > 0, tex, value)
                cover = np.maximum(cover, pmask)
        drawn = float(cover.sum())
        if drawn > 0:
            occluder = None
            if frac > 0:
                occluder = _occlusion_mask(cover, frac, rng)
                cover = np.where(occluder, 0.0, cover).astype(np.float32)
            alpha = cover.reshape(v1 - v0, s, u1 - u0, s).mean(axis=(1, 3))
            premult = (cover * value).reshape(v1 - v0, s, u1 - u0, s).mean(axis=(1, 3))
            roi = image[v0:v1, u0:u1]
            out = roi * (1.0 - alpha) + premult
            if occluder is not None and occluder_gray is not None:
                occ = occluder.reshape(v1 - v0, s, u1 - u0, s).mean(axis=(1, 3))
                out = out * (1.0 - occ) + float(occluder_gray) * occ
            image[v0:v1, u0:u1] = out
            visible = float(cover.sum()) / drawn
            bbox = (u0, v0, u1, v1)
            coverage_out = alpha.astype(np.float32)
    return bbox, visible, coverage_out


def _draw_target(image: np.ndarray, camera: Camera, helper_pose: CameraPose, frame: LocalFrame,
                 target: TargetPose, model: DroneModel | None, plate: Plate | None, drone_gray: float,
                 supersample: int, frac: float, occluder_gray: float | None,
                 rng: np.random.Generator) -> DroneTruth:
    """Composite one target into ``image`` (float32 ``(H, W)``, in place) and return its truth.

    ``frame`` is any local frame near the helper; the truth's vectors are in the ENU axes of
    ``frame``. Raises :class:`GeometryError` when the target is at or behind the camera.
    """
    cam_enu, r_frame_from_cam = helper_pose.in_frame(frame)
    target_enu = np.array([float(c) for c in frame.to_enu(target.lat_deg, target.lon_deg, target.alt_m)])
    r_frame_from_body = (frame.enu_rotation_at(target.lat_deg, target.lon_deg) @ R_ENU_FROM_NED
                         @ r_ned_from_frd(target.yaw_deg, target.pitch_deg, target.roll_deg))
    offset = target_enu - cam_enu
    range_m = float(np.linalg.norm(offset))
    if range_m <= 0.0:
        raise GeometryError("target and helper camera are at the same position")
    bearing = offset / range_m
    if float((offset @ r_frame_from_cam)[2]) <= 0.0:
        raise GeometryError(f"target is behind the helper camera (range {range_m:.2f} m)")
    centroid_uv = camera.project((offset @ r_frame_from_cam)[None, :])[0]
    # Elevation of the line of sight below the target's own horizontal plane.
    up_at_target = frame.enu_rotation_at(target.lat_deg, target.lon_deg)[:, 2]
    elevation_deg = math.degrees(math.asin(float(np.clip(-bearing @ up_at_target, -1.0, 1.0))))

    shapes: list[np.ndarray] = []
    values: list[float] = []
    if model is not None:
        for name, pts in model.parts():
            shapes.append(((pts @ r_frame_from_body.T) + target_enu - cam_enu) @ r_frame_from_cam)
            values.append(drone_gray * _PART_SHADE[name])
    plate_cam = None
    if plate is not None:
        plate_cam = ((plate.corners_body_m() @ r_frame_from_body.T) + target_enu - cam_enu) @ r_frame_from_cam
    all_cam = np.concatenate(shapes + ([plate_cam] if plate_cam is not None else []))
    if np.any(all_cam[:, 2] <= 1e-3):
        raise GeometryError("part of the target is at or behind the helper camera plane")
    bbox, visible, coverage_out = _composite(image, camera, shapes, values, plate, plate_cam, all_cam,
                                             supersample, frac, occluder_gray, rng)
    return DroneTruth(target_enu_m=offset.copy(), range_m=range_m, bearing_unit_enu=bearing,
                      centroid_uv=centroid_uv, elevation_deg=elevation_deg, bbox_px=bbox,
                      visible_fraction=visible, coverage=coverage_out)


def render_drone_view(camera: Camera, helper_pose: CameraPose, target: TargetPose,
                      model: DroneModel | None = None, *, background: str | GroundTexture | np.ndarray = "sky",
                      plate: Plate | None = None, drone_gray: float = 0.15, supersample: int = 8,
                      blur_sigma_px: float = 0.0, motion_blur_px: float = 0.0,
                      motion_blur_angle_deg: float = 0.0, noise_sigma: float = 0.0,
                      occlusion_fraction: float = 0.0, occluder_gray: float | None = None,
                      rng: np.random.Generator | None = None) -> DroneView:
    """Render ``model`` (and/or ``plate``) at ``target`` as seen by ``camera`` at ``helper_pose``.

    ``model=None`` draws only the plate. ``background``: ``"sky"``, a
    :class:`GroundTexture` (terrain, sky above the horizon) or a float ``(H, W)`` image.
    ``occlusion_fraction`` of the target is hidden behind a straight-edged occluder of
    grey ``occluder_gray`` (None: the background shows through, as if the target were
    cut off). Raises :class:`GeometryError` when the target is at or behind the camera.

    Example:
        A 0.5 m quad 20 m away, 10 deg above the helper whose camera (160 px, 30 deg: focal
        299 px) looks at it: drawn at the image centre, 12 px wide, darker than the sky:

        >>> from skyfix.crps import DroneModel
        >>> from skyfix.geo import destination
        >>> lat, lon = destination(47.0, 8.0, 0.0, 19.696)  # 20 m * cos(10 deg) north, 3.47 m up
        >>> view = render_drone_view(Camera.from_fov(160, 120, 30.0), CameraPose(47.0, 8.0, 400.0, gimbal_pitch_deg=10.0),
        ...                          TargetPose(float(lat), float(lon), 403.473), DroneModel.quad(0.5),
        ...                          rng=np.random.default_rng(0))
        >>> round(view.truth.range_m, 2), view.truth.centroid_uv.round(1).tolist(), view.truth.bbox_px
        (20.0, [79.5, 59.5], (74, 56, 86, 64))
        >>> bool(view.image[56:64, 74:86].min() < 0.5 < np.median(view.image))
        True
    """
    if model is None and plate is None:
        raise InputError("render_drone_view needs a model, a plate or both")
    supersample = validate.integer_in("supersample", supersample, 1)
    frac = validate.finite_scalar("occlusion_fraction", occlusion_fraction)
    if not 0.0 <= frac < 1.0:
        raise InputError(f"occlusion_fraction must be in [0, 1), got {frac}")
    rng = rng if rng is not None else np.random.default_rng()

    if isinstance(background, str):
        if background != "sky":
            raise InputError(f"background must be 'sky', a GroundTexture or an (H, W) image, got {background!r}")
        image = sky_background(camera, helper_pose, rng)
    elif isinstance(background, GroundTexture):
        image = terrain_background(background, camera, helper_pose, rng)
    else:
        image = validate.finite_array("background", background).astype(np.float32)
        if image.shape != (camera.height, camera.width):
            raise InputError(f"background image must be ({camera.height}, {camera.width}), got {image.shape}")
        image = image.copy()

    frame = LocalFrame(helper_pose.lat_deg, helper_pose.lon_deg, helper_pose.alt_m)
    truth = _draw_target(image, camera, helper_pose, frame, target, model, plate, drone_gray, supersample,
                         frac, occluder_gray, rng)
    if blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), validate.positive_scalar("blur_sigma_px", blur_sigma_px))
    if motion_blur_px > 0:
        image = cv2.filter2D(image, -1, motion_blur_kernel(validate.positive_scalar("motion_blur_px", motion_blur_px),
                                                       validate.finite_scalar("motion_blur_angle_deg",
                                                                              motion_blur_angle_deg)))
    if noise_sigma > 0:
        sigma = validate.positive_scalar("noise_sigma", noise_sigma)
        image = image + rng.standard_normal(image.shape, dtype=np.float32) * np.float32(sigma)
    return DroneView(image=image.astype(np.float32, copy=False), truth=truth)


@functools.lru_cache(maxsize=8)
def _normalised_extent(camera: Camera) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of x/z, y/z over the image border, camera frame (lens included)."""
    u = np.linspace(-0.5, camera.width - 0.5, 33)
    v = np.linspace(-0.5, camera.height - 0.5, 33)
    border = np.concatenate([np.column_stack((u, np.full_like(u, v[0]))), np.column_stack((u, np.full_like(u, v[-1]))),
                             np.column_stack((np.full_like(v, u[0]), v)), np.column_stack((np.full_like(v, u[-1]), v))])
    rays = camera.pixel_to_ray(border)
    x, y = rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2]
    return float(x.min()), float(x.max()), float(y.min()), float(y.max())


def render_drones(image: np.ndarray, camera: Camera, helper_pose: CameraPose, targets: Sequence[TargetPose],
                  model: DroneModel, *, drone_gray: float = 0.15, supersample: int = 4,
                  rng: np.random.Generator | None = None) -> list[DroneTruth | None]:
    """Composite every drone of ``targets`` the camera sees into ``image`` (float32 ``(H, W)``, in place).

    Drawn far to near, so a nearer drone hides a farther one. Returns one truth per target
    (vectors in ENU at the helper camera), None for a target behind the camera, outside
    the field of view or within its own radius of the lens.
    """
    supersample = validate.integer_in("supersample", supersample, 1)
    if image.shape != (camera.height, camera.width):
        raise InputError(f"image must be ({camera.height}, {camera.width}), got {image.shape}")
    rng = rng if rng is not None else np.random.default_rng()
    out: list[DroneTruth | None] = [None] * len(targets)
    if not targets:
        return out
    frame = LocalFrame(helper_pose.lat_deg, helper_pose.lon_deg, helper_pose.alt_m)
    cam_enu, r_frame_from_cam = helper_pose.in_frame(frame)
    lat = np.array([t.lat_deg for t in targets])
    lon = np.array([t.lon_deg for t in targets])
    alt = np.array([t.alt_m for t in targets])
    enu = np.stack([np.asarray(c, float).reshape(-1) for c in frame.to_enu(lat, lon, alt)], axis=1)
    in_cam = (enu - cam_enu) @ r_frame_from_cam
    radius = 0.6 * model.span_m  # rotor tips plus tilt
    x0, x1, y0, y1 = _normalised_extent(camera)
    z = np.maximum(in_cam[:, 2], 1e-9)
    margin = radius / z
    seen = ((in_cam[:, 2] > radius + 1e-3) & (in_cam[:, 0] / z >= x0 - margin) & (in_cam[:, 0] / z <= x1 + margin)
            & (in_cam[:, 1] / z >= y0 - margin) & (in_cam[:, 1] / z <= y1 + margin))
    for i in sorted(np.flatnonzero(seen), key=lambda k: -float(np.linalg.norm(in_cam[k]))):
        out[i] = _draw_target(image, camera, helper_pose, frame, targets[i], model, None, drone_gray,
                              supersample, 0.0, None, rng)
    return out
