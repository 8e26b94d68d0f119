"""Dense surface: OpenCV semi-global matching on rectified pairs of overlapping photos.

Each registered photo is paired with up to ``neighbours`` (6) others of the same model that
see at least one of its 3x3 footprint lattice points, with a useful baseline (0.08-1.5 of
the flying height: along the line and across to the next; on Seneca 1.2-1.5 adds nine
cross-line pairs, the only pairs over some ground only two photos see), and then any
pair whose footprints overlap on ground no chosen pair covers (at least 0.5 % of a
footprint: corners of photos on neighbouring lines, which the lattice misses; see
:mod:`skyfix.mapping.dense_pairs`). A pair is rectified with one
common rotation whose x axis is the baseline (both views turned to look alike, so epipolar
lines are image rows and the left camera is the first), undistorted through its lens
model, matched by ``cv2.StereoSGBM`` (left-right consistency, uniqueness and speckle
filters on) within the disparity range the sparse points both photos see allow (the left
photo's canvas starts that range's minimum to the right of the right photo's, so SGBM
searches from 0 and a wide-baseline corner overlap is not lost in its minimum-disparity
band), and triangulated:
depth = f * baseline / disparity. Photos are matched at ``scale`` of their size, so a
disparity pixel is 1/scale photo pixels. SGBM gives no disparity in the left canvas's
first numDisparities columns, the start of the overlap; that band is matched again with
the pair mirrored (the right photo, flipped, as the left one) and its cells join the
surface only through the fill rules (:mod:`skyfix.mapping.dense_fill`). Pixels SGBM leaves
empty on the contrast-equalised photos are matched again, same matcher and filters, on
locally normalised ones (:func:`local_contrast`: each neighbourhood less its mean, over its
standard deviation, as normalised cross-correlation sees it): on Seneca the dark, faint soil
of the photos' lower-texture fields matches there (``benchmarks/mapping.py``: DSM measured
94.2 -> 95.6 % of Seneca; ``benchmarks/mapping_dsm_truth.py``: the rendered survey's first
pass 88.3 % either way, its cells 0.060 m off the truth median, 0.17 m for 90 %).

Every pair's points land in the DSM grid in metres; each cell takes the median height of
all its points from all pairs, spikes (a cell more than ``spike_m`` off its 5x5 median)
and isolated cells are dropped, a pair whose heights sit metres off the other pairs' (a
wrong relative pose, or repetitive crop rows matched one period off) is left out, and only cells seen by at least ``min_pairs`` pairs are kept; holes are
filled from a coarser level for ``filled_m`` (the orthophoto's surface) and stay NaN in
``surface_m``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from skyfix.errors import DataError
from skyfix.mapping.dense_fill import fill_from, fill_holes, without_spikes
from skyfix.mapping.dense_pairs import camera_centre as _centre
from skyfix.mapping.dense_pairs import stereo_pairs
from skyfix.mapping.dsm import Dsm, cell_median, cell_medians
from skyfix.mapping.grid import EnuToUtm, Grid
from skyfix.mapping.ortho import View
from skyfix.progress import progress

__all__ = ["DenseCloud", "dense_dsm", "footprint_masks", "opencv_lens", "pair_offsets_m", "stereo_area",
           "stereo_pairs"]

log = logging.getLogger(__name__)

_OPENCV_LENS = {  # pycolmap model -> (indices of fx, fy, cx, cy), indices of OpenCV distortion coefficients
    "SIMPLE_PINHOLE": ((0, 0, 1, 2), ()), "PINHOLE": ((0, 1, 2, 3), ()),
    "SIMPLE_RADIAL": ((0, 0, 1, 2), (3,)), "RADIAL": ((0, 0, 1, 2), (3, 4)),
    "OPENCV": ((0, 1, 2, 3), (4, 5, 6, 7)), "FULL_OPENCV": ((0, 1, 2, 3), (4, 5, 6, 7, 8, 9, 10, 11)),
}


def opencv_lens(camera, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray] | None:
    """(K, distortion) in OpenCV's pixel convention of a ``pycolmap.Camera`` seen at
    ``scale`` of its size, or None for models OpenCV's pinhole undistortion lacks."""
    entry = _OPENCV_LENS.get(camera.model.name)
    if entry is None:
        return None
    p = np.asarray(camera.params, dtype=np.float64)
    (ifx, ify, icx, icy), idist = entry
    k = np.array([[p[ifx] * scale, 0.0, p[icx] * scale - 0.5], [0.0, p[ify] * scale, p[icy] * scale - 0.5],
                  [0.0, 0.0, 1.0]])
    dist = np.zeros(8 if len(idist) > 4 else 4)
    dist[:len(idist)] = p[list(idist)]
    if len(idist) == 2:  # RADIAL: k1, k2 then p1 = p2 = 0
        dist[:2] = p[list(idist)]
    return k, dist


