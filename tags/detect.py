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
from skyfix.tags.palette import srgb_grid_to_lab, srgb_to_lab

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
_CHANNEL_STRIDES = np.array([_LUT_STEPS * _LUT_STEPS, _LUT_STEPS, 1], dtype=np.intp)


@functools.lru_cache(maxsize=8)
def _colour_table(palette_bytes: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Nearest palette colour (CIELAB) and its margin for every quantised reflectance;
    keyed by the palette's float64 bytes so different palettes never share a table.

    Built once per palette (~110k entries): one palette colour at a time, keeping the
    nearest and second-nearest distance, so no (entries x colours x 3) temporaries."""
    palette_lab = srgb_to_lab(np.frombuffer(palette_bytes, dtype=np.float64).reshape(-1, 3))
    lab = srgb_grid_to_lab(np.linspace(0.0, 1.0, _LUT_STEPS)).reshape(-1, 3)
    l_, a_, b_ = lab[:, 0].copy(), lab[:, 1].copy(), lab[:, 2].copy()
    best = np.full(len(lab), np.inf)
    second = np.full(len(lab), np.inf)
    digit = np.zeros(len(lab), np.uint8)
    for i, (pl, pa, pb) in enumerate(palette_lab):
        d = np.sqrt((l_ - pl) ** 2 + (a_ - pa) ** 2 + (b_ - pb) ** 2)
        closer = d < best
        second = np.where(closer, best, np.minimum(second, d))
        best = np.where(closer, d, best)
        digit[closer] = i
    # Small dtypes: the tables are read at random, and a cold cache pays per line touched.
    return digit, (second - best).astype(np.float32)


@functools.lru_cache(maxsize=1)
def _quantised_reflectance() -> np.ndarray:
    """``table[ink, white]``: the colour-table step ``rint(47 * ink / max(white, 1))``
    (clipped) of a uint8 channel value relative to a uint8 white level."""
    ink = np.arange(256, dtype=float)[:, None]
    white = np.maximum(np.arange(256, dtype=float), 1.0)[None, :]
    q = np.clip(np.rint(ink / white * (_LUT_STEPS - 1)), 0, _LUT_STEPS - 1).astype(np.uint8)
    q.setflags(write=False)
    return q


def _classify_u8(codec: TileCodec, rgb: np.ndarray, white: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Palette index ``(K,)`` and CIE76 margin ``(K,)`` of uint8 colours ``(K, 3)``
    relative to the uint8 local white levels ``(K,)`` (reflectance = colour / white)."""
    digit, margin = _colour_table(np.ascontiguousarray(codec.palette_rgb, dtype=np.float64).tobytes())
    q = _quantised_reflectance()[rgb, white[:, None]] @ _CHANNEL_STRIDES
    return digit[q].astype(np.int64), margin[q].astype(float)


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
    st = stats[1:]
    x, y, bw, bh, area = st.T
    sh, sw = mask.shape
    ok = ((area >= (min_tile_px / 2.0) ** 2) & (area <= (max_tile_px / 2.0) ** 2) & (area >= 0.4 * bw * bh)
          & (np.minimum(x, y) > 0) & (x + bw < sw) & (y + bh < sh))
    n_ok = int(np.count_nonzero(ok))
    if n_ok < codec.tiles:
        return _empty(codec, n_ok, 0, blur)
    pts_small = cents[1:][ok]
    pts = 2.0 * pts_small + 0.5                  # half-res pixel centre -> full-res pixel
    area = 4.0 * area[ok]
    size = np.sqrt(area)
    # Centroids lie inside their (border-free) bounding boxes: no clipping needed.
    si = np.rint(pts_small).astype(np.intp)
    row, col = si[:, 1], si[:, 0]

    # Colour at the centroid (the half-res pixel: a 2x2 full-res mean), relative to the local white.
    digit, margin = _classify_u8(codec, small[row, col], white[row, col])

    # Group tiles: link pairs closer than the layout's loosest neighbour distance allows.
    link = 1.2 * _layout_links(geometry)
    pairs = cKDTree(pts, balanced_tree=False, compact_nodes=False).query_pairs(
        link * float(size.max()), output_type="ndarray")
    if pairs.size:
        a, b = pairs[:, 0], pairs[:, 1]
        dxy = pts[a] - pts[b]
        pairs = pairs[np.einsum("ij,ij->i", dxy, dxy) < (0.5 * link * link) * (area[a] + area[b])]
    m = len(pts)
    group = _link_groups(m, pairs)
    counts = np.bincount(group, minlength=m)
    n_groups = int(np.count_nonzero(counts))   # each group is labelled by its root
    keep = np.flatnonzero(counts == codec.tiles)
    if keep.size == 0:
        return _empty(codec, m, n_groups, blur, pts, digit, size)
    members = np.argsort(group, kind="stable")
    starts = np.cumsum(counts) - counts
    idx = members[starts[keep][:, None] + np.arange(codec.tiles)]     # (T, n)
    ordered, good = _reading_order(pts[idx], geometry)
    idx = np.take_along_axis(idx, ordered, axis=1)[good]
    # Tiles of one tag share a size (perspective changes it little across a tag).
    sizes = size[idx]
    srt = np.sort(sizes, axis=1)
    med = 0.5 * (srt[:, (codec.tiles - 1) // 2] + srt[:, codec.tiles // 2])[:, None]
    same = ((sizes > 0.7 * med) & (sizes < 1.4 * med)).all(axis=1)
    idx = idx[same]
    if len(idx) == 0:
        return _empty(codec, m, n_groups, blur, pts, digit, size)
    values = codec.decode(digit[idx])
    in_tag = np.zeros(m, bool)
    in_tag[idx.ravel()] = True
    return TileDetections(values, pts[idx], size[idx].mean(axis=1), margin[idx].min(axis=1), m, n_groups, blur,
                          pts, digit, size, in_tag)


def _empty(codec: TileCodec, n_blobs: int, n_groups: int, blur: float, pts: np.ndarray | None = None,
           digit: np.ndarray | None = None, size: np.ndarray | None = None) -> TileDetections:
    """Detections without a decoded tag (the loose candidate tiles kept when given)."""
    none = TileDetections(np.zeros(0, np.int64), np.zeros((0, codec.tiles, 2)), np.zeros(0), np.zeros(0),
                          n_blobs, n_groups, blur)
    if pts is None:
        return none
    return TileDetections(none.values, none.tiles_px, none.tile_size_px, none.colour_margin, n_blobs, n_groups,
                          blur, pts, digit, size, np.zeros(len(pts), bool))


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


@functools.lru_cache(maxsize=32)
def _layout_complex(geometry: TagGeometry) -> tuple[np.ndarray, float, complex, np.ndarray]:
    """Per-layout constants of :func:`_reading_order`: tile centres as complex numbers
    (y down), the expected spread ratio of the displaced tile, the displaced tile's offset
    from the others' mean, and every slot's offset from that mean."""
    layout = geometry.tile_centres_m()
    n = len(layout)
    zl = layout[:, 0] - 1j * layout[:, 1]            # image-like: y down
    l_spread = np.abs(zl - (zl.sum() - zl) / (n - 1))
    expected = float(l_spread[0] / np.sort(l_spread)[-2])
    rest = (zl.sum() - zl[0]) / (n - 1)
    return zl, expected, complex(zl[0] - rest), zl - rest


def _reading_order(tiles: np.ndarray, geometry: TagGeometry) -> tuple[np.ndarray, np.ndarray]:
    """For tile groups ``(T, n, 2)``: permutation ``(T, n)`` into reading order, and a
    validity mask ``(T,)`` (clear displaced tile, layout fits a similarity transform)."""
    _, expected, b, slots = _layout_complex(geometry)
    n = len(slots)
    zi = tiles @ np.array([1.0, 1j])                 # (T, n) complex
    others = (zi.sum(axis=1, keepdims=True) - zi) / (n - 1)
    spread = np.abs(zi - others)                     # distance of each tile from the others' mean
    disp = np.argmax(spread, axis=1)
    srt = np.sort(spread, axis=1)
    clear = srt[:, -1] > (1.0 + 0.4 * (expected - 1.0)) * np.maximum(srt[:, -2], 1e-9)
    rows = np.arange(len(zi))
    o_disp = others[rows, disp]
    s = (zi[rows, disp] - o_disp) / b                 # similarity: layout -> image
    pred = o_disp[:, None] + slots * s[:, None]
    d = np.abs(pred[:, :, None] - zi[:, None, :])     # (T, slot, detected)
    perm = np.argmin(d, axis=2)
    # Each detected tile in exactly one slot; the worst slot's distance is the fit residual.
    unique = np.bitwise_or.reduce(1 << perm, axis=1) == (1 << n) - 1
    fits = d.min(axis=2).max(axis=1) < 0.3 * geometry.pitch_m * np.abs(s)
    return perm, clear & unique & fits
