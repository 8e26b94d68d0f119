"""Camera intrinsics, camera pose on a vehicle, and ray casting onto the ground.

Pixel coordinates follow OpenCV: origin at the centre of the top-left pixel, u to the
right, v down. The camera optical frame is OpenCV's (x right, y down, z forward).
Vehicle attitude is aerospace Z-Y-X relative to local NED; see :mod:`skyfix.rotation`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from skyfix import validate
from skyfix.distortion import Barrel, BrownConrady, Distortion, Fisheye
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.rotation import R_ENU_FROM_NED, R_FRD_FROM_CAM, r_ned_from_frd, rot_x, rot_y, rot_z
from skyfix.units import PixelArray, Pixels

__all__ = ["Barrel", "BrownConrady", "Camera", "CameraPose", "Distortion", "Fisheye",
           "ground_intersection", "world_to_pixel"]


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with an optional lens distortion model.

    ``fx, fy`` are focal lengths in pixels, ``(cx, cy)`` the principal point in OpenCV
    pixel coordinates. ``distortion`` maps ideal pinhole pixels to raw pixels
    (see :mod:`skyfix.distortion`); ``None`` means an ideal pinhole.

    Example:
        >>> cam = Camera.from_fov(640, 480, 90.0)  # fx = 320 px, centre (319.5, 239.5)
        >>> cam.project([[1.0, 0.0, 2.0]])  # 1 m right, 2 m ahead (optical frame)
        array([[479.5, 239.5]])
        >>> cam.pixel_to_ray([[479.5, 239.5]]).round(4)  # back to a unit ray
        array([[0.4472, 0.    , 0.8944]])
    """

    width: int
    height: int
    fx: Pixels
    fy: Pixels
    cx: Pixels
    cy: Pixels
    distortion: Distortion | None = None

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise InputError(f"Camera.{name} must be a positive integer number of pixels, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("fx", "fy"):
            object.__setattr__(self, name, validate.positive_scalar(f"Camera.{name}", getattr(self, name)))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, validate.finite_scalar(f"Camera.{name}", getattr(self, name)))
        if self.distortion is not None and not isinstance(self.distortion, Distortion):
            raise InputError(f"Camera.distortion must provide distort()/undistort(), got {self.distortion!r}")

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, vfov_deg: float | None = None,
                 distortion: Distortion | None = None) -> Camera:
        """Camera with the principal point at the image centre and the given field of view.

        ``hfov_deg`` spans the full image width (pixel edges); ``vfov_deg`` defaults to
        square pixels (fy = fx).
        """
        hfov = validate.finite_scalar("hfov_deg", hfov_deg)
        if not 0.0 < hfov < 180.0:
            raise InputError(f"hfov_deg must be in (0, 180) for a pinhole camera, got {hfov}")
        fx = (width / 2.0) / math.tan(math.radians(hfov) / 2.0)
        if vfov_deg is None:
            fy = fx
        else:
            vfov = validate.finite_scalar("vfov_deg", vfov_deg)
            if not 0.0 < vfov < 180.0:
                raise InputError(f"vfov_deg must be in (0, 180), got {vfov}")
            fy = (height / 2.0) / math.tan(math.radians(vfov) / 2.0)
        return cls(width, height, fx, fy, (width - 1) / 2.0, (height - 1) / 2.0, distortion)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the standard name of the intrinsic matrix
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view of the ideal pinhole, degrees."""
        return math.degrees(2.0 * math.atan(self.width / 2.0 / self.fx))

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view of the ideal pinhole, degrees."""
        return math.degrees(2.0 * math.atan(self.height / 2.0 / self.fy))

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (pixel edges stay aligned)."""
        f = validate.positive_scalar("factor", factor)
        return Camera(round(self.width * f), round(self.height * f), self.fx * f, self.fy * f,
                      (self.cx + 0.5) * f - 0.5, (self.cy + 0.5) * f - 0.5, self.distortion)

    def in_image(self, uv: PixelArray) -> np.ndarray:
        """Boolean mask ``(N,)``: pixel inside the image (edges at -0.5 and size - 0.5)."""
        uv = validate.points("uv", uv, 2)
        return ((uv[:, 0] >= -0.5) & (uv[:, 0] <= self.width - 0.5)
                & (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.height - 0.5))

    def pixel_to_ray(self, uv: PixelArray) -> np.ndarray:
        """Raw pixels ``(N, 2)`` -> unit rays ``(N, 3)`` in the camera optical frame."""
        uv = validate.points("uv", uv, 2)
        if self.distortion is not None:
            uv = self.distortion.undistort(uv, self)
        rays = np.empty((uv.shape[0], 3))
        rays[:, 0] = (uv[:, 0] - self.cx) / self.fx
        rays[:, 1] = (uv[:, 1] - self.cy) / self.fy
        rays[:, 2] = 1.0
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def project(self, xyz: np.ndarray) -> PixelArray:
        """Points ``(N, 3)`` in the camera optical frame -> raw pixels ``(N, 2)``.

        Rows with z <= 0 (at or behind the camera) come back as NaN.
        """
        xyz = validate.points("xyz", xyz, 3)
        z = xyz[:, 2]
        front = z > 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack((self.fx * xyz[:, 0] / z + self.cx, self.fy * xyz[:, 1] / z + self.cy), axis=1)
        uv[~front] = np.nan
        if self.distortion is not None and np.any(front):
            uv[front] = self.distortion.distort(uv[front], self)
        return uv


@dataclass(frozen=True)
class CameraPose:
    """Where a camera is and where it looks.

    Position: ``lat_deg``/``lon_deg`` in degrees, ``alt_m`` metres above the WGS84 ellipsoid
    (convert AMSL altitudes with a geoid model first). Vehicle attitude in degrees,
    aerospace Z-Y-X relative to local NED: ``yaw_deg`` 0 = north, clockwise positive;
    ``pitch_deg`` nose-up positive; ``roll_deg`` right-wing-down positive.

    Gimbal (mount) angles in degrees, applied Z-Y-X as yaw, pitch, roll:
    ``gimbal_pitch_deg`` 0 = level forward, -90 = straight down; ``gimbal_yaw_deg`` is
    relative to the vehicle heading (not north). With ``stabilized=True`` the gimbal
    angles are relative to the local horizontal and the vehicle heading, so vehicle
    roll and pitch do not move the camera; with ``stabilized=False`` the camera is
    hard-mounted and the mount angles compose with the full vehicle attitude.

    Example:
        >>> pose = CameraPose(47.0, 8.0, 500.0)  # gimbal straight down by default
        >>> (pose.r_enu_from_cam() @ [0.0, 0.0, 1.0]).round(6) + 0.0  # optical axis, ENU
        array([ 0.,  0., -1.])
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0
    gimbal_pitch_deg: float = -90.0
    gimbal_yaw_deg: float = 0.0
    gimbal_roll_deg: float = 0.0
    stabilized: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "lat_deg", float(validate.latitude("CameraPose.lat_deg", self.lat_deg)))
        object.__setattr__(self, "lon_deg", float(validate.longitude("CameraPose.lon_deg", self.lon_deg)))
        for name in ("alt_m", "roll_deg", "pitch_deg", "yaw_deg", "gimbal_pitch_deg",
                     "gimbal_yaw_deg", "gimbal_roll_deg"):
            object.__setattr__(self, name, validate.finite_scalar(f"CameraPose.{name}", getattr(self, name)))
        if abs(self.pitch_deg) > 90.0 or abs(self.gimbal_pitch_deg) > 180.0:
            raise InputError(f"CameraPose pitch out of range: pitch_deg={self.pitch_deg} "
                             f"(|.| <= 90), gimbal_pitch_deg={self.gimbal_pitch_deg} (|.| <= 180)")

    def r_ned_from_cam(self) -> np.ndarray:
        """Rotation taking camera optical-frame vectors into local NED at the vehicle."""
        mount = rot_z(self.gimbal_yaw_deg) @ rot_y(self.gimbal_pitch_deg) @ rot_x(self.gimbal_roll_deg)
        if self.stabilized:
            reference = rot_z(self.yaw_deg)
        else:
            reference = r_ned_from_frd(self.yaw_deg, self.pitch_deg, self.roll_deg)
        return reference @ mount @ R_FRD_FROM_CAM

    def r_enu_from_cam(self) -> np.ndarray:
        """Rotation taking camera optical-frame vectors into local ENU at the vehicle."""
        return R_ENU_FROM_NED @ self.r_ned_from_cam()

    def in_frame(self, frame: LocalFrame) -> tuple[np.ndarray, np.ndarray]:
        """(camera position ``(3,)`` ENU metres, rotation frame-ENU <- camera) in ``frame``.

        Returns fresh arrays; results are cached per (pose, frame) because one frame's
        processing asks for them several times.
        """
        cam_enu, rotation, _ = _pose_in_frame(self, frame)
        return cam_enu.copy(), rotation.copy()