@dataclass(frozen=True)
class DenseCloud:
    """Fused dense points: ``xyz_utm_m`` (N, 3) easting, northing, height; ``rgb`` (N, 3) uint8;
    ``pairs`` matched and used; ``scale`` of the photos matched; ``dropped`` pairs (names and
    height offset) whose heights disagreed with the others'; ``candidates``: the pairs of
    view indices that were tried (:func:`stereo_pairs`); ``fills``: per coarser pass, its scale,
    the cells it added and, where a finer pass measured the same cell, their median and
    90th-percentile absolute height difference (m)."""

    xyz_utm_m: np.ndarray
    rgb: np.ndarray
    pairs: int
    scale: float
    dropped: tuple[str, ...] = ()
    candidates: tuple[tuple[int, int], ...] = ()
    fills: tuple[dict, ...] = ()


def _rectification(left: View, right: View) -> tuple[np.ndarray, float]:
    """World(ENU)->rectified rotation with x along the baseline, and the baseline (m)."""
    base = _centre(right) - _centre(left)
    baseline = float(np.linalg.norm(base))
    x = base / baseline
    z_mean = left.cam_from_enu[2, :3] + right.cam_from_enu[2, :3]
    y = np.cross(z_mean, x)
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    return np.stack((x, y, z)), baseline


def _pair_canvas(left: View, right: View, images: dict, sparse_enu: np.ndarray, scale: float,
                 block_px: int) -> tuple | None:
    """Rectified canvas of one pair at ``scale``: (lenses, rotation, f_px, baseline_m, x0, y0,
    min_disp, num_disp, size), or None (lens model, disparity range or degenerate geometry)."""
    lens_l, lens_r = opencv_lens(left.camera, scale), opencv_lens(right.camera, scale)
    if lens_l is None or lens_r is None:
        return None
    r_rect, baseline = _rectification(left, right)
    f = 0.5 * (lens_l[0][0, 0] + lens_r[0][0, 0])
    # Rectified frame of the left camera: sparse depths bound the disparities.
    pts = (sparse_enu - _centre(left)) @ r_rect.T
    corners = []
    for view, (k, _) in ((left, lens_l), (right, lens_r)):
        w, h = view.camera.width * scale, view.camera.height * scale
        uv = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], dtype=np.float64)
        rays = (np.linalg.inv(k) @ uv.T).T @ (r_rect @ view.cam_from_enu[:, :3].T).T
        corners.append(rays[:, :2] / rays[:, 2:3] * f)
    xy = np.vstack(corners)
    in_view = pts[:, 2] > 0
    pts = pts[in_view]
    u = pts[:, 0] / pts[:, 2] * f
    v = pts[:, 1] / pts[:, 2] * f
    left_box = corners[0]
    inside = (u > left_box[:, 0].min()) & (u < left_box[:, 0].max()) & (v > left_box[:, 1].min()) & \
        (v < left_box[:, 1].max())
    if inside.sum() < 20:
        return None
    right_box = corners[1]  # the right camera sits baseline metres along the rectified x axis
    u_right = u - f * baseline / pts[:, 2]
    in_both = inside & (u_right > right_box[:, 0].min()) & (u_right < right_box[:, 0].max())
    if in_both.sum() >= 20:  # the overlap's own depths: a corner overlap needs no range for the whole photo
        inside = in_both
    # Robust depth bounds: the 2-98 % of the sparse points in view, widened by 5 % (and
    # never beyond 0.6-1.6x their median: a stray sparse point must not open the range).
    # SGBM leaves the overlap's first numDisparities columns without a disparity, so a
    # narrower range measures more of the ground only two photos see (Seneca, 10 % -> 5 %:
    # 92.9 -> 93.75 % in a DSM-only re-run).
    near_m, far_m = np.percentile(pts[inside, 2], [2, 98])
    median_m = float(np.median(pts[inside, 2]))
    near_m, far_m = max(0.95 * near_m, 0.6 * median_m), min(1.05 * far_m, 1.6 * median_m)
    d_lo, d_hi = f * baseline / far_m, f * baseline / near_m
    min_disp = int(np.floor(d_lo))
    num_disp = int(np.ceil((d_hi - min_disp) / 16.0) * 16)
    if num_disp > 512:
        return None
    x0, y0 = np.floor(xy.min(axis=0)).astype(int)
    x1, y1 = np.ceil(xy.max(axis=0)).astype(int)
    # The left photo's canvas starts min_disp columns right of the right photo's (its columns
    # before that have no match at any disparity in range), so SGBM searches 0..num_disp.
    size = (int(x1 - x0 - min_disp), int(y1 - y0))
    if min_disp < 0 or num_disp + block_px >= size[0] or size[0] * size[1] > 16 * len(images[left.name][0]) \
            * images[left.name][0].shape[1]:
        return None  # overlap too small for the disparities, or a degenerate rectification
    return (lens_l, lens_r), r_rect, f, baseline, x0, y0, min_disp, num_disp, size


