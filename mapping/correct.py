"""Precomputed remap tables that turn raw photos into ideal pinhole images.

An :class:`Undistortion` holds, for every pixel of the corrected (output) image, the raw
pixel it samples: ``map_x``/``map_y`` ``(H_out, W_out)`` float32 in OpenCV pixel
coordinates of the raw image. It is built once per image size and applied to any
number of photos with ``cv2.remap``.

- ImageMagick barrel models: the output camera has the same pixel grid as the raw one,
  so the table is exactly ``Barrel.distort`` of each output pixel (ImageMagick's geometry).
- Brown-Conrady and fisheye cameras: the tables come from OpenCV's
  ``initUndistortRectifyMap`` / ``fisheye.initUndistortRectifyMap``.
- Any other foundation camera: output rays projected through the raw camera.

``crop=True`` keeps the largest rectangle, centred on the principal point and with the
original aspect ratio, whose pixels all sample inside the raw image.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import cv2
import numpy as np

from skyfix.camera import Camera
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import GeometryError, InputError
from skyfix.mapping.lens import barrel_camera

__all__ = ["Undistortion"]

_INTERPOLATION = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC,
                  "lanczos": cv2.INTER_LANCZOS4}
_TAPS_PX = 4  # rows the widest interpolation (Lanczos, 8x8) reads beyond its sample
BAND_ROWS = 64  # output rows remapped at a time (benchmarks/lens.py: 64-128 fastest on 1200 x 900 photos)


def _source_rows(map_y: np.ndarray, band_rows: int, height: int) -> tuple[tuple[int, int, int, int], ...]:
    """Per band of ``band_rows`` output rows: (first, end) output row and (first, end) raw row its samples read,
    the widest interpolation's taps included (clamped to the raw image)."""
    taps = _TAPS_PX
    out = []
    for y0 in range(0, map_y.shape[0], band_rows):
        y1 = min(map_y.shape[0], y0 + band_rows)
        band = map_y[y0:y1]
        band = band[np.isfinite(band)]  # a table may mark rays it cannot map with NaN
        if band.size:
            lo = int(np.clip(np.floor(band.min()) - taps, 0, height))
            hi = int(np.clip(np.ceil(band.max()) + taps + 1, 0, height))
        else:
            lo, hi = 0, height
        out.append((y0, y1, min(lo, hi), hi))
    return tuple(out)


def _pinhole(camera: Camera) -> Camera:
    return replace(camera, distortion=None)


def _maps_generic(source: Camera, output: Camera) -> tuple[np.ndarray, np.ndarray]:
    vv, uu = np.mgrid[0:output.height, 0:output.width].astype(np.float64)
    rays = output.pixel_to_ray(np.stack((uu.ravel(), vv.ravel()), axis=1))
    uv = source.project(rays)
    return (uv[:, 0].reshape(vv.shape).astype(np.float32),
            uv[:, 1].reshape(vv.shape).astype(np.float32))


def _maps_barrel(source: Camera, output: Camera) -> tuple[np.ndarray, np.ndarray] | None:
    """Direct ImageMagick geometry when the output grid is the source's ideal grid."""
    same_grid = (output.width == source.width and output.height == source.height
                 and np.allclose([output.fx, output.fy, output.cx, output.cy],
                                 [source.fx, source.fy, source.cx, source.cy], rtol=0, atol=1e-9))
    if not same_grid:
        return None
    # Barrel.distort on the whole grid, broadcast over rows and columns for speed:
    # src = centre + offset * radial_factor(|offset| / scale).
    barrel: Barrel = source.distortion
    ctr_x, ctr_y = (source.width - 1) / 2.0, (source.height - 1) / 2.0
    scale = min(source.width, source.height) / 2.0
    dx = np.arange(output.width, dtype=np.float64)[None, :] - ctr_x
    dy = np.arange(output.height, dtype=np.float64)[:, None] - ctr_y
    factor = barrel.radial_factor(np.sqrt(dx * dx + dy * dy) / scale)
    return (ctr_x + dx * factor).astype(np.float32), (ctr_y + dy * factor).astype(np.float32)


