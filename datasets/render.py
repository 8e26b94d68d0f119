"""Render what a camera sees of a flat, georeferenced ground texture.

The synthetic world is a planar patch: the texture lies in the horizontal plane
``up = 0`` of its own :class:`~skyfix.geo.LocalFrame` (whose ``alt0_m`` is the ground's
ellipsoidal height), row 0 along the north edge, column 0 along the west edge. Pixels
are rendered by exact ray casting through the camera model (distortion included), so
ground truth for any texel is known to floating-point precision. Within a few hundred
metres of the texture origin the plane departs from the curved ground surface by
millimetres (d^2 / 2R).
"""

from __future__ import annotations

import functools
import math
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from itertools import islice
from typing import TypeVar

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame


@dataclass(frozen=True, eq=False)
class GroundTexture:
    """A ground image laid on the plane ``up = 0`` of ``frame``.

    ``image`` is ``(H, W)`` or ``(H, W, C)`` (any numeric dtype; rendered as float32);
    ``metres_per_px`` the texel size; ``center_en_m`` the (east, north) position of the
    image centre in ``frame``, metres.

    Example:
        A 100 m square, black in the west and white in the east, seen by a nadir camera
        30 m up: the edge under the camera falls between the two middle columns:

        >>> image = np.zeros((200, 200), np.float32)
        >>> image[:, 100:] = 1.0
        >>> texture = GroundTexture(image, 0.5, LocalFrame(47.0, 8.0, 400.0))
        >>> seen = render_ground(texture, Camera.from_fov(64, 48, 60.0), CameraPose(47.0, 8.0, 430.0))
        >>> seen.image[24, 30:34].tolist(), bool(seen.mask.all())
        ([0.0, 0.0, 1.0, 1.0], True)
    """

    image: np.ndarray
    metres_per_px: float
    frame: LocalFrame
    center_en_m: tuple[float, float] = (0.0, 0.0)
    _pyramid: list = field(default_factory=list, init=False, repr=False)
    _pyramid_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.ndim not in (2, 3) or img.shape[0] < 2 or img.shape[1] < 2:
            raise InputError(f"GroundTexture.image must be (H, W) or (H, W, C) with H, W >= 2, got {img.shape}")
        if not np.issubdtype(img.dtype, np.number):
            raise InputError(f"GroundTexture.image must be numeric, got dtype {img.dtype}")
        if max(img.shape[:2]) >= 32767:
            raise InputError(f"GroundTexture.image is {img.shape[:2]}; at most 32766 px per side")
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "metres_per_px", validate.positive_scalar("metres_per_px", self.metres_per_px))
        ce, cn = validate.finite_array("center_en_m", self.center_en_m).reshape(2)
        object.__setattr__(self, "center_en_m", (float(ce), float(cn)))

    @property
    def size_m(self) -> tuple[float, float]:
        """(width east, height north) of the texture in metres."""
        return self.image.shape[1] * self.metres_per_px, self.image.shape[0] * self.metres_per_px

    def en_to_px(self, en_m: np.ndarray) -> np.ndarray:
        """(east, north) metres ``(N, 2)`` in ``frame`` -> texel (col, row) ``(N, 2)``."""
        en = validate.points("en_m", en_m, 2)
        h, w = self.image.shape[:2]
        col = (en[:, 0] - self.center_en_m[0]) / self.metres_per_px + (w - 1) / 2.0
        row = (h - 1) / 2.0 - (en[:, 1] - self.center_en_m[1]) / self.metres_per_px
        return np.stack((col, row), axis=1)

    def px_to_enu(self, colrow: np.ndarray) -> np.ndarray:
        """Texel (col, row) ``(N, 2)`` -> ENU metres ``(N, 3)`` in ``frame`` (up = 0)."""
        cr = validate.points("colrow", colrow, 2)
        h, w = self.image.shape[:2]
        e = (cr[:, 0] - (w - 1) / 2.0) * self.metres_per_px + self.center_en_m[0]
        n = ((h - 1) / 2.0 - cr[:, 1]) * self.metres_per_px + self.center_en_m[1]
        return np.stack((e, n, np.zeros_like(e)), axis=1)

    def level(self, index: int) -> np.ndarray:
        """Mip level ``index`` (0 = full resolution) as float32, built on first use (one thread
        builds it while frames are rendered ahead, :func:`rendered_in_order`)."""
        with self._pyramid_lock:
            if not self._pyramid:
                self._pyramid.append(np.ascontiguousarray(self.image, dtype=np.float32))
            while len(self._pyramid) <= index and min(self._pyramid[-1].shape[:2]) >= 4:
                self._pyramid.append(cv2.pyrDown(self._pyramid[-1]))
            return self._pyramid[min(index, len(self._pyramid) - 1)]