def _disparity(sgbm, pair: list[np.ndarray], num_disp: int, inside: np.ndarray) -> np.ndarray:
    """(H, W) float32 disparity (canvas pixels) of a rectified ``pair`` by ``sgbm``, NaN where
    none: outside the left canvas's photo (``inside`` False) and at the ends of the searched
    range (matches that wanted to go further)."""
    disparity = sgbm.compute(pair[0], pair[1]).astype(np.float32) / 16.0
    disparity[~((disparity > 0.5) & (disparity < num_disp - 1.5) & inside)] = np.nan
    return disparity


def local_contrast(lightness: np.ndarray, window_px: int) -> np.ndarray:
    """(H, W) uint8: ``lightness`` (uint8) less its mean over ``window_px`` x ``window_px`` and
    divided by its standard deviation there (plus 2 grey levels, about the photos' noise,
    so that flat ground is not amplified to pure noise), 40 grey levels per standard deviation
    around 128: every neighbourhood gets the same contrast, as normalised cross-correlation
    sees it, so faint texture on dark or bright ground matches like textured ground."""
    x = lightness.astype(np.float32)
    mean = cv2.blur(x, (window_px, window_px))
    std = np.sqrt(np.maximum(cv2.blur(x * x, (window_px, window_px)) - mean * mean, 0.0))
    return np.clip((x - mean) / (std + 2.0) * 40.0 + 128.0, 0, 255).astype(np.uint8)


