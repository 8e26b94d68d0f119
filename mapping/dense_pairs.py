"""Which photo pairs the dense surface matches (:mod:`skyfix.mapping.dense`).

Each registered photo is paired with its nearest neighbours that see part of its 3x3
footprint lattice; pairs whose footprints overlap on ground no chosen pair covers (corners
of photos on neighbouring lines, which the lattice misses) are then added. Only photos of
one model pair, or a photo alone in its model (placed on its partner's ground).
"""

from __future__ import annotations

import cv2
import numpy as np

from skyfix.mapping.ortho import View

__all__ = ["camera_centre", "stereo_pairs"]


def camera_centre(view: View) -> np.ndarray:
    """Camera centre of ``view`` in ENU metres."""
    return -view.cam_from_enu[:, :3].T @ view.cam_from_enu[:, 3]


def _cast_down(view: View, uv_px: np.ndarray, depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Image points ``uv_px`` (N, 2) cast on the level plane ``depth_m`` below the camera: ENU
    points (N, 3) and the (N,) rays' ENU up components (a ray with up >= 0 never reaches it)."""
    rays_cam = np.hstack((np.asarray(view.camera.cam_from_img(uv_px)), np.ones((len(uv_px), 1))))
    rays = rays_cam @ view.cam_from_enu[:, :3]  # rows: R^T d, camera rays in ENU
    return camera_centre(view) + rays * (depth_m / np.maximum(-rays[:, 2:3], 1e-6)), rays[:, 2]


def _footprint_samples(view: View, depth_m: float) -> np.ndarray:
    """ENU ground points (3x3 lattice at 1/4, 1/2, 3/4 of the photo) ``depth_m`` below its camera."""
    cam = view.camera
    uu, vv = np.meshgrid(np.array([0.25, 0.5, 0.75]) * cam.width, np.array([0.25, 0.5, 0.75]) * cam.height)
    return _cast_down(view, np.stack((uu.ravel(), vv.ravel()), axis=1), depth_m)[0]


def _footprint_polygon(view: View, depth_m: float) -> np.ndarray | None:
    """(4, 2) ENU east/north corners of the photo's ground footprint ``depth_m`` below its
    camera (image corners cast on a level plane), or None when a corner looks up."""
    cam = view.camera
    corners = np.array([[0.0, 0.0], [cam.width, 0.0], [cam.width, cam.height], [0.0, cam.height]])
    ground, up = _cast_down(view, corners, depth_m)
    return None if (up > -1e-6).any() else ground[:, :2]


def _pairable(views: list[View], i: int, j: int, per_model: np.ndarray) -> bool:
    """Both views in one model, or one alone in its model (placed on its partner's ground)."""
    return views[i].model == views[j].model or min(per_model[views[i].model], per_model[views[j].model]) == 1


def _coverage_pairs(views: list[View], depth_m: float, pairs: set[tuple[int, int]], baselines: np.ndarray,
                    min_ratio: float, max_ratio: float, min_new_share: float) -> list[tuple[int, int]]:
    """Pairs to add to ``pairs`` so that ground two photos see has a pair: candidate pairs
    (usable baseline, pairable models), shortest baseline first, whose footprints' overlap
    holds at least ``min_new_share`` of a footprint's area that no chosen pair's overlap
    covers (ground rasterised at 1/100 of a footprint's side)."""
    polygons = [_footprint_polygon(v, depth_m) for v in views]
    valid = [k for k, p in enumerate(polygons) if p is not None]
    if len(valid) < 2:
        return []
    corners = np.vstack([polygons[k] for k in valid])
    cell_m = float(np.sqrt(np.median([cv2.contourArea(polygons[k].astype(np.float32)) for k in valid]))) / 100.0
    origin = corners.min(axis=0)
    shape = tuple((np.ceil((corners.max(axis=0) - origin) / cell_m).astype(int) + 1)[::-1])

    def raster(k: int) -> np.ndarray:
        mask = np.zeros(shape, np.uint8)
        cv2.fillConvexPoly(mask, np.round((polygons[k] - origin) / cell_m).astype(np.int32), 1)
        return mask > 0

    masks = {k: raster(k) for k in valid}
    covered = np.zeros(shape, bool)
    for i, j in pairs:
        if i in masks and j in masks:
            covered |= masks[i] & masks[j]
    per_model = np.bincount([v.model for v in views])
    min_new_cells = min_new_share * 1e4  # a footprint covers ~100 x 100 raster cells
    added = []
    order = sorted((baselines[i, j], i, j) for i in valid for j in valid if i < j)
    for baseline, i, j in order:
        if (i, j) in pairs or not min_ratio * depth_m <= baseline <= max_ratio * depth_m \
                or not _pairable(views, i, j, per_model):
            continue
        new = masks[i] & masks[j] & ~covered
        if new.sum() >= min_new_cells:
            added.append((i, j))
            covered |= new
    return added


def stereo_pairs(views: list[View], depth_m: float, neighbours: int = 4, min_ratio: float = 0.08,
                 max_ratio: float = 1.2, min_shared: int = 3, min_new_share: float | None = None,
                 ) -> list[tuple[int, int]]:
    """Index pairs (i < j) of overlapping views: for each view its ``neighbours`` nearest
    others whose baseline is ``min_ratio``-``max_ratio`` of ``depth_m`` (the flying height)
    and which see at least ``min_shared`` of its 9 footprint lattice points (a third of it).
    Both views come from the same model, or one is alone in its model (a photo placed on
    its partner's ground, in the partner's model's frame): two models are georeferenced by
    separate similarity fits, metres apart in height, which stereo would turn into heights
    off by tens of metres. With ``min_new_share``, pairs are then added (shortest baseline
    first, same limits) whose footprints overlap on ground no chosen pair covers, at least
    that share of a footprint: corners of photos on neighbouring lines, which the lattice
    misses (Seneca: 1.3 % of the ground two photos see)."""
    centres = np.array([camera_centre(v) for v in views])
    baselines = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    per_model = np.bincount([v.model for v in views])
    pairs: set[tuple[int, int]] = set()
    for i, view in enumerate(views):
        ground = _footprint_samples(view, depth_m)
        found = []
        for j in np.argsort(baselines[i]):
            if j == i or not min_ratio * depth_m <= baselines[i, j] <= max_ratio * depth_m:
                continue
            if not _pairable(views, i, int(j), per_model):
                continue
            other = views[j]
            p = ground @ other.cam_from_enu[:, :3].T + other.cam_from_enu[:, 3]
            uv = np.asarray(other.camera.img_from_cam(p, check_cheirality=False))
            seen = (p[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < other.camera.width) & (uv[:, 1] >= 0) \
                & (uv[:, 1] < other.camera.height)
            if seen.sum() >= min_shared:
                found.append(int(j))
            if len(found) == neighbours:
                break
        pairs.update((min(i, j), max(i, j)) for j in found)
    if min_new_share is not None:
        pairs.update(_coverage_pairs(views, depth_m, pairs, baselines, min_ratio, max_ratio, min_new_share))
    return sorted(pairs)
