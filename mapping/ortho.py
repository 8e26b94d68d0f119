"""Orthomosaic: every registered photo orthorectified onto the DSM and blended.

For each output pixel (a UTM grid cell) the ground point is (easting, northing, DSM
height); it is moved into the local ENU frame (:class:`~skyfix.mapping.grid.UtmToEnu`),
into the camera (pose from structure from motion, ENU after georeferencing) and through
the reconstructed lens model (pycolmap ``img_from_cam``) to a photo pixel. The projection
is computed exactly on a lattice every ``lattice_px`` output pixels and interpolated
bilinearly in between (the DSM is smooth at that scale).

Blending is a weighted mean with seam-aware weights: a photo's weight falls to zero at its
edges, as ``(distance to the nearest edge / half the short side) ** blend_power``, so seams
between photos are feathered and the photo seen closest to its centre (the least oblique
view) dominates. Cells no photo sees are nodata (alpha 0).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from skyfix.errors import DataError
from skyfix.mapping.dsm import Dsm
from skyfix.mapping.grid import Grid, UtmToEnu, enu_to_utm
from skyfix.progress import progress

__all__ = ["Orthomosaic", "View", "footprint_window", "load_views", "orthomosaic", "project_window", "rectify"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class View:
    """A registered photo: ``cam_from_enu`` (3, 4) rigid transform (ENU metres -> camera),
    ``camera`` a ``pycolmap.Camera`` (pixel centres at +0.5, as pycolmap), ``model`` the
    index of the reconstruction it was posed in (photos of different models were placed
    by different similarity fits, so their relative poses are not a stereo geometry)."""

    name: str
    path: str
    cam_from_enu: np.ndarray
    camera: object
    model: int = 0


@dataclass(frozen=True)
class Orthomosaic:
    """``rgba`` (H, W, 4) uint8 on ``grid`` (alpha 255 where some photo sees the ground)."""

    grid: Grid
    rgba: np.ndarray
    photos_used: list[str]


def footprint_window(view: View, grid: Grid, to_enu: UtmToEnu, heights_m: tuple[float, float]
                      ) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1) of the grid part the photo can see, or None."""
    cam = view.camera
    w, h = cam.width, cam.height
    uu = np.linspace(0, w, 9)
    vv = np.linspace(0, h, 7)
    border = np.vstack([np.stack((uu, np.zeros_like(uu)), 1), np.stack((uu, np.full_like(uu, h)), 1),
                        np.stack((np.zeros_like(vv), vv), 1), np.stack((np.full_like(vv, w), vv), 1)])
    rays_cam = np.hstack((np.asarray(cam.cam_from_img(border)), np.ones((len(border), 1))))
    rot, t = view.cam_from_enu[:, :3], view.cam_from_enu[:, 3]
    centre = -rot.T @ t
    rays = rays_cam @ rot  # = (R^T d) per row: camera rays in ENU
    alt0 = to_enu.frame.alt0_m
    ground = []
    for height in heights_m:
        up = height - alt0
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (up - centre[2]) / rays[:, 2]
        if np.any(~np.isfinite(s)) or np.any(s <= 0):
            return None  # a border ray misses the ground (oblique view above the horizon)
        ground.append(centre + s[:, None] * rays)
    pts = np.vstack(ground)
    utm = enu_to_utm(to_enu.frame, pts, grid.epsg)
    col, row = grid.to_pixel(utm[:, 0], utm[:, 1])
    c0, c1 = max(int(np.floor(col.min())), 0), min(int(np.ceil(col.max())) + 1, grid.width)
    r0, r1 = max(int(np.floor(row.min())), 0), min(int(np.ceil(row.max())) + 1, grid.height)
    if c0 >= c1 or r0 >= r1:
        return None
    return r0, r1, c0, c1