@dataclass(frozen=True)
class Rendered:
    """A rendered frame: ``image`` float32 ``(H, W)`` or ``(H, W, C)``; ``mask`` ``(H, W)`` bool,
    True where the pixel centre sees the texture; ``ground_enu_m`` ``(H, W, 3)`` ENU metres
    of each pixel centre's ground point (NaN elsewhere) when requested."""

    image: np.ndarray
    mask: np.ndarray
    ground_enu_m: np.ndarray | None = None


_Item = TypeVar("_Item")
_Result = TypeVar("_Result")


def rendered_in_order(render: Callable[[_Item], _Result], items: Iterable[_Item], *, threads: int = 2
                      ) -> Iterator[tuple[_Item, _Result]]:
    """``(item, render(item))`` for each of ``items``, in their order, with ``threads`` renders
    running ahead at once (the renderers' numpy and OpenCV work releases the GIL). A caller
    that draws sensor noise as it consumes them draws it in frame order: the frames do not
    depend on ``threads``.

    Example:
        >>> list(rendered_in_order(lambda k: k * k, range(4), threads=2))
        [(0, 0), (1, 1), (2, 4), (3, 9)]
    """
    todo = iter(items)
    with ThreadPoolExecutor(validate.integer_in("threads", threads, 1, 64)) as pool:
        ahead = deque((item, pool.submit(render, item)) for item in islice(todo, threads))
        while ahead:
            item, rendered = ahead.popleft()
            nxt = next(todo, _DONE)
            if nxt is not _DONE:
                ahead.append((nxt, pool.submit(render, nxt)))
            yield item, rendered.result()


_DONE = object()


@functools.lru_cache(maxsize=8)
def _pixel_rays(camera: Camera, supersample: int) -> np.ndarray:
    """Unit rays ``(H*s, W*s, 3)`` through the centres of the (sub)pixels of ``camera``."""
    s = supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    rays = camera.pixel_to_ray(np.stack((uu.ravel(), vv.ravel()), axis=1))
    rays = rays.reshape(vv.shape[0], uu.shape[1], 3)
    rays.setflags(write=False)
    return rays


def motion_blur_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    """Normalised linear-streak kernel (odd size) of ``length_px`` along ``angle_deg`` (0 = +u,
    clockwise in the image), for ``cv2.filter2D``; sub-pixel length by bilinear splatting."""
    size = int(math.ceil(length_px)) | 1
    kernel = np.zeros((size, size), np.float32)
    c = (size - 1) / 2.0
    dx, dy = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    for t in np.linspace(-length_px / 2.0, length_px / 2.0, 4 * size):
        x, y = c + t * dx, c + t * dy
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        for xi, yi, wgt in ((x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)),
                            (x0, y0 + 1, (1 - fx) * fy), (x0 + 1, y0 + 1, fx * fy)):
            if 0 <= xi < size and 0 <= yi < size:
                kernel[yi, xi] += wgt
    return kernel / kernel.sum()


def _sensor_effects(img: np.ndarray, camera: Camera, vignetting: float, blur_sigma_px: float,
                    motion_blur_px: float, motion_blur_angle_deg: float, noise_sigma: float,
                    rng: np.random.Generator | None) -> np.ndarray:
    """Vignetting, Gaussian blur, motion blur and noise on a rendered image, in that order."""
    if vignetting > 0:
        vv, uu = np.mgrid[0:camera.height, 0:camera.width]
        r2 = ((uu - camera.cx) ** 2 + (vv - camera.cy) ** 2) / (camera.cx ** 2 + camera.cy ** 2)
        gain = (1.0 - vignetting * r2).astype(np.float32)
        img = img * (gain[..., None] if img.ndim == 3 else gain)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if motion_blur_px > 0:
        img = cv2.filter2D(img, -1, motion_blur_kernel(motion_blur_px, motion_blur_angle_deg))
    if noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng()
        img = img + rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
    return img


