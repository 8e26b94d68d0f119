"""Lens distortion models, pluggable into :class:`skyfix.camera.Camera`.

Every model maps between *ideal* pixels (what a pinhole camera with the camera's
intrinsics K would see) and *raw* pixels (what the lens actually recorded), both in
OpenCV pixel coordinates (pixel centres at integers, origin at the top-left pixel):

- ``distort(uv_ideal, grid) -> uv_raw``
- ``undistort(uv_raw, grid) -> uv_ideal`` (iterative inverse, converged to 1e-9 px)

All take and return ``(N, 2)`` float arrays. ``grid`` is anything with the pinhole
intrinsics and image size (:class:`Intrinsics`; a :class:`skyfix.camera.Camera` is one),
so this module knows nothing of cameras: the camera applies K, the model bends points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from skyfix import validate
from skyfix.errors import GeometryError
from skyfix.units import PixelArray, Pixels


class Intrinsics(Protocol):
    """Pinhole intrinsics in pixels (OpenCV convention) and the image size in pixels."""

    @property
    def fx(self) -> Pixels: ...
    @property
    def fy(self) -> Pixels: ...
    @property
    def cx(self) -> Pixels: ...
    @property
    def cy(self) -> Pixels: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...


@runtime_checkable
class Distortion(Protocol):
    """What a lens model must provide (see module docstring)."""

    def distort(self, uv_ideal: PixelArray, camera: Intrinsics) -> PixelArray: ...

    def undistort(self, uv_raw: PixelArray, camera: Intrinsics) -> PixelArray: ...


def _to_normalized(uv: np.ndarray, camera: Intrinsics) -> np.ndarray:
    return np.stack(((uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy), axis=1)


def _to_pixels(xy: np.ndarray, camera: Intrinsics) -> np.ndarray:
    return np.stack((xy[:, 0] * camera.fx + camera.cx, xy[:, 1] * camera.fy + camera.cy), axis=1)


def _newton_invert_2d(forward, target: np.ndarray, tol: float = 1e-13, max_iter: int = 30) -> np.ndarray:
    """Solve forward(x) = target for each row with Newton steps and a numeric 2x2 Jacobian."""
    x = target.copy()
    h = 1e-7
    for _ in range(max_iter):
        f = forward(x) - target
        if np.max(np.abs(f), initial=0.0) < tol:
            break
        fx = (forward(x + [h, 0.0]) - forward(x - [h, 0.0])) / (2 * h)
        fy = (forward(x + [0.0, h]) - forward(x - [0.0, h])) / (2 * h)
        det = fx[:, 0] * fy[:, 1] - fy[:, 0] * fx[:, 1]
        det = np.where(np.abs(det) < 1e-15, 1e-15, det)
        dx = (fy[:, 1] * f[:, 0] - fy[:, 0] * f[:, 1]) / det
        dy = (-fx[:, 1] * f[:, 0] + fx[:, 0] * f[:, 1]) / det
        x = x - np.stack((dx, dy), axis=1)
    residual = np.abs(forward(x) - target).max(axis=1) if len(x) else np.zeros(0)
    bad = ~(residual < 1e-9)
    if np.any(bad):
        raise GeometryError(f"{int(bad.sum())} point(s) lie outside the invertible domain of the "
                            f"distortion model (first normalised point {target[np.argmax(bad)].tolist()}); "
                            "the coefficients fold the image there")
    return x


@dataclass(frozen=True)
class BrownConrady:
    """OpenCV's radial-tangential model (k1, k2, p1, p2, k3) on normalised coordinates.

    Example:
        >>> from skyfix.camera import Camera
        >>> cam = Camera.from_fov(640, 480, 90.0)
        >>> lens = BrownConrady(k1=-0.2, k2=0.05)
        >>> raw = lens.distort(np.array([[600.0, 400.0]]), cam)  # barrel: pulled inwards
        >>> raw.round(2), lens.undistort(raw, cam).round(6)
        (array([[557.37, 375.61]]), array([[600., 400.]]))
    """

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def __post_init__(self) -> None:
        for name in ("k1", "k2", "p1", "p2", "k3"):
            object.__setattr__(self, name, validate.finite_scalar(name, getattr(self, name)))

    @property
    def opencv_coefficients(self) -> np.ndarray:
        """Coefficients in OpenCV's order ``(k1, k2, p1, p2, k3)``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    def _forward(self, xy: np.ndarray) -> np.ndarray:
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack((xd, yd), axis=1)

    def distort(self, uv_ideal: PixelArray, camera: Intrinsics) -> PixelArray:
        return _to_pixels(self._forward(_to_normalized(uv_ideal, camera)), camera)

    def undistort(self, uv_raw: PixelArray, camera: Intrinsics) -> PixelArray:
        xy = _newton_invert_2d(self._forward, _to_normalized(uv_raw, camera))
        return _to_pixels(xy, camera)