def _maps_opencv(source: Camera, output: Camera) -> tuple[np.ndarray, np.ndarray]:
    size = (output.width, output.height)
    if isinstance(source.distortion, Fisheye):
        return cv2.fisheye.initUndistortRectifyMap(source.K, source.distortion.opencv_coefficients,
                                                   np.eye(3), output.K, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(source.K, source.distortion.opencv_coefficients, None,
                                       output.K, size, cv2.CV_32FC1)


def _valid(map_x: np.ndarray, map_y: np.ndarray, source: Camera) -> np.ndarray:
    """Output pixels whose bilinear sample lies entirely inside the raw image."""
    return ((map_x >= 0) & (map_x <= source.width - 1) & (map_y >= 0) & (map_y <= source.height - 1))


def _centred_crop(valid: np.ndarray, cx: float, cy: float) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) exclusive: largest all-valid rectangle about (cx, cy) with the image's aspect."""
    h, w = valid.shape
    integral = cv2.integral(valid.astype(np.uint8))
    half_w_max = min(cx + 0.5, w - 0.5 - cx)
    half_h_max = min(cy + 0.5, h - 0.5 - cy)

    def box(scale: float) -> tuple[int, int, int, int]:
        hw, hh = scale * half_w_max, scale * half_h_max
        x0, x1 = int(np.ceil(cx - hw + 0.5)), int(np.floor(cx + hw + 0.5))
        y0, y1 = int(np.ceil(cy - hh + 0.5)), int(np.floor(cy + hh + 0.5))
        return max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)

    def all_valid(b: tuple[int, int, int, int]) -> bool:
        x0, y0, x1, y1 = b
        if x1 <= x0 or y1 <= y0:
            return False
        count = integral[y1, x1] - integral[y0, x1] - integral[y1, x0] + integral[y0, x0]
        return int(count) == (x1 - x0) * (y1 - y0)

    lo, hi = 0.0, 1.0
    if all_valid(box(hi)):
        return box(hi)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if all_valid(box(mid)) else (lo, mid)
    result = box(lo)
    if not all_valid(result) or (result[2] - result[0]) < 2 or (result[3] - result[1]) < 2:
        raise GeometryError("no valid pixels around the principal point to crop to; check the lens model")
    return result