def _sample_dsm(dsm: Dsm, east_m: np.ndarray, north_m: np.ndarray) -> np.ndarray:
    col, row = dsm.grid.to_pixel(east_m, north_m)
    return cv2.remap(dsm.filled_m, col.astype(np.float32), row.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def project_window(view: View, grid: Grid, dsm: Dsm, to_enu: UtmToEnu, window: tuple[int, int, int, int],
                    lattice_px: int, with_depth: bool = False) -> tuple[np.ndarray, ...]:
    """Photo pixel coordinates (OpenCV convention) of every grid cell in ``window``, and
    with ``with_depth`` the cell's depth along the optical axis (m)."""
    r0, r1, c0, c1 = window
    rows = np.arange(r0, r1 + lattice_px, lattice_px, dtype=np.float64)
    cols = np.arange(c0, c1 + lattice_px, lattice_px, dtype=np.float64)
    cc, rr = np.meshgrid(cols, rows)
    east, north = grid.centres_m(rr, cc)
    height = _sample_dsm(dsm, east.astype(np.float64), north.astype(np.float64))
    enu = to_enu(east, north, height).reshape(-1, 3)
    cam_pts = enu @ view.cam_from_enu[:, :3].T + view.cam_from_enu[:, 3]
    uv = np.asarray(view.camera.img_from_cam(cam_pts, check_cheirality=False), dtype=np.float64)
    uv[cam_pts[:, 2] <= 0] = -1e6
    u = (uv[:, 0] - 0.5).reshape(rr.shape).astype(np.float32)
    v = (uv[:, 1] - 0.5).reshape(rr.shape).astype(np.float32)
    yy, xx = np.mgrid[0:r1 - r0, 0:c1 - c0].astype(np.float32) / np.float32(lattice_px)
    lattices = [u, v] + ([cam_pts[:, 2].reshape(rr.shape).astype(np.float32)] if with_depth else [])
    return tuple(cv2.remap(a, xx, yy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for a in lattices)


def rectify(view: View, grid: Grid, dsm: Dsm, to_enu: UtmToEnu, *, blend_power: float = 2.0,
            lattice_px: int = 8) -> tuple[tuple[int, int, int, int], np.ndarray, np.ndarray] | None:
    """One photo on ``grid``: (window (row0, row1, col0, col1), BGR float32 (h, w, 3),
    weight (h, w)), or None when it does not reach the grid."""
    finite = dsm.filled_m[np.isfinite(dsm.filled_m)]
    window = footprint_window(view, grid, to_enu, (float(finite.min()), float(finite.max())))
    if window is None:
        return None
    image = cv2.imread(view.path, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise DataError(f"{view.path}: photo could not be decoded for the orthophoto")
    u, v = project_window(view, grid, dsm, to_enu, window, lattice_px)
    h, w = image.shape[:2]
    edge = np.minimum(np.minimum(u + 0.5, w - 0.5 - u), np.minimum(v + 0.5, h - 0.5 - v))
    weight = np.clip(edge / (min(w, h) / 2.0), 0.0, 1.0) ** blend_power
    sampled = cv2.remap(image, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return window, sampled.astype(np.float32), weight


def orthomosaic(views: list[View], grid: Grid, dsm: Dsm, to_enu: UtmToEnu, *, blend_power: float = 2.0,
                lattice_px: int = 8) -> Orthomosaic:
    """Orthorectify and blend ``views`` onto ``grid`` (see the module docstring)."""
    acc = np.zeros((grid.height, grid.width, 3), np.float32)
    weight_sum = np.zeros((grid.height, grid.width), np.float32)
    used = []
    for view in progress(views, desc="orthophoto", unit="photo"):
        rectified = rectify(view, grid, dsm, to_enu, blend_power=blend_power, lattice_px=lattice_px)
        if rectified is None or not np.any(rectified[2] > 0):
            log.warning("%s: footprint does not reach the ground grid; skipped in the orthophoto", view.name)
            continue
        (r0, r1, c0, c1), sampled, weight = rectified
        acc[r0:r1, c0:c1] += sampled * weight[..., None]
        weight_sum[r0:r1, c0:c1] += weight
        used.append(view.name)
    covered = weight_sum > 1e-6
    rgba = np.zeros((grid.height, grid.width, 4), np.uint8)
    rgb = acc[covered] / weight_sum[covered][:, None]
    rgba[covered, :3] = np.clip(np.rint(rgb[:, ::-1]), 0, 255).astype(np.uint8)  # BGR -> RGB
    rgba[covered, 3] = 255
    return Orthomosaic(grid, rgba, used)


def load_views(models: list, image_dir: Path) -> list[View]:
    """Views of every registered image of georeferenced ``pycolmap.Reconstruction`` models."""
    views = []
    for index, rec in enumerate(models):
        for image in rec.images.values():
            if image.has_pose:
                matrix = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
                views.append(View(image.name, str(image_dir / image.name), matrix, rec.cameras[image.camera_id],
                                  index))
    return views
