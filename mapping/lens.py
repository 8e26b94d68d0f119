"""Lens models for photo correction, and conversion between ImageMagick's barrel and OpenCV's.

The models themselves live in the foundation (:mod:`skyfix.distortion`) so that every
module projects through the same code; this module adds what correcting photos needs:

- :data:`BarrelModel` is the foundation's :class:`~skyfix.distortion.Barrel`, i.e.
  ImageMagick's ``-distort barrel 'a b c [d]'``: the raw (source) pixel of an ideal pixel
  at normalised radius r lies at radius ``(a r^3 + b r^2 + c r + d) r``, r normalised by
  half the smaller image side, centre at the image centre, ``d = 1 - a - b - c`` by default.
- :func:`barrel_camera` puts a barrel model on a :class:`~skyfix.camera.Camera` with the
  focal length that the *corrected* image has (raw paraxial focal / d).
- :func:`barrel_to_opencv` and :func:`opencv_to_barrel` fit one model to the other by
  least squares over the whole raw image and report the residual in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skyfix import validate
from skyfix.camera import Camera
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import GeometryError, InputError

__all__ = ["BarrelModel", "BrownConrady", "Fisheye", "LensFit", "barrel_camera", "barrel_to_opencv",
           "opencv_to_barrel", "parse_barrel", "projection_difference_px"]

#: ImageMagick's barrel model (the foundation's :class:`skyfix.distortion.Barrel`).
BarrelModel = Barrel


def parse_barrel(text: str) -> Barrel:
    """Parse ImageMagick's argument string ``'a b c'`` or ``'a b c d'`` (spaces or commas).

    Example:
        >>> parse_barrel("0.1 -0.32 0")  # d defaults to 1 - a - b - c
        Barrel(a=0.1, b=-0.32, c=0.0, d=1.22)
    """
    if not isinstance(text, str):
        raise InputError(f"barrel coefficients must be a string like '0.1 -0.32 0', got {text!r}")
    parts = text.replace(",", " ").split()
    if len(parts) not in (3, 4):
        raise InputError(f"barrel coefficients must be 3 or 4 numbers 'a b c [d]', got {text!r}")
    values = [validate.finite_scalar(f"barrel coefficient {name}", p) for name, p in zip("abcd", parts, strict=False)]
    return Barrel(*values)


def _half_min_side_px(width: int, height: int) -> float:
    return min(width, height) / 2.0


def barrel_camera(barrel: Barrel, width: int, height: int, raw_focal_px: float | None = None) -> Camera:
    """The camera whose raw images follow ``barrel``, with ideal intrinsics of the corrected image.

    ``raw_focal_px`` is the paraxial focal length of the raw photos in pixels (e.g. from
    EXIF); the corrected image magnifies the centre by ``1 / d``, so its focal length is
    ``raw_focal_px / d``. Without it, the raw focal defaults to ``d`` times half the smaller
    image side, which makes the ideal focal equal to ImageMagick's radius normaliser (any
    value gives the same pixel geometry). Principal point: the image centre.
    """
    if not isinstance(barrel, Barrel):
        raise InputError(f"barrel must be a BarrelModel, got {type(barrel).__name__}")
    if barrel.d <= 0:
        raise GeometryError(f"barrel d = {barrel.d} must be > 0 (the centre would be flipped or collapsed)")
    scale_px = _half_min_side_px(width, height)
    f_raw = barrel.d * scale_px if raw_focal_px is None else validate.positive_scalar("raw_focal_px", raw_focal_px)
    f_ideal = f_raw / barrel.d
    return Camera(width, height, f_ideal, f_ideal, (width - 1) / 2.0, (height - 1) / 2.0, barrel)


def _raw_grid(camera: Camera, n: int) -> np.ndarray:
    """``(n*n, 2)`` raw pixels spread over the whole image, edges included."""
    u = np.linspace(0.0, camera.width - 1.0, n)
    v = np.linspace(0.0, camera.height - 1.0, n)
    uu, vv = np.meshgrid(u, v)
    return np.stack((uu.ravel(), vv.ravel()), axis=1)


def projection_difference_px(reference: Camera, other: Camera, n: int = 41) -> tuple[float, float]:
    """(RMS, max) pixel distance between where two cameras put the same rays.

    Rays come from an ``n x n`` grid over ``reference``'s raw image; both cameras
    project them to raw pixels.
    """
    uv = _raw_grid(reference, n)
    rays = reference.pixel_to_ray(uv)
    diff = np.linalg.norm(other.project(rays) - uv, axis=1)
    return float(np.sqrt(np.mean(diff ** 2))), float(np.max(diff))


def _paraxial_magnification(camera: Camera, eps_px: float = 1e-3) -> float:
    """Raw / ideal pixel offset for rays next to the optical axis (1 for OpenCV models, d for barrel)."""
    if camera.distortion is None:
        return 1.0
    ideal = np.array([[camera.cx + eps_px, camera.cy], [camera.cx, camera.cy]])
    raw = camera.distortion.distort(ideal, camera)
    return float((raw[0, 0] - raw[1, 0]) / eps_px)


@dataclass(frozen=True)
class LensFit:
    """A fitted camera and how far it departs from the model it was fitted to, in pixels."""

    camera: Camera
    rms_px: float
    max_px: float


def barrel_to_opencv(barrel: Barrel, width: int, height: int, raw_focal_px: float | None = None,
                     n_grid: int = 41) -> LensFit:
    """OpenCV Brown-Conrady camera (k1, k2, k3; no tangential terms) closest to ``barrel``.

    The OpenCV camera's focal length is the raw paraxial focal (``raw_focal_px``, see
    :func:`barrel_camera`); k1..k3 are found by linear least squares on the raw-pixel
    radius of rays sampled over the whole image. The barrel polynomial has odd powers the
    even OpenCV series cannot express exactly, hence the reported residual.

    Example:
        A 1200 x 900 photo's barrel model as OpenCV k1..k3: the even series misses it by
        about a pixel (RMS over the image), most in the corners:

        >>> fit = barrel_to_opencv(parse_barrel("0.1 -0.32 0"), 1200, 900)
        >>> round(fit.camera.fx, 1), round(fit.camera.distortion.k1, 3), round(fit.rms_px, 1), round(fit.max_px, 1)
        (549.0, -0.215, 1.2, 6.7)
    """
    source = barrel_camera(barrel, width, height, raw_focal_px)
    f_raw = source.fx * barrel.d
    uv_raw = _raw_grid(source, n_grid)
    rays = source.pixel_to_ray(uv_raw)
    r_n = np.hypot(rays[:, 0], rays[:, 1]) / rays[:, 2]
    rho_raw = np.hypot(uv_raw[:, 0] - source.cx, uv_raw[:, 1] - source.cy)
    design = f_raw * r_n[:, None] * np.stack((r_n ** 2, r_n ** 4, r_n ** 6), axis=1)
    k, *_ = np.linalg.lstsq(design, rho_raw - f_raw * r_n, rcond=None)
    camera = Camera(width, height, f_raw, f_raw, source.cx, source.cy,
                    BrownConrady(k1=float(k[0]), k2=float(k[1]), k3=float(k[2])))
    rms, worst = projection_difference_px(source, camera, n_grid)
    return LensFit(camera, rms, worst)


def opencv_to_barrel(camera: Camera, n_grid: int = 41) -> LensFit:
    """ImageMagick barrel camera closest to an OpenCV camera (any foundation distortion model).

    Fits a, b, c with ImageMagick's default ``d = 1 - a - b - c``; the ideal focal is set
    so that the paraxial (raw, near-axis) focal length matches ``camera``'s. The barrel model is centred on the
    image and isotropic, so an off-centre principal point, fx != fy or tangential terms
    show up in the residual.
    """
    from scipy.optimize import least_squares

    if not isinstance(camera, Camera):
        raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
    uv_raw = _raw_grid(camera, n_grid)
    rays = camera.pixel_to_ray(uv_raw)
    f_raw = float(np.sqrt(camera.fx * camera.fy)) * _paraxial_magnification(camera)

    def build(p: np.ndarray) -> Camera:
        return barrel_camera(Barrel(float(p[0]), float(p[1]), float(p[2])), camera.width, camera.height, f_raw)

    def residual(p: np.ndarray) -> np.ndarray:
        if 1.0 - p.sum() <= 0.05:
            return np.full(2 * len(uv_raw), 1e6)
        return (build(p).project(rays) - uv_raw).ravel()

    result = least_squares(residual, np.zeros(3), x_scale=0.1, method="lm")
    fitted = build(result.x)
    rms, worst = projection_difference_px(camera, fitted, n_grid)
    return LensFit(fitted, rms, worst)
