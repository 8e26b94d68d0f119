"""Synthetic downward-camera frames of a tag field, with exact ground truth.

The printed field (tile tags or AprilTag/ArUco boards: anything with a ``rasterise``
method) becomes a :class:`~skyfix.datasets.render.GroundTexture` on the plane up = 0 of
a :class:`~skyfix.geo.LocalFrame`; frames are ray-cast by
:func:`~skyfix.datasets.render.render_ground` from a hard-mounted, straight-down camera
on a vehicle at a given position and attitude, then degraded by uneven lighting,
occluders (other drones passing under the camera), motion blur and sensor noise.

Field frame = ENU of ``frame``: x east, y north, z up, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.datasets.render import GroundTexture, render_ground
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.rotation import R_ENU_FROM_NED, euler_zyx_from_r_ned_from_frd

#: Where synthetic fields are laid (any point works; the math is exact on WGS84).
DEFAULT_FRAME = LocalFrame(45.4786, 9.2277, 120.0)


@dataclass(frozen=True)
class SceneEffects:
    """Degradations applied to a rendered frame.

    ``lighting`` 0..1: brightness falls by up to this fraction across the frame (a ramp
    in a random direction plus a radial fall-off); ``occlusion_share`` 0..1: fraction of
    the frame hidden by dark drone silhouettes; ``motion_blur_px`` streak length in
    pixels along ``motion_blur_angle_deg``; ``noise_sigma`` additive Gaussian noise in
    [0, 1] image units; ``blur_sigma_px`` optics blur.
    """

    lighting: float = 0.0
    occlusion_share: float = 0.0
    motion_blur_px: float = 0.0
    motion_blur_angle_deg: float = 0.0
    noise_sigma: float = 0.0
    blur_sigma_px: float = 0.0

    def __post_init__(self) -> None:
        for name in ("lighting", "occlusion_share"):
            v = validate.finite_scalar(name, getattr(self, name))
            if not 0.0 <= v < 1.0:
                raise InputError(f"{name} must be in [0, 1), got {v}")
        for name in ("motion_blur_px", "noise_sigma", "blur_sigma_px"):
            validate.nonnegative_scalar(name, getattr(self, name))


@dataclass(frozen=True)
class TagFrame:
    """One rendered frame: ``image`` uint8 RGB ``(H, W, 3)``; ground truth of the camera
    centre (``x_m``, ``y_m``, ``z_m``) in the field frame and vehicle attitude in degrees
    (yaw 0 = field north, clockwise; aerospace Z-Y-X); ``occluded_share`` achieved."""

    image: np.ndarray
    x_m: float
    y_m: float
    z_m: float
    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    occluded_share: float


def field_texture(printable, metres_per_px: float = 0.0025, frame: LocalFrame = DEFAULT_FRAME,
                  margin_m: float = 0.5) -> GroundTexture:
    """Texture of anything with ``rasterise(metres_per_px, margin_m) -> (image, centre_xy)``."""
    image, centre = printable.rasterise(metres_per_px, margin_m=margin_m)
    return GroundTexture(image, metres_per_px, frame, centre)


def _lighting_gain(camera: Camera, strength: float, rng: np.random.Generator) -> np.ndarray:
    vv, uu = np.mgrid[0:camera.height, 0:camera.width].astype(np.float32)
    a = rng.uniform(0, 2 * math.pi)
    ramp = ((uu - camera.cx) * math.cos(a) + (vv - camera.cy) * math.sin(a)) / math.hypot(camera.cx, camera.cy)
    cu, cv = rng.uniform(0, camera.width), rng.uniform(0, camera.height)
    radial = ((uu - cu) ** 2 + (vv - cv) ** 2) / (camera.width ** 2 + camera.height ** 2)
    shade = 0.5 * (ramp + 1.0) * 0.7 + 0.3 * np.clip(radial * 2.0, 0.0, 1.0)
    shade = (shade - shade.min()) / max(float(np.ptp(shade)), 1e-6)
    return (1.0 - strength * shade).astype(np.float32)


def _occluders(camera: Camera, share: float, rng: np.random.Generator) -> np.ndarray:
    """Coverage ``(H, W)`` float32 in [0, 1] of quadcopter silhouettes covering ~``share``."""
    cover = np.zeros((camera.height, camera.width), np.float32)
    if share <= 0:
        return cover
    for _ in range(200):
        if float((cover > 0.5).mean()) >= share:
            break
        size = rng.uniform(0.12, 0.3) * camera.height
        cx, cy = rng.uniform(0, camera.width), rng.uniform(0, camera.height)
        rot = rng.uniform(0, math.pi / 2)
        arm = int(max(2, size * 0.08))
        for k in range(4):
            ang = rot + k * math.pi / 2 + math.pi / 4
            ex, ey = cx + size * math.cos(ang), cy + size * math.sin(ang)
            cv2.line(cover, (int(cx), int(cy)), (int(ex), int(ey)), 1.0, arm, cv2.LINE_AA)
            cv2.circle(cover, (int(ex), int(ey)), int(size * 0.45), 1.0, -1, cv2.LINE_AA)
        cv2.circle(cover, (int(cx), int(cy)), int(size * 0.3), 1.0, -1, cv2.LINE_AA)
    return cover


def vehicle_pose(frame: LocalFrame, x_m: float, y_m: float, height_m: float, yaw_deg: float,
                 pitch_deg: float = 0.0, roll_deg: float = 0.0) -> CameraPose:
    """A hard-mounted straight-down camera on a vehicle at (x, y, height) in the field frame."""
    lat, lon, alt = frame.to_geodetic(x_m, y_m, height_m)
    return CameraPose(float(lat), float(lon), float(alt), roll_deg, pitch_deg, yaw_deg,
                      gimbal_pitch_deg=-90.0, stabilized=False)


def render_tag_frame(texture: GroundTexture, camera: Camera, x_m: float, y_m: float, height_m: float,
                     yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0,
                     effects: SceneEffects = SceneEffects(), rng: np.random.Generator | None = None,
                     mount_r_frd_from_cam: np.ndarray | None = None) -> TagFrame:
    """Render the texture from a vehicle at (x, y, height) in the field frame with the given
    attitude (degrees), apply ``effects`` and return a uint8 frame with its ground truth."""
    rng = rng if rng is not None else np.random.default_rng()
    pose = vehicle_pose(texture.frame, x_m, y_m, height_m, yaw_deg, pitch_deg, roll_deg)
    out = render_ground(texture, camera, pose, background=1.0, supersample=1,
                        blur_sigma_px=effects.blur_sigma_px, motion_blur_px=effects.motion_blur_px,
                        motion_blur_angle_deg=effects.motion_blur_angle_deg)
    img = out.image
    if effects.lighting > 0:
        img = img * _lighting_gain(camera, effects.lighting, rng)[..., None]
    cover = _occluders(camera, effects.occlusion_share, rng)
    if effects.occlusion_share > 0:
        body = np.array([0.18, 0.18, 0.2], np.float32) * rng.uniform(0.7, 1.3)
        img = img * (1.0 - cover[..., None]) + cover[..., None] * body
    if effects.noise_sigma > 0:
        img = img + rng.normal(0.0, effects.noise_sigma, img.shape).astype(np.float32)
    image = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    cam_enu, r_frame_from_cam = pose.in_frame(texture.frame)
    yaw, pitch, roll = euler_zyx_from_r_ned_from_frd(R_ENU_FROM_NED @ r_frame_from_cam @ _frd_from_cam(pose))
    return TagFrame(image, float(cam_enu[0]), float(cam_enu[1]), float(cam_enu[2]), yaw, pitch, roll,
                    float((cover > 0.5).mean()))


def _frd_from_cam(pose: CameraPose) -> np.ndarray:
    """Camera -> body FRD rotation of the pose's (hard) mount, i.e. R_cam_from_frd inverse."""
    mount = CameraPose(0.0, 0.0, 0.0, gimbal_pitch_deg=pose.gimbal_pitch_deg,
                       gimbal_yaw_deg=pose.gimbal_yaw_deg, gimbal_roll_deg=pose.gimbal_roll_deg,
                       stabilized=False).r_ned_from_cam()
    return mount.T


def random_poses(n: int, bounds_xy_m: tuple[float, float, float, float], *, heights_m=(1.0, 3.0),
                 tilt_deg: float = 15.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """``(n, 6)`` rows of (x_m, y_m, height_m, yaw_deg, pitch_deg, roll_deg), uniform within
    ``bounds_xy_m`` = (x_min, y_min, x_max, y_max), heights and |pitch|, |roll| <= tilt."""
    rng = rng if rng is not None else np.random.default_rng()
    x0, y0, x1, y1 = bounds_xy_m
    return np.stack((rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), rng.uniform(*heights_m, n),
                     rng.uniform(-180, 180, n), rng.uniform(-tilt_deg, tilt_deg, n),
                     rng.uniform(-tilt_deg, tilt_deg, n)), axis=1)