def _match_pair(left: View, right: View, images: dict, sparse_enu: np.ndarray, scale: float,
                block_px: int, band: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 3) ENU points and (N, 3) BGR colours from one pair, or None. ``images``: name ->
    (contrast-equalised photo to match, photo for the colours[, locally normalised photo for the
    pixels the first leaves empty: :func:`local_contrast`, present when that is on]), all at ``scale``. ``band``:
    only the band SGBM leaves without a disparity (the left canvas's first numDisparities
    columns: the start of the overlap), matched with the pair mirrored (the right photo,
    flipped, as the left one: the band is then at the far end of its canvas)."""
    canvas = _pair_canvas(left, right, images, sparse_enu, scale, block_px)
    if canvas is None:
        return None
    (lens_l, lens_r), r_rect, f, baseline, x0, y0, min_disp, num_disp, size = canvas
    rectified, maps = [], []
    for view, (k, dist), start in ((left, lens_l, x0 + min_disp), (right, lens_r, x0)):
        k_new = np.array([[f, 0.0, -start], [0.0, f, -y0], [0.0, 0.0, 1.0]])
        rot = r_rect @ view.cam_from_enu[:, :3].T  # camera -> rectified
        maps.append(cv2.initUndistortRectifyMap(k, dist, rot, k_new, size, cv2.CV_32FC1))
        rectified.append(cv2.remap(images[view.name][0], *maps[-1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num_disp, blockSize=block_px,
                                 P1=8 * 3 * block_px ** 2, P2=32 * 3 * block_px ** 2, disp12MaxDiff=1,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    seen = cv2.cvtColor(rectified[0], cv2.COLOR_BGR2GRAY) > 0
    pair = [cv2.flip(rectified[1], 1), cv2.flip(rectified[0], 1)] if band else rectified
    inside = cv2.cvtColor(pair[0], cv2.COLOR_BGR2GRAY) > 0
    disparity = _disparity(sgbm, pair, num_disp, inside)
    if len(images[left.name]) > 2:  # pixels left empty: matched again on the locally normalised photos
        normed = [cv2.remap(images[v.name][2], *m, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
                  for v, m in ((left, maps[0]), (right, maps[1]))]
        normed = [cv2.flip(normed[1], 1), cv2.flip(normed[0], 1)] if band else normed
        empty = np.isnan(disparity)
        disparity[empty] = _disparity(sgbm, normed, num_disp, inside)[empty]
    valid = np.isfinite(disparity)
    rows, cols = np.nonzero(valid)
    d = disparity[rows, cols]
    cols_px = cols.astype(np.float32)
    if band:  # mirrored right-canvas column -> the left canvas column of the same ground
        cols_px = size[0] - 1 - cols_px + d
        cols = np.minimum(np.rint(cols_px).astype(np.int64), size[0] - 1)
        keep = (cols_px < num_disp) & seen[rows, cols]
        rows, cols, cols_px, d = rows[keep], cols[keep], cols_px[keep], d[keep]
    d = d + min_disp
    z = f * baseline / d
    rect = np.stack(((cols_px + x0 + min_disp) * z / f, (rows + y0) * z / f, z), axis=1)
    colours = cv2.remap(images[left.name][1], *maps[0], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return rect @ r_rect + _centre(left), colours[rows, cols]


def footprint_masks(views: list[View], grid: Grid, to_utm: EnuToUtm, ground_up_m: float) -> list[np.ndarray]:
    """Per view, (H, W) bool: the grid cells inside its ground footprint, its image border
    cast to ``ground_up_m`` (ENU up, metres); all False for a view that does not look down."""
    masks = []
    t = np.linspace(0.0, 1.0, 9)
    for view in views:
        cam = view.camera
        border = np.vstack([np.stack((t * cam.width, np.zeros(9)), 1), np.stack((np.full(9, cam.width), t * cam.height), 1),
                            np.stack((t[::-1] * cam.width, np.full(9, cam.height)), 1),
                            np.stack((np.zeros(9), t[::-1] * cam.height), 1)])
        rays = np.hstack((np.asarray(cam.cam_from_img(border)), np.ones((len(border), 1)))) @ view.cam_from_enu[:, :3]
        down = rays[:, 2] < -1e-6
        mask = np.zeros((grid.height, grid.width), np.uint8)
        if down.sum() >= 3:
            centre = _centre(view)
            ground = centre + rays[down] * ((ground_up_m - centre[2]) / rays[down, 2:3])
            col, row = grid.to_pixel(*to_utm(ground)[:, :2].T)
            cv2.fillPoly(mask, [np.round(np.stack((col, row), 1)).astype(np.int32)], 1)
        masks.append(mask > 0)
    return masks


def stereo_area(views: list[View], grid: Grid, to_utm: EnuToUtm, ground_up_m: float,
                pairs: list[tuple[int, int]] | None = None) -> np.ndarray:
    """(H, W) bool: grid cells inside the ground footprints of at least two photos (the area
    a stereo surface can exist in), each footprint its image border cast to ``ground_up_m``;
    with ``pairs`` (view indices), only the cells both photos of one of those pairs see."""
    masks = footprint_masks(views, grid, to_utm, ground_up_m)
    if pairs is not None:
        area = np.zeros((grid.height, grid.width), bool)
        for i, j in pairs:
            area |= masks[i] & masks[j]
        return area
    return np.sum(masks, axis=0, dtype=np.int32) >= 2 if masks else np.zeros((grid.height, grid.width), bool)


def pair_offsets_m(pair_cells: dict[int, tuple[np.ndarray, np.ndarray]], agree_m: float = 0.5,
                   min_cells: int = 500) -> dict[int, float]:
    """Median height offset (m) of each pair from the other pairs. ``pair_cells``: pair ->
    (cell indices, heights_m) of its points. A pair is judged only on the cells that at
    least two other pairs measured and on which they agree within ``agree_m`` (one wrong
    pair cannot make such a reference), and only when it has ``min_cells`` of them."""
    medians = {n: cell_medians(cells, heights)[:2] for n, (cells, heights) in pair_cells.items()}
    all_cells = np.concatenate([m[0] for m in medians.values()])
    all_heights = np.concatenate([m[1] for m in medians.values()])
    owner = np.concatenate([np.full(len(m[0]), n) for n, m in medians.items()])
    offsets = {}
    for n, (cells, heights) in medians.items():
        others = (owner != n) & np.isin(all_cells, cells, assume_unique=False)
        c, h = all_cells[others], all_heights[others]
        if len(c) < min_cells:
            continue
        order = np.lexsort((h, c))
        c, h = c[order], h[order]
        starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        ends = np.r_[starts[1:], len(c)] - 1
        count = ends - starts + 1
        reference = 0.5 * (h[starts + (count - 1) // 2] + h[starts + count // 2])
        good = (count >= 2) & (h[ends] - h[starts] <= agree_m)
        ref_cells, ref_heights = c[starts][good], reference[good]
        at = np.clip(np.searchsorted(ref_cells, cells), 0, max(len(ref_cells) - 1, 0))
        hit = (ref_cells[at] == cells) if len(ref_cells) else np.zeros(len(cells), bool)
        if hit.sum() >= min_cells:
            offsets[n] = float(np.median(heights[hit] - ref_heights[at[hit]]))
    return offsets


def _drop_offset_pairs(matched: dict[int, tuple], views: list[View], pairs: list[tuple[int, int]],
                       max_pair_offset_m: float) -> list[str]:
    """Remove from ``matched`` (in place) the pairs whose heights sit more than
    ``max_pair_offset_m`` off the other pairs'; their names and offsets, for the report."""
    offsets = pair_offsets_m({n: m[:2] for n, m in matched.items()})
    dropped = []
    for n, offset in [(n, o) for n, o in offsets.items() if abs(o) > max_pair_offset_m]:
        names = f"{views[pairs[n][0]].name}/{views[pairs[n][1]].name}"
        log.warning("dense pair %s dropped: its heights are %+.1f m off the other pairs' (limit %g m)", names,
                    offset, max_pair_offset_m)
        dropped.append(f"{names} ({offset:+.1f} m)")
        del matched[n]
    return dropped