@functools.lru_cache(maxsize=64)
def _pose_in_frame(pose: CameraPose, frame: LocalFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(camera ENU, frame <- camera rotation, local up at the camera in frame axes), read-only."""
    e, n, u = frame.to_enu(pose.lat_deg, pose.lon_deg, pose.alt_m)
    r_frame_from_enu_here = frame.enu_rotation_at(pose.lat_deg, pose.lon_deg)
    out = (np.array([float(e), float(n), float(u)]), r_frame_from_enu_here @ pose.r_enu_from_cam(),
           r_frame_from_enu_here[:, 2].copy())
    for a in out:
        a.setflags(write=False)
    return out


def ground_intersection(camera: Camera, pose: CameraPose, uv: PixelArray, ground_alt_m: float,
                        frame: LocalFrame, *, max_range_m: float = 100_000.0) -> np.ndarray:
    """Cast raw pixels ``(N, 2)`` onto the surface of constant ellipsoidal height.

    The ground is the surface at ``ground_alt_m`` metres above the WGS84 ellipsoid (not
    AGL, not AMSL); the intersection is exact on the curved earth, solved by Newton
    steps on the ray parameter starting from the local tangent plane. Returns ``(N, 3)``
    ENU metres in ``frame``. Raises :class:`GeometryError` naming the pixels whose
    rays are at or above the horizon, or that miss the surface within ``max_range_m``.

    Example:
        >>> from skyfix.geo import LocalFrame
        >>> cam, frame = Camera.from_fov(640, 480, 90.0), LocalFrame(47.0, 8.0, 400.0)
        >>> pose = CameraPose(47.0, 8.0, 500.0)  # 100 m above the ground, looking down
        >>> ground_intersection(cam, pose, [[479.5, 239.5]], 400.0, frame).round(2) + 0.0  # 45 deg right
        array([[50.,  0.,  0.]])
    """
    uv = validate.points("uv", uv, 2)
    h0 = validate.finite_scalar("ground_alt_m", ground_alt_m)
    rays_cam = camera.pixel_to_ray(uv)
    cam_enu, r_frame_from_cam, up_at_cam = _pose_in_frame(pose, frame)
    if pose.alt_m <= h0:
        raise GeometryError(f"camera altitude {pose.alt_m:.3f} m is not above the ground at {h0:.3f} m "
                            "(both are ellipsoidal heights)")
    d = rays_cam @ r_frame_from_cam.T
    d_up = d @ up_at_cam
    bad = d_up >= -1e-12
    if np.any(bad):
        idx = np.flatnonzero(bad)
        raise GeometryError(f"{idx.size} ray(s) at or above the horizon (first pixel "
                            f"{uv[idx[0]].tolist()}, index {int(idx[0])}); they never reach the ground")
    t = (pose.alt_m - h0) / -d_up
    for _ in range(8):
        pts = cam_enu + t[:, None] * d
        h = frame._heights_unchecked(pts)  # finite by construction: skip re-validation
        err = h - h0
        t = t - err / d_up
        # Newton: after a correction below 1 mm the height error left is second order
        # (~err^2 / earth radius, < 1e-9 m), so no further evaluation is needed.
        if np.max(np.abs(err)) < 1e-3:
            break
    else:
        raise GeometryError("ground intersection did not converge (grazing rays)")
    if np.any((t <= 0) | (t > max_range_m)):
        idx = np.flatnonzero((t <= 0) | (t > max_range_m))
        raise GeometryError(f"{idx.size} ray(s) meet the ground beyond max_range_m={max_range_m} "
                            f"(first pixel {uv[idx[0]].tolist()})")
    return cam_enu + t[:, None] * d


def world_to_pixel(camera: Camera, pose: CameraPose, frame: LocalFrame, enu_m: np.ndarray) -> PixelArray:
    """Project points ``(N, 3)`` given in ``frame``'s ENU metres to raw pixels ``(N, 2)``.

    Points at or behind the camera come back as NaN (see :meth:`Camera.project`).

    Example:
        >>> from skyfix.geo import LocalFrame
        >>> cam, frame = Camera.from_fov(640, 480, 90.0), LocalFrame(47.0, 8.0, 400.0)
        >>> world_to_pixel(cam, CameraPose(47.0, 8.0, 500.0), frame, [[50.0, 0.0, 0.0]]).round(2)
        array([[479.5, 239.5]])
    """
    pts = validate.points("enu_m", enu_m, 3)
    cam_enu, r_frame_from_cam = pose.in_frame(frame)
    return camera.project((pts - cam_enu) @ r_frame_from_cam)
