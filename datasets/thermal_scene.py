"""Synthetic thermal scenes: a forest-like temperature field with fires, smoke and a sensor.

The ground is the plane ``up = 0`` of the scene's :class:`~skyfix.geo.LocalFrame` (its
``alt0_m`` is the ground's ellipsoidal height). Two layers are rendered with
:func:`skyfix.datasets.render.render_ground` and composited in degrees Celsius:

- background: multi-scale smooth noise (tree crowns ~2 m, stands ~10 m, slopes ~40 m)
  around ``ambient_c``;
- fires: discs of burning area whose radius grows or shrinks linearly in time, with a
  slightly hotter core, plus an optional smoke plume (opacity on the ground layer,
  drawn downwind) that pulls observed temperatures towards the smoke's own.

:class:`ThermalSensor` adds the camera: temporal noise (NETD), stuck ("dead") pixels
at the counts range limits, and conversion to 16-bit radiometric counts or 8-bit
display frames (fixed span or automatic gain, any palette).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.datasets.render import GroundTexture, render_ground
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.thermal.palettes import apply_palette, check_palette

ZERO_C_IN_K = 273.15


@dataclass(frozen=True)
class FireSpec:
    """One fire: centre (``east_m``, ``north_m``) in the scene frame, burning-disc radius
    ``radius_m`` at ``start_s`` changing by ``growth_mps`` (negative: dying), peak
    temperature ``peak_c``, burning between ``start_s`` and ``end_s`` (seconds).
    ``smoke_opacity`` (0-1) and ``smoke_length_m`` describe a plume drifting towards
    ``wind_to_deg`` (clockwise from north)."""

    east_m: float
    north_m: float
    radius_m: float = 1.5
    peak_c: float = 600.0
    growth_mps: float = 0.0
    start_s: float = -math.inf
    end_s: float = math.inf
    smoke_opacity: float = 0.0
    smoke_length_m: float = 30.0
    wind_to_deg: float = 45.0

    def __post_init__(self) -> None:
        for name in ("east_m", "north_m", "peak_c", "growth_mps", "smoke_length_m", "wind_to_deg"):
            validate.finite_scalar(f"FireSpec.{name}", getattr(self, name))
        validate.positive_scalar("FireSpec.radius_m", self.radius_m)
        if not 0.0 <= self.smoke_opacity <= 1.0:
            raise InputError(f"FireSpec.smoke_opacity must be in [0, 1], got {self.smoke_opacity}")
        if not self.start_s < self.end_s:
            raise InputError(f"FireSpec.start_s ({self.start_s}) must be before end_s ({self.end_s})")

    def radius_at(self, time_s: float) -> float:
        """Burning radius (m) at ``time_s``; 0 when not burning."""
        if not self.start_s <= time_s <= self.end_s:
            return 0.0
        dt = 0.0 if math.isinf(self.start_s) else time_s - self.start_s
        return max(self.radius_m + self.growth_mps * dt, 0.0)


def random_fires(n: int, rng: np.random.Generator, *, half_extent_m: float = 20.0,
                 radius_m: tuple[float, float] = (0.6, 1.5), peak_c: tuple[float, float] = (350.0, 700.0),
                 growth_mps: float = 0.0, start_s: float = 0.0, smoke_opacity: float = 0.0) -> list[FireSpec]:
    """``n`` fires uniformly within +-``half_extent_m`` of the scene origin, radius and peak
    temperature uniform in the given (low, high) ranges, all starting at ``start_s``."""
    n = validate.integer_in("n", n, 0)
    half = validate.positive_scalar("half_extent_m", half_extent_m)
    return [FireSpec(float(rng.uniform(-half, half)), float(rng.uniform(-half, half)),
                     float(rng.uniform(*radius_m)), float(rng.uniform(*peak_c)), growth_mps=growth_mps,
                     start_s=start_s, smoke_opacity=smoke_opacity, wind_to_deg=float(rng.uniform(0.0, 360.0)))
            for _ in range(int(n))]


@functools.lru_cache(maxsize=4)
def forest_texture(size_px: int, metres_per_px: float, seed: int) -> np.ndarray:
    """Zero-mean, unit-ish-variance ``(size_px, size_px)`` float32 forest-like pattern."""
    rng = np.random.default_rng(seed)
    out = np.zeros((size_px, size_px), np.float32)
    for scale_m, weight in ((2.0, 0.6), (10.0, 0.6), (40.0, 0.5)):
        sigma_px = max(scale_m / metres_per_px / 2.0, 0.5)
        # Blur a coarser noise field and resize: same spectrum, much cheaper than a huge kernel.
        step = max(int(sigma_px // 4), 1)
        small = rng.standard_normal((size_px // step + 1, size_px // step + 1)).astype(np.float32)
        small = cv2.GaussianBlur(small, (0, 0), sigma_px / step)
        small /= small.std() + 1e-12
        layer = cv2.resize(small, (size_px, size_px), interpolation=cv2.INTER_CUBIC) if step > 1 else small[:size_px, :size_px]
        out += weight * layer
    out /= out.std()
    out.setflags(write=False)
    return out


class ThermalScene:
    """A rendered thermal world (see module docstring).

    ``frame``: scene frame, origin on the ground. ``fires``: :class:`FireSpec` list.
    ``size_m``/``metres_per_px``: extent and texel of the background; outside it the
    ground is at ``ambient_c``. ``texture_sigma_c``: background temperature spread.
    ``fire_metres_per_px``: texel of the fire layer (coarsened automatically so that
    layer stays under 4096 px per side).
    """

    def __init__(self, frame: LocalFrame, fires: list[FireSpec] | tuple[FireSpec, ...] = (), *,
                 ambient_c: float = 15.0, texture_sigma_c: float = 3.0, size_m: float = 600.0,
                 metres_per_px: float = 0.25, fire_metres_per_px: float = 0.04, seed: int = 0,
                 smoke_c: float | None = None) -> None:
        if not isinstance(frame, LocalFrame):
            raise InputError(f"frame must be a LocalFrame, got {type(frame).__name__}")
        self.frame = frame
        self.fires = tuple(fires)
        for f in self.fires:
            if not isinstance(f, FireSpec):
                raise InputError(f"fires must be FireSpec objects, got {type(f).__name__}")
        self.ambient_c = validate.finite_scalar("ambient_c", ambient_c)
        self.texture_sigma_c = validate.finite_scalar("texture_sigma_c", texture_sigma_c)
        self.smoke_c = self.ambient_c + 10.0 if smoke_c is None else validate.finite_scalar("smoke_c", smoke_c)
        mpp = validate.positive_scalar("metres_per_px", metres_per_px)
        size_px = int(round(validate.positive_scalar("size_m", size_m) / mpp))
        pattern = forest_texture(size_px, mpp, int(seed))
        self._background = GroundTexture(self.ambient_c + self.texture_sigma_c * pattern, mpp, frame)
        self._fire_mpp = validate.positive_scalar("fire_metres_per_px", fire_metres_per_px)
        self._fire_cache: tuple[tuple, GroundTexture | None] | None = None

    @property
    def ground_alt_m(self) -> float:
        """Ellipsoidal height of the ground plane, metres."""
        return self.frame.alt0_m

    def fire_positions(self, time_s: float) -> list[tuple[int, np.ndarray, float]]:
        """(index, ENU ``(3,)`` in the scene frame, radius_m) of the fires burning at ``time_s``."""
        out = []
        for i, f in enumerate(self.fires):
            r = f.radius_at(time_s)
            if r > 0:
                out.append((i, np.array([f.east_m, f.north_m, 0.0]), r))
        return out

    def _fire_layer(self, time_s: float) -> GroundTexture | None:
        radii = tuple(f.radius_at(time_s) for f in self.fires)
        cached = self._fire_cache  # one read: frames may be rendered in two threads (rendered_in_order)
        if cached is not None and cached[0] == radii:
            return cached[1]
        active = [(f, r) for f, r in zip(self.fires, radii, strict=True) if r > 0]
        tex = None
        if active:
            lo = np.array([np.inf, np.inf])
            hi = -lo
            for f, r in active:
                c = np.array([f.east_m, f.north_m])
                reach = r + 1.0
                lo, hi = np.minimum(lo, c - reach), np.maximum(hi, c + reach)
                if f.smoke_opacity > 0:
                    w = np.radians(f.wind_to_deg)
                    end = c + f.smoke_length_m * np.array([np.sin(w), np.cos(w)])
                    width = r + 0.3 * f.smoke_length_m
                    lo, hi = np.minimum(lo, end - width), np.maximum(hi, end + width)
            mpp = max(self._fire_mpp, float((hi - lo).max()) / 4096.0)
            ncol, nrow = (np.ceil((hi - lo) / mpp).astype(int) + 1)
            centre = (lo + hi) / 2.0
            east = centre[0] + (np.arange(ncol) - (ncol - 1) / 2.0) * mpp
            north = centre[1] - (np.arange(nrow) - (nrow - 1) / 2.0) * mpp
            excess = np.zeros((nrow, ncol), np.float32)
            opacity = np.zeros((nrow, ncol), np.float32)
            edge_m = max(0.15, 2.0 * mpp)
            for f, r in active:
                # each term on the texels where it can be non-zero, a box of rows x columns (a layer is up to
                # 4096 x 4096 texels; the same values as over the whole layer, zero outside the box)
                de_col, dn_row = east - f.east_m, north - f.north_m
                rows, cols = np.flatnonzero(np.abs(dn_row) < r + edge_m), np.flatnonzero(np.abs(de_col) < r + edge_m)
                box = np.ix_(rows, cols)  # cover > 0 only where dist < r + edge / 2
                de, dn = np.meshgrid(de_col[cols], dn_row[rows])
                dist = np.hypot(de, dn)
                cover = np.clip((r - dist) / edge_m + 0.5, 0.0, 1.0)
                core = 1.0 - 0.3 * np.clip(dist / r, 0.0, 1.0) ** 2
                excess[box] = np.maximum(excess[box], ((f.peak_c - self.ambient_c) * cover * core).astype(np.float32))
                if f.smoke_opacity > 0:
                    w = np.radians(f.wind_to_deg)
                    # the plume is 0 up-wind of along = -r; along = east part + north part, so its largest value on a
                    # column (row) is at the row (column) where that part is largest (1 m margin for rounding)
                    a_col, a_row = de_col * np.sin(w), dn_row * np.cos(w)
                    rows, cols = np.flatnonzero(a_row + a_col.max() > -r - 1.0), np.flatnonzero(a_col + a_row.max() > -r - 1.0)
                    box = np.ix_(rows, cols)
                    # opacity * clip(along / r + 1, 0, 1) * exp(-max(along, 0) / length) * exp(-(across / width)^2 / 2),
                    # width = r + 0.3 max(along, 0), evaluated in place (the same operations in the same order)
                    along = np.add.outer(a_row[rows], a_col[cols])
                    across = np.add.outer(dn_row[rows] * np.sin(w), -de_col[cols] * np.cos(w))
                    ahead = np.clip(along, 0.0, None)
                    width = 0.3 * ahead
                    width += r
                    env = along / r
                    env += 1.0
                    np.clip(env, 0.0, 1.0, out=env)
                    np.negative(ahead, out=ahead)
                    ahead /= f.smoke_length_m
                    env *= np.exp(ahead, out=ahead)
                    across /= width
                    across **= 2
                    across *= -0.5
                    a = f.smoke_opacity * env
                    a *= np.exp(across, out=across)
                    opacity[box] = np.maximum(opacity[box], a.astype(np.float32))
            tex = GroundTexture(np.dstack((excess, opacity)), mpp, self.frame, (float(centre[0]), float(centre[1])))
        self._fire_cache = (radii, tex)
        return tex

    def render(self, camera: Camera, pose: CameraPose, time_s: float = 0.0, *,
               supersample: int = 2, blur_sigma_px: float = 0.5) -> np.ndarray:
        """Noise-free apparent temperature (deg C) ``(H, W)`` float32 seen at ``pose``.

        ``blur_sigma_px``: optics point-spread (Gaussian sigma, pixels).
        """
        bg = render_ground(self._background, camera, pose, background=self.ambient_c,
                           blur_sigma_px=blur_sigma_px).image
        tex = self._fire_layer(validate.finite_scalar("time_s", time_s))
        if tex is None:
            return bg
        layer = render_ground(tex, camera, pose, background=0.0, supersample=supersample,
                              blur_sigma_px=blur_sigma_px).image
        alpha = np.clip(layer[..., 1], 0.0, 1.0)
        return ((bg + layer[..., 0]) * (1.0 - alpha) + alpha * self.smoke_c).astype(np.float32)


@dataclass(frozen=True)
class ThermalSensor:
    """The camera's own imperfections. ``noise_sigma_c``: temporal noise (NETD), deg C.
    ``dead_pixel_fraction``: share of stuck pixels, half stuck at the top of the counts
    range (hot), half at zero (cold); the map is fixed by ``seed`` like a real sensor's.
    ``kelvin_per_count``: radiometric scale of the 16-bit output."""

    width: int
    height: int
    noise_sigma_c: float = 0.05
    dead_pixel_fraction: float = 2e-4
    kelvin_per_count: float = 0.01
    seed: int = 0

    @functools.cached_property
    def dead_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices of (stuck-hot, stuck-cold) pixels."""
        rng = np.random.default_rng(self.seed + 7919)
        n = int(round(self.dead_pixel_fraction * self.width * self.height))
        idx = rng.choice(self.width * self.height, size=n, replace=False)
        return idx[: n // 2 + n % 2], idx[n // 2 + n % 2:]

    @property
    def max_c(self) -> float:
        """Temperature of the largest count, deg C (stuck-hot pixels read this)."""
        return 65535 * self.kelvin_per_count - ZERO_C_IN_K

    def observe(self, celsius: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Sensor reading in deg C ``(H, W)`` float32: noise, then dead pixels."""
        img = np.asarray(celsius, np.float32)
        if img.shape != (self.height, self.width):
            raise InputError(f"celsius must be ({self.height}, {self.width}), got {img.shape}")
        out = img + rng.normal(0.0, self.noise_sigma_c, img.shape).astype(np.float32)
        hot, cold = self.dead_pixels
        out.ravel()[hot] = self.max_c
        out.ravel()[cold] = -ZERO_C_IN_K
        return out

    def to_counts(self, celsius: np.ndarray) -> np.ndarray:
        """Deg C -> uint16 radiometric counts (kelvin / kelvin_per_count, clipped)."""
        counts = np.rint((np.asarray(celsius, np.float64) + ZERO_C_IN_K) / self.kelvin_per_count)
        return np.clip(counts, 0, 65535).astype(np.uint16)


def to_display(celsius: np.ndarray, *, palette: str = "white-hot",
               span_c: tuple[float, float] | None = None) -> np.ndarray:
    """Deg C ``(H, W)`` -> 8-bit display frame: ``(H, W)`` uint8 for grey palettes,
    ``(H, W, 3)`` RGB otherwise. ``span_c`` (low, high) fixes the gain; None is
    automatic gain (0.5th to 99.99th percentile), which loses the temperature scale."""
    check_palette(palette)
    img = np.asarray(celsius, np.float32)
    if span_c is None:
        lo, hi = np.percentile(img, [0.5, 99.99])
    else:
        lo, hi = (validate.finite_scalar("span_c", v) for v in span_c)
    if not hi > lo:
        hi = lo + 1.0
    level = np.clip((img - lo) / (hi - lo) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if palette == "white-hot":
        return level
    if palette == "black-hot":
        return 255 - level
    return apply_palette(level, palette)