def _match_pairs(views: list[View], pairs: list[tuple[int, int]], image_paths: dict[str, str],
                 sparse_enu: np.ndarray, to_utm: EnuToUtm, grid: Grid, scale: float, block_px: int,
                 neighbours: int, max_points: int, seed: int, band_of: set[int] | None = None,
                 local_norm_px: int = 0) -> dict[int, tuple]:
    """Pair index -> (cells, heights_m, cloud xyz UTM, cloud rgb) of every pair SGBM matched at
    ``scale``; with ``band_of``, only those pairs' bands (:func:`_match_pair`); with
    ``local_norm_px``, pixels left empty matched again on :func:`local_contrast` photos."""
    images: dict[str, tuple[np.ndarray, ...]] = {}  # see _match_pair
    # Contrast equalised per 8x8 tile (CLAHE on lightness) before matching: the faint crop
    # rows of bright fields then pass SGBM's uniqueness test (Seneca: 86 -> 90 % of the
    # stereo area measured, fewer pairs metres off the others).
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
    matched: dict[int, tuple] = {}
    for n, (i, j) in enumerate(progress(pairs, desc=f"dense matching at {scale:g}", unit="pair")):
        if band_of is not None and n not in band_of:
            continue
        for view in (views[i], views[j]):
            if view.name not in images:
                image = cv2.imread(image_paths[view.name], cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
                if image is None:
                    raise DataError(f"{image_paths[view.name]}: photo could not be decoded for dense matching")
                image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
                lab = cv2.cvtColor(image, cv2.COLOR_BGR2LAB)
                lightness = lab[..., 0].copy()
                lab[..., 0] = clahe.apply(lightness)
                images[view.name] = (cv2.cvtColor(lab, cv2.COLOR_LAB2BGR), image)
                if local_norm_px:
                    lab[..., 0] = local_contrast(lightness, local_norm_px)
                    images[view.name] += (cv2.cvtColor(lab, cv2.COLOR_LAB2BGR),)
        # Left camera: the one the baseline leaves from, so disparities are positive.
        found = _match_pair(views[i], views[j], images, sparse_enu, scale, block_px, band_of is not None)
        if found is None:
            log.info("pair %s / %s: no dense match (lens model or disparity range)", views[i].name, views[j].name)
            continue
        enu, bgr = found
        utm = to_utm(enu)
        col, row = grid.to_pixel(utm[:, 0], utm[:, 1])
        col, row = np.rint(col).astype(np.int64), np.rint(row).astype(np.int64)
        ok = (col >= 0) & (col < grid.width) & (row >= 0) & (row < grid.height)
        if not ok.any():
            continue
        keep = np.flatnonzero(ok)
        if len(keep) > max_points // len(pairs):  # the cloud's share of this pair, a seeded subset
            keep = np.sort(np.random.default_rng(seed + n).choice(keep, max_points // len(pairs), replace=False))
        matched[n] = (row[ok] * grid.width + col[ok], utm[ok, 2], utm[keep], bgr[keep][:, ::-1])
        if len(images) > 2 * neighbours + 4:  # keep memory flat: drop photos no later pair needs
            needed = {views[a].name for a, b in pairs[n + 1:]} | {views[b].name for a, b in pairs[n + 1:]}
            for name in [k for k in images if k not in needed]:
                del images[name]
    return matched


def _fused_surface(matched: dict[int, tuple], grid: Grid, min_pairs: int) -> np.ndarray:
    """(H, W) median height of each cell over all matched pairs' points, NaN where none (or
    fewer than ``min_pairs`` pairs) measured it."""
    cells = np.concatenate([m[0] for m in matched.values()])
    heights = np.concatenate([m[1] for m in matched.values()])
    surface = cell_median(cells, heights, grid.width * grid.height).reshape(grid.height, grid.width)
    if min_pairs > 1:
        seen_by = np.bincount(np.concatenate([np.unique(m[0]) for m in matched.values()]),
                              minlength=grid.width * grid.height).reshape(surface.shape)
        surface[seen_by < min_pairs] = np.nan
    return surface


def dense_dsm(views: list[View], image_paths: dict[str, str], sparse_enu: np.ndarray, to_utm: EnuToUtm,
              grid: Grid, *, scale: float = 0.5, fill_scales: tuple[float, ...] = (0.4, 0.3, 0.2), neighbours: int = 6,
              max_ratio: float = 1.5, block_px: int = 5, min_pairs: int = 1, min_shared: int = 1,
              min_new_share: float | None = 0.005,
              spike_m: float = 2.0, max_pair_offset_m: float = 1.0, fill_max_range_m: float = 1.0,
              max_points: int = 5_000_000, seed: int = 0, band_fill: bool = True,
              fill_rounds: int = 100, local_norm_px: int = 15) -> tuple[Dsm, DenseCloud]:
    """Dense DSM on ``grid`` (every matched pixel) and the dense point cloud (at most
    ``max_points``: each pair contributes an equal seeded subset) from ``views`` (ENU poses) and the sparse points'
    ENU positions ``sparse_enu`` (disparity ranges). A pair whose heights sit more than
    ``max_pair_offset_m`` off the other pairs' (:func:`pair_offsets_m`) is dropped: its
    relative pose is wrong (stereo noise at survey scale is centimetres). ``min_new_share``:
    pairs are added whose footprints overlap on at least that share of a footprint that no
    other pair covers (:func:`stereo_pairs`; None: the lattice rule alone).

    ``band_fill``: the band SGBM leaves without a disparity at the start of each overlap is
    matched with the pair mirrored (pairs the first pass kept), and filled into the surface
    like a coarser pass. ``fill_scales``: coarser passes (fractions of the photos' size) that
    measure only the cells every finer pass left empty, each pair judged (offset from the
    other pairs) and the fused surface filtered (spikes, isolated cells) like the first
    pass. A filled cell is kept only on smooth ground next to the surface measured so far
    (:func:`skyfix.mapping.dense_fill.fill_from`): not a spike on the merged surface, its
    5x5 cells within ``fill_max_range_m`` (1 m) of each other, no step of more than twice
    that among the measured cells within 11x11, at least 6 measured cells within 7x7 and
    within ``fill_max_range_m`` of their interpolation; repeated (at most ``fill_rounds``)
    while it adds cells, so a hole fills inward from its rim. A coarse pass smears roofs
    and crowns into the ground beside them, and the mirrored band matches the photos'
    borders: on the rendered survey, without the last three checks, 10 % of the coarse
    cells were 9-10 m off and 16 % of the band's over 1 m; with them, the band and fill
    cells are 0.08 m off the truth median, 0.20 m for 90 %, 1.2 % over 1 m (the first
    pass: 0.06 and 0.17 m, 4.1 %; ``benchmarks/mapping_dsm_truth.py``). Faint, bright
    fields whose crop rows are too fine for SGBM's window at ``scale`` match at a smaller
    size (Seneca: 89.9 -> 91.0 % of the stereo area). ``DenseCloud.fills`` states each
    pass's cells and its agreement with the finer passes. The point cloud holds the first
    pass's points only. ``local_norm_px``: every pass matches the pixels SGBM left empty again
    on :func:`local_contrast` photos of that window (0: off)."""
    if len(views) < 2:
        raise DataError("a dense surface needs at least two registered photos")
    depth_m = float(np.median([_centre(v)[2] for v in views]) - np.median(sparse_enu[:, 2]))
    pairs = stereo_pairs(views, depth_m, neighbours, max_ratio=max_ratio, min_shared=min_shared,
                         min_new_share=min_new_share)
    if not pairs:
        raise DataError("no pair of registered photos overlaps with a usable baseline for dense matching")
    matched = _match_pairs(views, pairs, image_paths, sparse_enu, to_utm, grid, scale, block_px, neighbours,
                           max_points, seed, local_norm_px=local_norm_px)
    if not matched:
        raise DataError("dense matching found no point in any pair")
    dropped = _drop_offset_pairs(matched, views, pairs, max_pair_offset_m)
    surface = without_spikes(_fused_surface(matched, grid, min_pairs), spike_m)
    fills: list[dict] = []
    if band_fill:
        band = _match_pairs(views, pairs, image_paths, sparse_enu, to_utm, grid, scale, block_px, neighbours, 0,
                            seed, band_of=set(matched), local_norm_px=local_norm_px)
        if band:
            filler = without_spikes(_fused_surface(band, grid, min_pairs), spike_m)
            surface, stats = fill_from(surface, filler, spike_m, fill_max_range_m, fill_rounds)
            fills.append({"scale": scale, "band": True, **stats})
            log.info("dense band at %g: %d cells added", scale, stats["cells_added"])
    for coarse_scale in fill_scales:
        coarse = _match_pairs(views, pairs, image_paths, sparse_enu, to_utm, grid, coarse_scale, block_px,
                              neighbours, 0, seed, local_norm_px=local_norm_px)
        if coarse:
            dropped += [f"{d} at {coarse_scale:g}" for d in _drop_offset_pairs(coarse, views, pairs, max_pair_offset_m)]
        if not coarse:
            continue
        filler = without_spikes(_fused_surface(coarse, grid, min_pairs), spike_m)
        surface, stats = fill_from(surface, filler, spike_m, fill_max_range_m, fill_rounds)
        fills.append({"scale": coarse_scale, **stats})
        log.info("dense fill at %g: %d cells added; where the finer passes measured too, %.2f m median, %.2f m "
                 "for 90 %%", coarse_scale, stats["cells_added"], stats["median_abs_diff_m"], stats["p90_abs_diff_m"])
    filled = fill_holes(surface)
    xyz_keep, rgb_keep = [m[2] for m in matched.values()], [m[3] for m in matched.values()]
    xyz, rgb = np.concatenate(xyz_keep), np.concatenate(rgb_keep)
    observed = np.isfinite(surface)
    dsm = Dsm(grid, surface.astype(np.float32), filled.astype(np.float32), observed)
    return dsm, DenseCloud(xyz, rgb.astype(np.uint8), len(matched), scale, tuple(dropped), tuple(pairs), tuple(fills))
