"""Hotspot detection in thermal frames: threshold, connected components, sub-pixel centroid.

Accepted frames (``(H, W)`` unless stated):

- float (16/32/64-bit): temperatures in degrees Celsius; NaN pixels are no-data.
- uint16: radiometric counts; kelvin = counts * ``kelvin_per_count`` (default 0.01 K).
- uint8: an 8-bit display frame in ``palette`` "white-hot" or "black-hot".
- uint8 ``(H, W, 3)``: an RGB display frame in any palette ("ironbow", "arctic", ...).

Radiometric frames (float, uint16) are thresholded in degrees Celsius. 8-bit frames
have lost their temperature scale (palette, automatic gain): detection is relative,
with an automatic threshold unless one is given in 8-bit levels, and a
:class:`RelativeTemperatureWarning` is issued.

A hotspot is a connected component (8-connectivity) of pixels above the threshold
with at least ``min_area_px`` such pixels; isolated hot or dead pixels and pairs of
them never qualify. Each component is median-filtered (3x3) within its bounding box
before its centroid is taken, so a stuck pixel touching a fire does not pull it; the
reported peak is the hottest pixel not hotter than its hottest neighbour. The
centroid is weighted by the excess over the threshold, which makes it vary
continuously as the fire moves across pixels (sub-pixel accuracy).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from skyfix import validate
from skyfix.errors import InputError
from skyfix.thermal.palettes import GREY_PALETTES, check_palette, palette_to_intensity

#: Default threshold for radiometric frames, degrees Celsius. Open flame and embers read
#: 300-1000 C; sun-heated rock and roofs stay below ~70 C.
DEFAULT_THRESHOLD_C = 100.0
#: Default radiometric scale of uint16 frames (FLIR Boson/Lepton TLinear high-resolution).
DEFAULT_KELVIN_PER_COUNT = 0.01
#: Automatic 8-bit threshold: at least this many robust sigmas and levels above the median.
AUTO_SIGMAS = 8.0
AUTO_MIN_CONTRAST_LEVELS = 40.0

_ZERO_C_IN_K = 273.15


class RelativeTemperatureWarning(UserWarning):
    """Detection ran on a frame without a temperature scale (8-bit / palette)."""


@dataclass(frozen=True)
class Hotspot:
    """One detected hotspot in OpenCV pixel coordinates.

    ``u_px, v_px``: excess-weighted centroid (sub-pixel). ``area_px``: pixels above the
    threshold. ``peak``/``threshold``: in ``units`` ("celsius" for radiometric frames,
    "level" for 8-bit relative intensity 0-255, white-hot sense). ``bbox_px``: (u0, v0,
    width, height) of the component.
    """

    u_px: float
    v_px: float
    area_px: int
    peak: float
    threshold: float
    bbox_px: tuple[int, int, int, int]
    units: str

    @property
    def uv(self) -> np.ndarray:
        """Centroid as a ``(2,)`` float array (u, v) in pixels."""
        return np.array([self.u_px, self.v_px])

    @property
    def radiometric(self) -> bool:
        """True when ``peak``/``threshold`` are temperatures in degrees Celsius."""
        return self.units == "celsius"


def _check_frame(frame: np.ndarray) -> np.ndarray:
    if not isinstance(frame, np.ndarray):
        raise InputError(f"frame must be a numpy array, got {type(frame).__name__}")
    if frame.size == 0:
        raise InputError(f"frame is empty (shape {frame.shape})")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[..., 0]
    if frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
        raise InputError(f"frame must be (H, W) or (H, W, 3), got shape {frame.shape}")
    if frame.shape[0] < 3 or frame.shape[1] < 3:
        raise InputError(f"frame must be at least 3x3 pixels, got shape {frame.shape}")
    return frame


def _to_work(frame: np.ndarray, palette: str, threshold: float | None, kelvin_per_count: float
             ) -> tuple[np.ndarray, float | None, str, float]:
    """(2-D work image, threshold in work units or None=auto, units, scale work->units).

    Work values map to reported units as ``value * scale + offset`` where the offset is
    only non-zero for counts (see :func:`_report`).
    """
    kind = frame.dtype
    if frame.ndim == 3:
        if kind != np.uint8:
            raise InputError(f"3-channel frames must be uint8 RGB palette images, got dtype {kind}")
        check_palette(palette)
        if palette in GREY_PALETTES:
            work = np.ascontiguousarray(frame[..., 0])
        else:
            work = palette_to_intensity(frame, palette)
        if palette == "black-hot":
            work = 255 - work
        return work, threshold, "level", 1.0
    if kind == np.uint8:
        check_palette(palette)
        if palette not in GREY_PALETTES:
            raise InputError(f"a single-channel uint8 frame must be 'white-hot' or 'black-hot', "
                             f"got palette {palette!r}; colour palettes need (H, W, 3) RGB")
        work = 255 - frame if palette == "black-hot" else frame
        return work, threshold, "level", 1.0
    thr_c = DEFAULT_THRESHOLD_C if threshold is None else validate.finite_scalar("threshold", threshold)
    if kind == np.uint16:
        thr_counts = (thr_c + _ZERO_C_IN_K) / kelvin_per_count
        return frame, thr_counts, "counts", kelvin_per_count
    if np.issubdtype(kind, np.floating):
        work = frame if kind in (np.float32, np.float64) else frame.astype(np.float32)
        return work, thr_c, "celsius", 1.0
    raise InputError(f"frame dtype must be float (deg C), uint16 (counts) or uint8 (8-bit display), "
                     f"got {kind}")


_LEVELS = np.arange(256, dtype=np.float64)
_ABS_DEV = np.abs(np.arange(256)[:, None] - np.arange(256)[None, :])  # [median, level] -> |level - median|


def auto_threshold_u8(work: np.ndarray) -> float:
    """Automatic threshold (8-bit levels) for a frame without temperature scale.

    The larger of Otsu's threshold and ``median + max(AUTO_SIGMAS * robust sigma,
    AUTO_MIN_CONTRAST_LEVELS)``, robust sigma = 1.4826 * median absolute deviation:
    a fire-free frame's own texture then never crosses it.
    """
    # Every 4th row and column (20k of 330k pixels at 640x512): plenty for a median and MAD.
    hist = cv2.calcHist([np.ascontiguousarray(work[::4, ::4])], [0], None, [256], [0, 256])
    hist = hist.ravel().astype(np.float64)
    cdf = np.cumsum(hist)
    total = cdf[-1]
    median = int(np.searchsorted(cdf, total / 2.0))
    dev_hist = np.bincount(_ABS_DEV[median], weights=hist, minlength=256)
    mad = float(np.searchsorted(np.cumsum(dev_hist), total / 2.0))
    sigma = max(1.4826 * mad, 1.0)
    # Otsu on the histogram: maximise the between-class variance over split levels.
    w0 = cdf / total
    mu = np.cumsum(hist * _LEVELS) / total
    denom = w0 * (1.0 - w0)
    valid = denom > 1e-12
    otsu = float(median)
    if valid.any():
        between = np.where(valid, (mu[-1] * w0 - mu) ** 2 / np.where(valid, denom, 1.0), -1.0)
        otsu = float(np.argmax(between)) + 0.5
    return max(otsu, median + max(AUTO_SIGMAS * sigma, AUTO_MIN_CONTRAST_LEVELS))


def detect_hotspots(frame: np.ndarray, *, threshold: float | None = None, palette: str = "white-hot",
                    min_area_px: int = 4, kelvin_per_count: float = DEFAULT_KELVIN_PER_COUNT
                    ) -> list[Hotspot]:
    """Detect hotspots in one thermal frame (see the module docstring for frame kinds).

    ``threshold``: degrees Celsius for radiometric frames (default
    :data:`DEFAULT_THRESHOLD_C`); 8-bit levels (white-hot sense) for 8-bit frames,
    automatic (:func:`auto_threshold_u8`) when None. ``min_area_px``: minimum number of
    pixels above the threshold (>= 2). Returns hotspots sorted by decreasing area.
    Raises :class:`InputError` for a wrong dtype/shape, an empty, all-NaN or constant
    frame.

    Example:
        A radiometric frame in deg C: 20 deg C ground and a 300 deg C fire 4 x 4 px; the
        default threshold is 100 deg C:

        >>> frame = np.full((120, 160), 20.0, np.float32)
        >>> frame[40:44, 100:104] = 300.0
        >>> [fire] = detect_hotspots(frame)
        >>> fire.u_px, fire.v_px, fire.peak, fire.units
        (101.5, 41.5, 300.0, 'celsius')
    """
    frame = _check_frame(frame)
    min_area_px = validate.integer_in("min_area_px", min_area_px, 2)  # a single pixel is never a fire
    kpc = validate.positive_scalar("kelvin_per_count", kelvin_per_count)
    work, thr, units, scale = _to_work(frame, palette, threshold, kpc)
    if units == "level":
        warnings.warn("8-bit/palette frame: no temperature scale, detection is relative "
                      "(use radiometric counts or deg C frames for absolute thresholds)",
                      RelativeTemperatureWarning, stacklevel=2)
        thr = auto_threshold_u8(work) if thr is None else validate.finite_scalar("threshold", thr)
    # work > thr as uint8, non-zero where hot (NaN is not), by whichever is faster for the dtype.
    if work.dtype == np.uint16:  # 0/255; OpenCV compares integers with a fractional threshold exactly
        mask = cv2.compare(work, thr, cv2.CMP_GT)
    else:
        mask = (work > thr).view(np.uint8)
    regions = _candidate_regions(mask, min_area_px)
    # A frame hot everywhere is one window over all of it.
    if not regions or (regions[0] == (0, mask.shape[0], 0, mask.shape[1]) and cv2.countNonZero(mask) == mask.size):
        # Only frames with nothing (or everything) hot can be blank: check them fully.
        lo, hi, _, _ = cv2.minMaxLoc(work)
        if math.isnan(lo) or math.isnan(hi):
            raise InputError("frame has no valid pixel (all NaN)")
        if lo == hi:
            raise InputError(f"frame is constant ({lo!r} everywhere): dropped, frozen or blank frame")
    out = []
    for r0, r1, c0, c1 in regions:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask[r0:r1, c0:c1], connectivity=8, ltype=cv2.CV_32S)
        labels = cv2.copyMakeBorder(labels, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)  # a component's padded box fits
        for k in range(1, n):
            if stats[k, cv2.CC_STAT_AREA] < min_area_px:
                continue
            spot = _measure(work, labels, stats[k], k, thr, min_area_px, r0, c0)
            if spot is not None:
                out.append(spot)
    out.sort(key=lambda s: -s[2])
    return [_report(s, units, scale, thr) for s in out]


_BLOCK_PX = 16
_RING = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], np.uint8)  # the 8 neighbours of a pixel


def _candidate_regions(mask: np.ndarray, min_area_px: int) -> list[tuple[int, int, int, int]]:
    """Pixel windows (r0, r1, c0, c1) around groups of touching 16x16 blocks that hold at
    least ``min_area_px`` hot pixels; scanning only these keeps sparse frames fast.
    ``mask`` is uint8, non-zero where hot."""
    b = _BLOCK_PX
    h, w = mask.shape
    nbr, nbc = -(-h // b), -(-w // b)
    padded = mask
    if nbr * b != h or nbc * b != w:
        padded = cv2.copyMakeBorder(mask, 0, nbr * b - h, 0, nbc * b - w, cv2.BORDER_CONSTANT, value=0)
    padded = np.ascontiguousarray(padded)
    # Read the mask 8 bytes at a time: a block is occupied when any of its words is non-zero.
    words = b * padded.itemsize // 8
    word_max = padded.view(np.uint64).reshape(nbr, b, nbc, words).max(axis=1)
    occupied = word_max[..., 0] != 0
    for k in range(1, words):  # or-ing word by word: numpy reduces a short last axis slowly
        occupied |= word_max[..., k] != 0
    _, _, stats, _ = cv2.connectedComponentsWithStats(occupied.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    stats = stats[1:]
    # A lone block can hold only stray pixels (dead pixels): count its pixels, all lone
    # blocks of the frame at once (a mountain frame holds dozens of them).
    lone = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] == 1)
    if lone.size:
        blocks = padded.reshape(nbr, b, nbc, b)[stats[lone, 1], :, stats[lone, 0], :]
        stray = (blocks.reshape(lone.size, b * b) != 0).sum(axis=1) < min_area_px
        kept = np.ones(stats.shape[0], bool)
        kept[lone[stray]] = False
        stats = stats[kept]
    return [(r0 * b, min((r0 + rh) * b, h), c0 * b, min((c0 + cw) * b, w)) for c0, r0, cw, rh, _ in stats.tolist()]


def _measure(work: np.ndarray, labels: np.ndarray, stat: np.ndarray, k: int, thr: float,
             min_area_px: int, r_off: int, c_off: int) -> tuple | None:
    """Centroid of component ``k`` after a 3x3 median within its (padded) bounding box.

    ``labels`` covers the window starting at row ``r_off``, column ``c_off`` of ``work``,
    with a one-pixel border of zeros.
    """
    u0, v0, w, h = stat[:4].tolist()
    u0, v0 = u0 + c_off, v0 + r_off
    hgt, wid = work.shape
    a0, b0 = max(u0 - 1, 0), max(v0 - 1, 0)
    a1, b1 = min(u0 + w + 1, wid), min(v0 + h + 1, hgt)
    patch = work[b0:b1, a0:a1]
    if patch.dtype.kind == "f":
        patch = patch.astype(np.float32)  # a copy: NaNs are patched in place below
        cv2.patchNaNs(patch, float(thr))
    mine = labels[b0 - r_off + 1:b1 - r_off + 1, a0 - c_off + 1:a1 - c_off + 1] == k
    excess = np.where(mine, np.subtract(cv2.medianBlur(patch, 3), np.float32(thr), dtype=np.float32), np.float32(0.0))
    np.maximum(excess, 0.0, out=excess)
    area = cv2.countNonZero(excess)
    if area < min_area_px:
        return None
    m = cv2.moments(excess)
    u = a0 + m["m10"] / m["m00"]
    v = b0 + m["m01"] / m["m00"]
    # Peak: a pixel's excess may be at most twice its hottest neighbour's, so a stuck
    # pixel on the edge of a fire cannot be its peak while a real peak stays intact.
    neighbour = cv2.dilate(patch, _RING)[mine].astype(np.float64)
    peak = float(np.minimum(patch[mine].astype(np.float64), 2.0 * neighbour - thr).max())
    return u, v, area, peak, (u0, v0, w, h)


def _report(s: tuple, units: str, scale: float, thr: float) -> Hotspot:
    u, v, area, peak, bbox = s
    if units == "counts":
        return Hotspot(u, v, area, peak * scale - _ZERO_C_IN_K, thr * scale - _ZERO_C_IN_K, bbox, "celsius")
    return Hotspot(u, v, area, peak, thr, bbox, units)