@dataclass(frozen=True)
class Fisheye:
    """OpenCV's fisheye (Kannala-Brandt) model: theta_d = theta (1 + k1 theta^2 + ... k4 theta^8).

    Through the ideal-pinhole intermediate it covers view angles below 90 degrees
    off-axis (fields of view under 180 degrees).

    Example:
        >>> from skyfix.camera import Camera
        >>> cam, lens = Camera.from_fov(640, 480, 90.0), Fisheye(k1=0.05)
        >>> raw = lens.distort(np.array([[600.0, 400.0]]), cam)
        >>> raw.round(2), lens.undistort(raw, cam).round(6)
        (array([[545.87, 369.03]]), array([[600., 400.]]))
    """

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    def __post_init__(self) -> None:
        for name in ("k1", "k2", "k3", "k4"):
            object.__setattr__(self, name, validate.finite_scalar(name, getattr(self, name)))

    @property
    def opencv_coefficients(self) -> np.ndarray:
        """Coefficients in OpenCV's ``cv2.fisheye`` order ``(k1, k2, k3, k4)``."""
        return np.array([self.k1, self.k2, self.k3, self.k4])

    def _theta_d(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        return theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def distort(self, uv_ideal: PixelArray, camera: Intrinsics) -> PixelArray:
        xy = _to_normalized(uv_ideal, camera)
        r = np.hypot(xy[:, 0], xy[:, 1])
        theta = np.arctan(r)
        scale = np.where(r > 1e-12, self._theta_d(theta) / np.maximum(r, 1e-300), 1.0)
        return _to_pixels(xy * scale[:, None], camera)

    def undistort(self, uv_raw: PixelArray, camera: Intrinsics) -> PixelArray:
        xy_d = _to_normalized(uv_raw, camera)
        rd = np.hypot(xy_d[:, 0], xy_d[:, 1])
        theta = rd.copy()
        for _ in range(30):
            t2 = theta * theta
            f = self._theta_d(theta) - rd
            df = 1.0 + t2 * (3 * self.k1 + t2 * (5 * self.k2 + t2 * (7 * self.k3 + 9 * self.k4 * t2)))
            step = f / np.where(np.abs(df) < 1e-12, 1e-12, df)
            theta = theta - step
            if np.max(np.abs(step), initial=0.0) < 1e-15:
                break
        if np.any(theta >= np.pi / 2):
            raise GeometryError("fisheye pixel maps to a view angle >= 90 deg, outside the pinhole domain")
        scale = np.where(rd > 1e-12, np.tan(theta) / np.maximum(rd, 1e-300), 1.0)
        return _to_pixels(xy_d * scale[:, None], camera)


@dataclass(frozen=True)
class Barrel:
    """ImageMagick's ``-distort barrel 'a b c [d]'`` model, with exactly its semantics.

    For an ideal (corrected) pixel at radius r from the image centre, normalised by half
    the smaller image side, the raw (source) pixel lies on the same ray from the centre at
    radius ``(a r^3 + b r^2 + c r + d) r``; ``d`` defaults to ``1 - a - b - c`` so the
    scale is preserved at r = 1. The centre is the image centre, ImageMagick's
    (w/2, h/2) in pixel-edge coordinates, i.e. ((w-1)/2, (h-1)/2) in OpenCV's.
    The model ignores the camera's fx/cx: it is defined on the pixel grid.

    Example:
        >>> from skyfix.camera import Camera
        >>> cam, lens = Camera.from_fov(640, 480, 90.0), Barrel(0.0, 0.0, -0.1)  # d = 1.1
        >>> lens.distort(np.array([[439.5, 239.5]]), cam)  # r = 0.5: source at 1.05 r
        array([[445.5, 239.5]])
    """

    a: float
    b: float
    c: float
    d: float | None = None

    def __post_init__(self) -> None:
        for name in ("a", "b", "c"):
            object.__setattr__(self, name, validate.finite_scalar(name, getattr(self, name)))
        d = 1.0 - self.a - self.b - self.c if self.d is None else validate.finite_scalar("d", self.d)
        object.__setattr__(self, "d", d)

    @staticmethod
    def _centre_and_scale(camera: Intrinsics) -> tuple[np.ndarray, float]:
        centre = np.array([(camera.width - 1) / 2.0, (camera.height - 1) / 2.0])
        return centre, min(camera.width, camera.height) / 2.0

    def radial_factor(self, r: np.ndarray) -> np.ndarray:
        """Source-radius factor ``a r^3 + b r^2 + c r + d`` at normalised radius ``r``."""
        return ((self.a * r + self.b) * r + self.c) * r + self.d

    def distort(self, uv_ideal: PixelArray, camera: Intrinsics) -> PixelArray:
        centre, scale = self._centre_and_scale(camera)
        offset = uv_ideal - centre
        r = np.hypot(offset[:, 0], offset[:, 1]) / scale
        return centre + offset * self.radial_factor(r)[:, None]

    def undistort(self, uv_raw: PixelArray, camera: Intrinsics) -> PixelArray:
        centre, scale = self._centre_and_scale(camera)
        offset = uv_raw - centre
        r_src = np.hypot(offset[:, 0], offset[:, 1]) / scale
        r = r_src.copy()
        for _ in range(50):
            f = r * self.radial_factor(r) - r_src
            df = ((4 * self.a * r + 3 * self.b) * r + 2 * self.c) * r + self.d
            if np.any(np.abs(df) < 1e-9):
                raise GeometryError("barrel model is not invertible at these pixels (d r_src / d r = 0)")
            step = f / df
            r = r - step
            if np.max(np.abs(step), initial=0.0) < 1e-15:
                break
        factor = np.where(r_src > 1e-15, r / np.maximum(r_src, 1e-300), 1.0 / self.d)
        return centre + offset * factor[:, None]