@dataclass(frozen=True, eq=False)
class Undistortion:
    """Remap tables from a raw camera to a pinhole output camera (see module docstring).

    ``source``: the raw camera (with its distortion). ``output``: the pinhole camera of the
    corrected image. ``map_x``/``map_y``: ``(output.height, output.width)`` float32 raw pixel
    coordinates sampled by each output pixel. ``valid``: ``(H, W)`` bool, True where the
    sample lies inside the raw image. ``focal_scale``: output focal / raw paraxial focal,
    what a corrected photo's EXIF focal length is multiplied by.
    """

    source: Camera
    output: Camera
    map_x: np.ndarray
    map_y: np.ndarray
    valid: np.ndarray
    focal_scale: float

    def __post_init__(self) -> None:
        for arr in (self.map_x, self.map_y, self.valid):
            arr.setflags(write=False)

    @cached_property
    def _bands(self) -> tuple[tuple[int, int, int, int], ...]:
        """:func:`_source_rows` of the table, computed on the first :meth:`apply`."""
        return _source_rows(self.map_y, BAND_ROWS, self.source.height)

    @classmethod
    def from_cameras(cls, source: Camera, output: Camera, focal_scale: float | None = None,
                     crop: bool = False) -> Undistortion:
        """Tables taking ``source`` raw images to ``output`` (whose distortion is ignored)."""
        if not isinstance(source, Camera) or not isinstance(output, Camera):
            raise InputError("source and output must be skyfix.camera.Camera instances")
        output = _pinhole(output)
        if source.distortion is None:
            maps = _maps_generic(source, output)
        elif isinstance(source.distortion, Barrel):
            maps = _maps_barrel(source, output) or _maps_generic(source, output)
        elif isinstance(source.distortion, (BrownConrady, Fisheye)):
            maps = _maps_opencv(source, output)
        else:
            maps = _maps_generic(source, output)
        map_x, map_y = (np.ascontiguousarray(m, dtype=np.float32) for m in maps)
        valid = _valid(map_x, map_y, source)
        if not valid.any():
            raise GeometryError("the output camera sees nothing of the raw image")
        if focal_scale is None:
            focal_scale = output.fx / source.fx
        if crop:
            x0, y0, x1, y1 = _centred_crop(valid, output.cx, output.cy)
            output = Camera(x1 - x0, y1 - y0, output.fx, output.fy, output.cx - x0, output.cy - y0)
            map_x, map_y, valid = (np.ascontiguousarray(m[y0:y1, x0:x1]) for m in (map_x, map_y, valid))
        return cls(source, output, map_x, map_y, valid, float(focal_scale))

    @classmethod
    def for_barrel(cls, barrel: Barrel, width: int, height: int, raw_focal_px: float | None = None,
                   crop: bool = False) -> Undistortion:
        """ImageMagick ``-distort barrel`` on a ``width x height`` photo (same output grid).

        Example:
            The corrected photo's focal is the raw one over d = 1 - a - b - c = 1.22, and
            the ends of its middle row sample raw pixels 67 px inside the photo:

            >>> from skyfix.mapping.lens import parse_barrel
            >>> tables = Undistortion.for_barrel(parse_barrel("0.1 -0.32 0"), 1200, 900)
            >>> round(tables.focal_scale, 4), tables.output.distortion is None
            (0.8197, True)
            >>> [round(float(tables.map_x[449, u]), 1) for u in (0, 1199)]
            [66.8, 1132.2]
        """
        source = barrel_camera(barrel, width, height, raw_focal_px)
        return cls.from_cameras(source, _pinhole(source), focal_scale=1.0 / barrel.d, crop=crop)

    @classmethod
    def for_camera(cls, camera: Camera, crop: bool = False) -> Undistortion:
        """Correct photos of a calibrated ``camera`` onto a pinhole camera with the same K."""
        if camera.distortion is None:
            raise InputError("camera has no distortion model; nothing to correct")
        return cls.from_cameras(camera, _pinhole(camera), focal_scale=1.0, crop=crop)

    def apply(self, image: np.ndarray, interpolation: str = "linear", border: str = "replicate") -> np.ndarray:
        """Corrected image ``(H_out, W_out[, C])`` from a raw ``(H, W[, C])`` image (any cv2 dtype).

        ``border='replicate'`` repeats the edge pixel outside the raw image (ImageMagick's
        default virtual pixels); ``'constant'`` paints zeros there.
        """
        img = np.asarray(image)
        if img.ndim not in (2, 3) or img.shape[:2] != (self.source.height, self.source.width):
            raise InputError(f"image must be ({self.source.height}, {self.source.width}[, C]) to match "
                             f"the lens tables, got {img.shape}")
        if interpolation not in _INTERPOLATION:
            raise InputError(f"interpolation must be one of {sorted(_INTERPOLATION)}, got {interpolation!r}")
        if border not in ("replicate", "constant"):
            raise InputError(f"border must be 'replicate' or 'constant', got {border!r}")
        border_mode = cv2.BORDER_REPLICATE if border == "replicate" else cv2.BORDER_CONSTANT
        # Float tables, not OpenCV's fixed-point ones (1/32 px): exact, and with OpenCV 5's
        # vectorised float path as fast on 3 channels and ~1.7x faster on 1 or 4 (BGRX).
        if not img.flags.c_contiguous or img.dtype == bool:
            return cv2.remap(img, self.map_x, self.map_y, _INTERPOLATION[interpolation], borderMode=border_mode)
        # Band by band, each band's raw rows read once in order first: the curved reads of a lens table then
        # hit the cache instead of memory that the hardware prefetcher, which follows straight runs, did not
        # fetch (a 1200 x 900 BGRX photo just decoded: 5.4 ms in one remap, 2.6 ms so; the same pixels).
        out = np.empty(self.map_x.shape + img.shape[2:], img.dtype)
        for y0, y1, lo, hi in self._bands:
            if hi > lo:
                cv2.sumElems(img[lo:hi].reshape(hi - lo, -1))
            cv2.remap(img, self.map_x[y0:y1], self.map_y[y0:y1], _INTERPOLATION[interpolation], dst=out[y0:y1],
                      borderMode=border_mode)
        return out