def _pixel_mask(inside: np.ndarray, camera: Camera, s: int) -> np.ndarray:
    """Per-pixel validity from the ``s`` x ``s`` subsamples' ``inside`` mask."""
    if s == 1:
        return inside
    if s % 2 == 1:
        return inside[s // 2::s, s // 2::s]
    # even supersampling has no sample at the pixel centre: require all samples inside
    return inside.reshape(camera.height, s, camera.width, s).all(axis=(1, 3))


def render_ground(texture: GroundTexture, camera: Camera, pose: CameraPose, *,
                  background: float = 0.0, supersample: int = 1, blur_sigma_px: float = 0.0,
                  motion_blur_px: float = 0.0, motion_blur_angle_deg: float = 0.0,
                  vignetting: float = 0.0, noise_sigma: float = 0.0,
                  rng: np.random.Generator | None = None, return_ground: bool = False) -> Rendered:
    """Render ``texture`` as seen by ``camera`` at ``pose``.

    Each (sub)pixel's ray is cast onto the texture plane; texels are sampled bilinearly
    from a mip level matched to the median ground footprint so distant texture does not
    alias. Pixels that see sky or ground outside the texture get ``background``.

    Optional effects, applied in this order: ``supersample`` (s x s rays per pixel,
    averaged), ``vignetting`` (gain ``1 - vignetting * (r / r_corner)^2``),
    ``blur_sigma_px`` (Gaussian), ``motion_blur_px`` (linear streak of that length along
    ``motion_blur_angle_deg``, 0 = +u, clockwise in the image), ``noise_sigma`` (additive
    Gaussian in image units, from ``rng``).
    """
    supersample = validate.integer_in("supersample", supersample, 1)
    for name, value in (("blur_sigma_px", blur_sigma_px), ("motion_blur_px", motion_blur_px),
                        ("vignetting", vignetting), ("noise_sigma", noise_sigma)):
        validate.nonnegative_scalar(name, value)
    background = validate.finite_scalar("background", background)
    cam_enu, r_frame_from_cam = pose.in_frame(texture.frame)
    if cam_enu[2] <= 0.0:
        raise GeometryError(f"camera is {cam_enu[2]:.3f} m above the texture plane; it must be above it")

    rays = _pixel_rays(camera, supersample)
    d = rays @ r_frame_from_cam.T
    d_up = d[..., 2]
    down = d_up < -1e-9
    t = np.where(down, cam_enu[2] / np.where(down, -d_up, 1.0), np.nan)
    east = cam_enu[0] + t * d[..., 0]
    north = cam_enu[1] + t * d[..., 1]

    h_tex, w_tex = texture.image.shape[:2]
    col = (east - texture.center_en_m[0]) / texture.metres_per_px + (w_tex - 1) / 2.0
    row = (h_tex - 1) / 2.0 - (north - texture.center_en_m[1]) / texture.metres_per_px
    inside = down & (col >= -0.5) & (col <= w_tex - 0.5) & (row >= -0.5) & (row <= h_tex - 0.5)

    level = 0
    if np.any(inside):
        # Ground footprint of one sample: slant range / focal, stretched by obliquity.
        footprint_m = t[inside] / (camera.fx * supersample) / np.sqrt(np.abs(d_up[inside]))
        ratio = float(np.median(footprint_m)) / texture.metres_per_px
        level = max(0, int(math.floor(math.log2(ratio)))) if ratio > 1.0 else 0
    src = texture.level(level)
    scale = 2.0 ** level
    # cv2.pyrDown centres level-L texel i on level-0 texel 2^L * i (not on 2^L * (i + 0.5) - 0.5).
    map_x = np.where(inside, col / scale, -10.0).astype(np.float32)
    map_y = np.where(inside, row / scale, -10.0).astype(np.float32)
    img = cv2.remap(src, map_x, map_y, interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    if img.ndim == 3:
        img[~inside] = background
    else:
        img = np.where(inside, img, np.float32(background))

    s = supersample
    if s > 1:
        hh, ww = camera.height, camera.width
        img = img.reshape(hh, s, ww, s, *img.shape[2:]).mean(axis=(1, 3)).astype(np.float32)
    img = _sensor_effects(img, camera, vignetting, blur_sigma_px, motion_blur_px, motion_blur_angle_deg,
                          noise_sigma, rng)
    mask = _pixel_mask(inside, camera, s)
    ground = None
    if return_ground:
        rays_c = _pixel_rays(camera, 1) @ r_frame_from_cam.T
        du = rays_c[..., 2]
        ok = du < -1e-9
        tc = np.where(ok, cam_enu[2] / np.where(ok, -du, 1.0), np.nan)
        ground = cam_enu + tc[..., None] * rays_c
        ground[..., 2] = np.where(ok, 0.0, np.nan)
    return Rendered(image=img.astype(np.float32, copy=False), mask=mask, ground_enu_m=ground)
