"""Classical detector of a drone against sky or smooth ground, with sub-pixel moments.

Search: at each pyramid level the image minus its local box mean is divided by the
local clutter (RMS of that difference over a larger box, never below the sensor noise);
pixels beyond ``threshold_sigma`` form connected components, merged across levels.
Measurement: around each candidate a plane is fitted to a ring of background pixels;
the contrast against that plane weights the zeroth, first and second moments. Blurring
adds the PSF variance to the second moments (convolution adds variances), so the
optical PSF (``psf_sigma_px``) and the pixel footprint (1/12 px^2) are subtracted. The
noise of each moment is propagated from the sensor noise and the plane-fit error.
A candidate is kept when its integrated contrast is significant, the ring around it
is clean compared with its contrast, and it is not too large for the ring to see past.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from skyfix import validate
from skyfix.crps.detection import Detection, Roi, to_gray
from skyfix.errors import InputError

__all__ = ["SilhouetteConfig", "SilhouetteDetector", "estimate_noise_sigma"]

_PIXEL_VARIANCE = 1.0 / 12.0  # variance of the unit pixel footprint, px^2


@dataclass(frozen=True)
class SilhouetteConfig:
    """Settings of :class:`SilhouetteDetector`."""

    psf_sigma_px: float = 0.7  # camera optical blur (Gaussian 1-sigma, px), without the pixel footprint
    psf_var_sigma_px2: float = 0.1  # uncertainty of the blur variance (focus, motion blur), px^2
    threshold_sigma: float = 6.0  # per-pixel contrast / local clutter to seed a candidate
    min_snr: float = 12.0  # integrated contrast / its noise, to report a detection
    min_clutter_ratio: float = 8.0  # median target contrast / background-ring RMS
    polarity: Literal["dark", "bright", "both"] = "dark"  # target darker (drones against sky) or brighter
    box_px: int = 21  # background box at each pyramid level, px
    levels: int = 4  # pyramid levels searched (level L finds targets up to about box_px * 2^L / 2)
    min_area_px: int = 3  # seed pixels per component at its level
    ring_px: int = 3  # width of the background ring around the measurement window, px
    max_size_px: float = 400.0  # largest target extent searched, px

    def __post_init__(self) -> None:
        for name in ("psf_sigma_px", "psf_var_sigma_px2"):
            if validate.finite_scalar(name, getattr(self, name)) < 0:
                raise InputError(f"SilhouetteConfig.{name} must be >= 0")
        for name in ("threshold_sigma", "min_snr", "min_clutter_ratio", "max_size_px"):
            validate.positive_scalar(f"SilhouetteConfig.{name}", getattr(self, name))
        if self.polarity not in ("dark", "bright", "both"):
            raise InputError(f"SilhouetteConfig.polarity must be 'dark', 'bright' or 'both', got {self.polarity!r}")
        for name in ("box_px", "levels", "min_area_px", "ring_px"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise InputError(f"SilhouetteConfig.{name} must be a positive integer, got {value!r}")


def estimate_noise_sigma(gray: np.ndarray) -> float:
    """Robust sensor-noise 1-sigma of a grey image from horizontal second differences (MAD).

    Uses every 4th row; texture raises the estimate, which only makes detection stricter.
    """
    rows = gray[::4]
    d2 = rows[:, 2:] - 2.0 * rows[:, 1:-1] + rows[:, :-2]
    mad = float(np.median(np.abs(d2)))
    return max(1.4826 * mad / math.sqrt(6.0), 1e-6)


class SilhouetteDetector:
    """Find drones by local contrast and measure them by moments; a :class:`Detector`.

    Example:
        A dark disc 9 px across on a bright sky, blurred and noisy, is found at its centre:

        >>> image = np.full((240, 320), 0.8, np.float32)
        >>> _ = cv2.circle(image, (200, 100), 4, 0.2, -1)
        >>> noise = np.random.default_rng(0).normal(0.0, 0.01, image.shape).astype(np.float32)
        >>> [det] = SilhouetteDetector()(cv2.GaussianBlur(image, (0, 0), 0.7) + noise)
        >>> det.kind, bool(np.allclose(det.centroid_uv, (200.0, 100.0), atol=0.1))
        ('silhouette', True)
    """

    def __init__(self, config: SilhouetteConfig | None = None) -> None:
        self.config = config if config is not None else SilhouetteConfig()

    def __call__(self, image: np.ndarray, roi: Roi | None = None, *, time_s: float = 0.0) -> list[Detection]:
        """Detections in ``image`` (optionally only inside ``roi``), best score first."""
        gray = to_gray(image)
        h, w = gray.shape
        u0, v0, u1, v1 = (0, 0, w, h) if roi is None else _check_roi(roi, w, h)
        sub = gray[v0:v1, u0:u1]
        noise = estimate_noise_sigma(sub)
        candidates = self._candidates(sub, noise)
        out = []
        for box in candidates:
            det = self._measure(sub, box, noise, time_s)
            if det is not None:
                out.append(_shift(det, u0, v0))
        out.sort(key=lambda d: -d.score)
        return out

    # -- search -----------------------------------------------------------------------
    def _candidates(self, gray: np.ndarray, noise: float) -> list[tuple[int, int, int, int]]:
        cfg = self.config
        boxes: list[tuple[int, int, int, int]] = []
        level_img = gray
        level_noise = noise
        for level in range(cfg.levels):
            if level > 0:
                if min(level_img.shape) < 2 * cfg.box_px:
                    break
                level_img = cv2.pyrDown(level_img)
                level_noise = estimate_noise_sigma(level_img) if min(level_img.shape) > 16 else level_noise
            if cfg.box_px * 2 ** level / 2 > cfg.max_size_px * 2:
                break
            scale = 2 ** level
            diff = level_img - cv2.blur(level_img, (cfg.box_px, cfg.box_px), borderType=cv2.BORDER_REFLECT)
            clutter = cv2.blur(diff * diff, (3 * cfg.box_px, 3 * cfg.box_px), borderType=cv2.BORDER_REFLECT)
            floor = np.float32((1.5 * level_noise) ** 2)
            z = diff / np.sqrt(np.maximum(clutter, floor))
            if cfg.polarity == "dark":
                seed = z < -cfg.threshold_sigma
            elif cfg.polarity == "bright":
                seed = z > cfg.threshold_sigma
            else:
                seed = np.abs(z) > cfg.threshold_sigma
            n, _, stats, _ = cv2.connectedComponentsWithStats(seed.view(np.uint8), connectivity=8)
            for x, y, bw, bh, area in stats[1:]:
                if area < cfg.min_area_px and level == 0:
                    continue
                if area < 1:
                    continue
                boxes.append((int(x * scale), int(y * scale), int((x + bw) * scale), int((y + bh) * scale)))
        return _merge_boxes(boxes, 3, gray.shape)

    # -- measurement ------------------------------------------------------------------
    def _measure(self, gray: np.ndarray, box: tuple[int, int, int, int], noise: float,
                 time_s: float) -> Detection | None:
        cfg = self.config
        h, w = gray.shape
        bu0, bv0, bu1, bv1 = box
        size = max(bu1 - bu0, bv1 - bv0)
        if size > cfg.max_size_px:
            return None
        blur_sigma = math.sqrt(cfg.psf_sigma_px ** 2 + _PIXEL_VARIANCE)
        margin = int(math.ceil(3.0 * blur_sigma + 3 + 0.5 * size))
        u0, v0 = bu0 - margin - cfg.ring_px, bv0 - margin - cfg.ring_px
        u1, v1 = bu1 + margin + cfg.ring_px, bv1 + margin + cfg.ring_px
        if u0 < 0 or v0 < 0 or u1 > w or v1 > h:
            return None  # touches the image edge: the silhouette may be cut off
        win = gray[v0:v1, u0:u1].astype(np.float64)
        hh, ww = win.shape
        vv, uu = np.mgrid[0:hh, 0:ww]
        r = cfg.ring_px
        ring = (uu < r) | (vv < r) | (uu >= ww - r) | (vv >= hh - r)
        diff, ring_rms, ring_used = _subtract_background(win, uu, vv, ring, noise)
        # Polarity from the integrated contrast inside the seed box.
        seed = np.zeros(win.shape, bool)
        seed[bv0 - v0:bv1 - v0, bu0 - u0:bu1 - u0] = True
        sign = -1.0 if diff[seed].sum() < 0 else 1.0
        if (cfg.polarity == "dark" and sign > 0) or (cfg.polarity == "bright" and sign < 0):
            return None
        inner = _support(sign * diff, seed, ring, ring_rms, blur_sigma)
        if inner is None:
            return None
        wgt = np.where(inner, sign * diff, 0.0)
        m0 = float(wgt.sum())
        snr = m0 / (noise * math.sqrt(int(inner.sum())))
        if m0 <= 0 or snr < cfg.min_snr:
            return None
        strong = wgt > 0.5 * np.percentile(wgt[inner], 99.5)
        contrast = float(np.median(wgt[strong])) if strong.any() else 0.0
        if contrast < cfg.min_clutter_ratio * ring_rms:
            return None
        shape = _shape(wgt, inner, uu, vv, noise, ring_rms ** 2 / max(ring_used, 1), blur_sigma ** 2,
                       cfg.psf_var_sigma_px2)
        if shape is None:
            return None  # no larger than the blur: a point, not a measurable silhouette
        (cu, cv_), moments, sigma_rel, cen_cov = shape
        return Detection(np.array([cu + u0, cv_ + v0]), cen_cov, (bu0, bv0, bu1, bv1), snr, "silhouette",
                         moments_px2=moments, moments_sigma_rel=sigma_rel, time_s=time_s)


def _subtract_background(win: np.ndarray, uu: np.ndarray, vv: np.ndarray, ring: np.ndarray,
                         noise: float) -> tuple[np.ndarray, float, int]:
    """(window minus the plane fitted robustly to its ``ring`` pixels, the ring's RMS about
    the plane (at least ``noise``), the number of ring pixels the final fit used)."""
    a = np.column_stack((np.ones(int(ring.sum())), uu[ring], vv[ring]))
    vals = win[ring]
    coef, *_ = np.linalg.lstsq(a, vals, rcond=None)
    res = vals - a @ coef
    keep = np.abs(res) <= 3.0 * max(1.4826 * float(np.median(np.abs(res))), noise)
    if keep.sum() >= 10:
        coef, *_ = np.linalg.lstsq(a[keep], vals[keep], rcond=None)
        res = vals[keep] - a[keep] @ coef
    ring_rms = max(float(np.sqrt(np.mean(res ** 2))), noise)
    return win - (coef[0] + coef[1] * uu + coef[2] * vv), ring_rms, int(keep.sum())


def _support(signal: np.ndarray, seed: np.ndarray, ring: np.ndarray, ring_rms: float,
             blur_sigma: float) -> np.ndarray | None:
    """The above-noise pixels connected to the seed, grown by the blur tails (None when none,
    or when they reach the background ring). Summing moments over the support only keeps
    far-away noise out of them."""
    peak = float(signal[seed].max())
    above = (signal > max(2.5 * ring_rms, 0.03 * peak)) & ~ring
    _, labels = cv2.connectedComponents(above.view(np.uint8), connectivity=8)
    ids = np.unique(labels[seed & above])
    if ids.size == 0:
        return None
    grow = max(2, int(math.ceil(2.5 * blur_sigma)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))
    support = cv2.dilate(np.isin(labels, ids).view(np.uint8), kernel).astype(bool)
    return None if (support & ring).any() else support  # ring reached: the target does not fit


def _shape(wgt: np.ndarray, inner: np.ndarray, uu: np.ndarray, vv: np.ndarray, noise: float,
           plane_var: float, blur_var: float, psf_var_sigma_px2: float) -> tuple | None:
    """Centroid ``(u, v)``, blur-corrected second moments ``(2, 2)`` px^2, their relative
    1-sigma and the centroid covariance, from the weights ``wgt`` over ``inner``; None when
    the silhouette is no larger than the blur. ``plane_var``: variance of the background
    plane's offset (px value^2), common to every pixel."""
    m0 = float(wgt.sum())
    cu = float((wgt * uu).sum() / m0)
    cv_ = float((wgt * vv).sum() / m0)
    du, dv = (uu - cu)[inner], (vv - cv_)[inner]
    wi = wgt[inner]
    m2 = np.array([[(wi * du * du).sum(), (wi * du * dv).sum()],
                   [(wi * du * dv).sum(), (wi * dv * dv).sum()]]) / m0
    evals, evecs = np.linalg.eigh(m2)
    # Noise on the off-diagonal moment pushes the eigenvalues apart: the largest is
    # biased up by var(m12) / gap (second-order perturbation); remove that bias.
    xm = du * evecs[0, -1] + dv * evecs[1, -1]
    ym = du * evecs[0, 0] + dv * evecs[1, 0]
    var_m12 = noise ** 2 * float(((xm * ym) ** 2).sum()) / m0 ** 2
    gap = evals[-1] - evals[0]
    if gap > 0:
        shift = min(var_m12 / gap, 0.5 * gap)
        evals = evals + np.array([shift, -shift])
    if evals[-1] <= 2.0 * blur_var:
        return None
    true_evals = np.maximum(evals - blur_var, 0.05 * max(evals[-1] - blur_var, 1e-6))
    moments = (evecs * true_evals) @ evecs.T
    # Noise of the major-axis second moment: sensor noise on every pixel and the
    # plane-offset error (ring RMS / sqrt(ring pixels)) on all of them at once.
    x = du * evecs[0, -1] + dv * evecs[1, -1]
    g = x * x - evals[-1]
    var_m2 = (noise ** 2 * float((g * g).sum()) + plane_var * float(g.sum()) ** 2) / m0 ** 2
    sigma_rel = 0.5 * math.sqrt(var_m2 + psf_var_sigma_px2 ** 2) / true_evals[-1]
    cen_cov = noise ** 2 * np.array([[(du * du).sum(), (du * dv).sum()],
                                     [(du * dv).sum(), (dv * dv).sum()]]) / m0 ** 2
    return (cu, cv_), moments, sigma_rel, cen_cov + np.eye(2) * 1e-6


