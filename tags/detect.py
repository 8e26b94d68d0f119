"""Tile-tag detection: segment tiles, classify their colours, group and decode tags.

Pipeline (all in image pixels, OpenCV convention): estimate the local paper-white level
(max filter on a downsampled brightness image) so lighting gradients cancel; tiles are
pixels darker than ``ink_threshold`` x white in some channel; connected components give
tile centroids and areas; each tile's colour is sampled at its centroid, divided by the
local white and classified to the nearest palette colour in CIELAB; tiles closer than
the tag layout allows are grouped into tags; the displaced tile fixes the orientation
and reading order; digits decode to the value.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from skyfix.tags.blur import motion_blur_half_res
from skyfix.tags.codec import TagGeometry, TileCodec
from skyfix.tags.image import as_rgb_u8
from skyfix.tags.palette import srgb_to_lab

_DOWN = 4  # white-level estimation grid, half-resolution pixels


@dataclass(frozen=True)
class TileDetections:
    """Decoded tags in one image.

    ``values`` ``(T,)``; ``tiles_px`` ``(T, n, 2)`` tile centroids (raw pixels, reading
    order); ``tile_size_px`` ``(T,)`` apparent tile side; ``colour_margin`` ``(T,)`` the
    smallest (second-nearest minus nearest) CIE76 margin over the tag's tiles;
    ``n_blobs`` candidate tiles seen; ``n_groups`` tile groups of any size;
    ``motion_blur_px`` the frame's estimated blur streak (full-resolution pixels);
    ``blobs_px`` ``(M, 2)``, ``blob_digit``, ``blob_size_px``, ``blob_in_tag``: every
    candidate tile, its colour index and whether it belongs to a decoded tag (the rest
    can still be matched to the layout once a pose is known).
    """

    values: np.ndarray
    tiles_px: np.ndarray
    tile_size_px: np.ndarray
    colour_margin: np.ndarray
    n_blobs: int
    n_groups: int
    motion_blur_px: float = 0.0
    blobs_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    blob_digit: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    blob_size_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    blob_in_tag: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


def _white_level(bright: np.ndarray, tile_px_max: float) -> np.ndarray:
    """Local paper-white level of a brightness image (max filter wider than a tile)."""
    h, w = bright.shape
    small = cv2.resize(bright, (max(1, w // _DOWN), max(1, h // _DOWN)), interpolation=cv2.INTER_AREA)
    k = 2 * int(np.ceil(tile_px_max / _DOWN)) + 1
    white = cv2.dilate(small, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    white = cv2.blur(white, (k, k))
    return cv2.resize(white, (w, h), interpolation=cv2.INTER_LINEAR)


_LUT_STEPS = 48   # reflectance quantisation of the colour table: 1/47 ~ 5 DN per channel


@functools.lru_cache(maxsize=8)
def _colour_table(palette_bytes: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Nearest palette colour (CIELAB) and its margin for every quantised reflectance;
    keyed by the palette's float64 bytes so different palettes never share a table."""
    palette_lab = srgb_to_lab(np.frombuffer(palette_bytes, dtype=np.float64).reshape(-1, 3))
    q = np.linspace(0.0, 1.0, _LUT_STEPS)
    grid = np.stack(np.meshgrid(q, q, q, indexing="ij"), axis=-1).reshape(-1, 3)
    dist = np.linalg.norm(srgb_to_lab(grid)[:, None, :] - palette_lab[None], axis=2)
    order = np.argsort(dist, axis=1)
    rows = np.arange(len(grid))
    margin = dist[rows, order[:, 1]] - dist[rows, order[:, 0]]
    return order[:, 0].astype(np.int64), margin.astype(np.float32)