def _check_roi(roi: Roi, width: int, height: int) -> Roi:
    try:
        u0, v0, u1, v1 = (int(x) for x in roi)
    except (TypeError, ValueError):
        raise InputError(f"roi must be (u0, v0, u1, v1) integers, got {roi!r}") from None
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, width), min(v1, height)
    if u1 - u0 < 8 or v1 - v0 < 8:
        raise InputError(f"roi {roi!r} leaves less than 8x8 pixels inside the {width}x{height} image")
    return u0, v0, u1, v1


def _shift(det: Detection, du: int, dv: int) -> Detection:
    if du == 0 and dv == 0:
        return det
    u0, v0, u1, v1 = det.bbox_px
    return Detection(det.centroid_uv + np.array([du, dv]), det.centroid_cov_px2, (u0 + du, v0 + dv, u1 + du, v1 + dv),
                     det.score, det.kind, det.moments_px2, det.moments_sigma_rel, det.size_px,
                     det.size_sigma_px, det.marker_id, det.time_s)


def _merge_boxes(boxes: list[tuple[int, int, int, int]], gap: int,
                 shape: tuple[int, int]) -> list[tuple[int, int, int, int]]:
    """Union boxes that overlap or lie within ``gap`` pixels, transitively (via a mask)."""
    if not boxes:
        return []
    mask = np.zeros(shape, np.uint8)
    for u0, v0, u1, v1 in boxes:
        cv2.rectangle(mask, (u0 - gap, v0 - gap), (u1 - 1 + gap, v1 - 1 + gap), 1, thickness=-1)
    _, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=4)
    h, w = shape
    return [(max(int(x) + gap, 0) if x > 0 else 0, max(int(y) + gap, 0) if y > 0 else 0,
             min(int(x + bw) - gap, w) if x + bw < w else w, min(int(y + bh) - gap, h) if y + bh < h else h)
            for x, y, bw, bh, _ in stats[1:]]