def _classify(codec: TileCodec, reflectance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Palette index ``(K,)`` and CIE76 margin ``(K,)`` of reflectances ``(K, 3)`` in [0, 1]."""
    digit, margin = _colour_table(np.ascontiguousarray(codec.palette_rgb, dtype=np.float64).tobytes())
    q = np.clip(np.rint(reflectance * (_LUT_STEPS - 1)), 0, _LUT_STEPS - 1).astype(np.int64)
    flat = (q[:, 0] * _LUT_STEPS + q[:, 1]) * _LUT_STEPS + q[:, 2]
    return digit[flat], margin[flat].astype(float)


@functools.lru_cache(maxsize=32)
def _layout_links(geometry: TagGeometry) -> float:
    """Largest nearest-neighbour tile distance of the layout, in tile sides."""
    xy = geometry.tile_centres_m()
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(d.min(axis=1).max() / geometry.tile_m)


def detect_tiles(image, codec: TileCodec, geometry: TagGeometry, *, ink_threshold: float = 0.6,
                 min_tile_px: float = 4.0, max_tile_px: float = 120.0) -> TileDetections:
    """Find and decode every complete tile tag in an RGB image ``(H, W, 3)``."""
    rgb = as_rgb_u8(image)
    h, w = rgb.shape[:2]
    # Segment at half resolution (2x2 box average: exact, unbiased centroids, 4x less work).
    small = cv2.resize(rgb, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    ch = cv2.split(small)
    bright = cv2.max(cv2.max(ch[0], ch[1]), ch[2])
    darkest = cv2.min(cv2.min(ch[0], ch[1]), ch[2])
    white = _white_level(bright, max_tile_px / 2.0)
    limit = cv2.convertScaleAbs(white, alpha=ink_threshold)
    mask = cv2.compare(darkest, limit, cv2.CMP_LT)
    # Paper must be visibly brighter than ink: a flat grey frame has no white to compare with.
    mask = cv2.bitwise_and(mask, cv2.compare(white, 40, cv2.CMP_GE))
    blur = motion_blur_half_res(bright)
    # 16-bit labels suffice at half resolution (< 2^16 components) and label faster.
    n_lab, _, stats, cents = cv2.connectedComponentsWithStatsWithAlgorithm(mask, 8, cv2.CV_16U, cv2.CCL_GRANA)
    x, y, bw, bh, area = (stats[1:, i] for i in range(5))
    sh, sw = mask.shape
    ok = ((area >= (min_tile_px / 2.0) ** 2) & (area <= (max_tile_px / 2.0) ** 2) & (area >= 0.4 * bw * bh)
          & (x > 0) & (y > 0) & (x + bw < sw) & (y + bh < sh))
    empty = TileDetections(np.zeros(0, np.int64), np.zeros((0, codec.tiles, 2)), np.zeros(0),
                           np.zeros(0), int(ok.sum()), 0, blur)
    if ok.sum() < codec.tiles:
        return empty
    pts_small = cents[1:][ok]
    pts = 2.0 * pts_small + 0.5                  # half-res pixel centre -> full-res pixel
    area = 4.0 * area[ok].astype(float)
    size = np.sqrt(area)
    si = np.clip(np.round(pts_small).astype(int), 0, [sw - 1, sh - 1])
    white_at = white[si[:, 1], si[:, 0]].astype(float)

    # Colour at the centroid (the half-res pixel: a 2x2 full-res mean), relative to the local white.
    refl = small[si[:, 1], si[:, 0]].astype(float) / np.maximum(white_at, 1.0)[:, None]
    digit, margin = _classify(codec, refl)

    # Group tiles: link pairs closer than the layout's loosest neighbour distance allows.
    link = 1.2 * _layout_links(geometry)
    pairs = cKDTree(pts).query_pairs(link * float(size.max()), output_type="ndarray")
    if pairs.size:
        d = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)
        pairs = pairs[d < link * np.sqrt(0.5 * (area[pairs[:, 0]] + area[pairs[:, 1]]))]
    m = len(pts)
    group = _link_groups(m, pairs)
    n_groups = int(np.count_nonzero(group == np.arange(m)))   # each group is labelled by its root
    counts = np.bincount(group, minlength=m)
    keep = np.flatnonzero(counts == codec.tiles)
    if keep.size == 0:
        return TileDetections(empty.values, empty.tiles_px, empty.tile_size_px, empty.colour_margin,
                              m, n_groups, blur, pts, digit, size, np.zeros(m, bool))
    members = np.argsort(group, kind="stable")
    starts = np.concatenate(([0], np.cumsum(counts)))
    idx = members[starts[keep][:, None] + np.arange(codec.tiles)[None, :]]     # (T, n)
    ordered, good = _reading_order(pts[idx], geometry)
    idx = np.take_along_axis(idx, ordered, axis=1)[good]
    # Tiles of one tag share a size (perspective changes it little across a tag).
    sizes = size[idx]
    srt = np.sort(sizes, axis=1)
    med = 0.5 * (srt[:, (codec.tiles - 1) // 2] + srt[:, codec.tiles // 2])[:, None]
    same = np.all((sizes > 0.7 * med) & (sizes < 1.4 * med), axis=1)
    idx = idx[same]
    values = codec.decode(digit[idx]) if len(idx) else np.zeros(0, np.int64)
    in_tag = np.zeros(m, bool)
    in_tag[idx.ravel()] = True
    return TileDetections(values, pts[idx], size[idx].mean(axis=1) if len(idx) else np.zeros(0),
                          margin[idx].min(axis=1) if len(idx) else np.zeros(0), m, n_groups, blur,
                          pts, digit, size, in_tag)


def _link_groups(m: int, pairs: np.ndarray) -> np.ndarray:
    """Connected-component label ``(m,)`` (the smallest member index) of linked pairs."""
    label = np.arange(m)
    if pairs.size == 0:
        return label
    a, b = pairs[:, 0], pairs[:, 1]
    while True:   # groups hold a handful of tiles: a few sweeps of min-propagation converge
        low = np.minimum(label[a], label[b])
        new = label.copy()
        np.minimum.at(new, a, low)
        np.minimum.at(new, b, low)
        new = new[new]
        if np.array_equal(new, label):
            return label
        label = new


def _reading_order(tiles: np.ndarray, geometry: TagGeometry) -> tuple[np.ndarray, np.ndarray]:
    """For tile groups ``(T, n, 2)``: permutation ``(T, n)`` into reading order, and a
    validity mask ``(T,)`` (clear displaced tile, layout fits a similarity transform)."""
    layout = geometry.tile_centres_m()
    n = len(layout)
    zl = layout[:, 0] - 1j * layout[:, 1]            # image-like: y down
    zi = tiles[..., 0] + 1j * tiles[..., 1]          # (T, n)
    total = zi.sum(axis=1, keepdims=True)
    others = (total - zi) / (n - 1)
    spread = np.abs(zi - others)                     # distance of each tile from the others' mean
    disp = np.argmax(spread, axis=1)
    srt = np.sort(spread, axis=1)
    l_spread = np.abs(zl - (zl.sum() - zl) / (n - 1))
    expected = l_spread[0] / np.sort(l_spread)[-2]
    clear = srt[:, -1] / np.maximum(srt[:, -2], 1e-9) > 1.0 + 0.4 * (expected - 1.0)
    rows = np.arange(len(zi))
    a = zi[rows, disp] - others[rows, disp]
    b = zl[0] - (zl.sum() - zl[0]) / (n - 1)
    s = a / b                                         # similarity: layout -> image
    pred = others[rows, disp][:, None] + (zl[None, :] - (zl.sum() - zl[0]) / (n - 1)) * s[:, None]
    d = np.abs(pred[:, :, None] - zi[:, None, :])     # (T, slot, detected)
    perm = np.argmin(d, axis=2)
    unique = np.all(np.diff(np.sort(perm, axis=1), axis=1) > 0, axis=1)
    resid = np.take_along_axis(d, perm[..., None], 2)[..., 0].max(axis=1)
    fits = resid < 0.3 * np.abs(s) * geometry.pitch_m
    return perm, clear & unique & fits
