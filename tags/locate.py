"""Tile-tag localisation: detect, decode, reference-map, then solve the pose."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from skyfix.camera import Camera
from skyfix.errors import EstimationError, InputError
from skyfix.tags.detect import TileDetections, detect_tiles
from skyfix.tags.field import TagField
from skyfix.tags.image import as_rgb_u8
from skyfix.tags.pose import DOWN_MOUNT, AttitudePrior, TagFix, _project, _solve, make_fix
from skyfix.tags.reference import consistent_tags

#: Streaks longer than this are flagged "motion_blur" (pixels).
BLUR_FLAG_PX = 3.0


def ideal_pixels(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Raw pixels ``(N, 2)`` -> ideal pinhole pixels of ``camera.K`` (distortion removed)."""
    return uv if camera.distortion is None else camera.distortion.undistort(uv, camera)


def tile_pixel_sigma(tile_size_px: np.ndarray, blur_px: float) -> np.ndarray:
    """1-sigma of a tile centroid, pixels: boundary quantisation and noise average over the
    tile's perimeter (~1/sqrt(side)); a blur streak adds a fraction of its length."""
    return 0.3 / np.sqrt(np.maximum(tile_size_px, 1.0) / 10.0) + 0.05 * blur_px


def locate_tiles(image, field: TagField, camera: Camera, *, prior: AttitudePrior | None = None,
                 mount: np.ndarray = DOWN_MOUNT, min_tags: int = 2, time_s: float = 0.0,
                 source_id: str = "", detections: TileDetections | None = None,
                 densify_below: int = 30) -> TagFix:
    """Position and heading of the camera's vehicle over ``field`` from one RGB frame.

    With fewer than ``densify_below`` tags (occluders, low flight) the first pose predicts
    where every field tile should appear; loose tiles of partly hidden tags that sit within
    a fifth of a tile of a prediction and show the expected colour join the final solve.
    This recovers most of the geometry occluders take away; with more tags the extra
    points change the fix by little and the step is skipped for speed (0 disables it).

    Raises :class:`~skyfix.errors.EstimationError` when fewer than ``min_tags`` tags are
    both decoded and consistent with the field's layout (a grey frame, a frame without
    tags or a frame of another field all end there, never in a fix).
    """
    if not isinstance(field, TagField):
        raise InputError(f"field must be a TagField, got {type(field).__name__}")
    if not isinstance(camera, Camera):
        raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
    rgb = as_rgb_u8(image)
    if rgb.shape[:2] != (camera.height, camera.width):
        raise InputError(f"image is {rgb.shape[1]}x{rgb.shape[0]} but the camera is {camera.width}x{camera.height}")
    det = detections if detections is not None else detect_tiles(rgb, field.codec, field.geometry)
    index = field.index_of(det.values)
    known = index >= 0
    n_decoded = len(det.values)
    if known.sum() < min_tags:
        raise EstimationError(f"found {det.n_blobs} tile candidates and {n_decoded} decoded tags, "
                              f"{int(known.sum())} of them in the field; need {min_tags}")
    ground = field.tile_points_m(index[known])
    uv_raw = det.tiles_px[known]
    uv = ideal_pixels(camera, uv_raw.reshape(-1, 2)).reshape(uv_raw.shape)
    # The vote alone: the planar-pose re-judging below replaces its tile-level homography check.
    keep = consistent_tags(ground, uv, field.spacing_m, field.geometry.pitch_m, min_support=min_tags,
                           check_tiles=False)
    blur = det.motion_blur_px
    sizes_all = det.tile_size_px[known]
    sigma_all = tile_pixel_sigma(sizes_all, blur)
    # Per-tag tolerance on the pose residual: a quarter of the tile pitch, in pixels. A tag
    # read in the wrong orientation is off by a whole pitch and drops out here.
    tol2_px2 = (0.25 * field.geometry.pitch_m / field.geometry.tile_m * sizes_all) ** 2
    sol, used = _planar_pose_of_agreeing_tags(ground, uv, keep, sigma_all, tol2_px2, camera, prior, mount,
                                              min_tags)
    n_tiles = ground.shape[1]
    g_tag, uv_tag = ground[used].reshape(-1, 2), uv[used].reshape(-1, 2)
    sigma_tag = np.repeat(sigma_all[used], n_tiles)
    n_used = int(np.count_nonzero(used))
    # In a frame of this field nearly every decoded tag fits; in a frame of another field
    # (or garbage) a few values can agree by chance, but never most of them.
    if n_used < 0.5 * n_decoded:
        raise EstimationError(f"only {n_used} of {n_decoded} decoded tags fit one camera pose: "
                              "the frame does not show this field (or is mostly misread)")
    g_pts, uv_pts, sigma = g_tag, uv_tag, sigma_tag
    if n_used < densify_below and sol.rms_px <= 3.0:
        if n_used < 10:
            # Few tags: the planar pose alone tilts freely; with the IMU prior it predicts
            # far tiles well enough to match them (many tags pin the tilt already).
            sol = _solve(g_tag, uv_tag, camera.K, prior, mount, sigma_tag, initial=sol)
        extra_g, extra_uv, extra_size = _guided_tiles(det, field, camera, sol.state, mount)
        if len(extra_g):
            g_pts = np.concatenate((g_pts, extra_g))
            uv_pts = np.concatenate((uv_pts, extra_uv))
            sigma = np.concatenate((sigma, tile_pixel_sigma(extra_size, blur)))
    sol = _solve(g_pts, uv_pts, camera.K, prior, mount, sigma, initial=sol)
    if sol.rms_px > 3.0:
        raise EstimationError(f"tag points fit the pose with {sol.rms_px:.1f} px RMS; expected < 3 px")
    return make_fix(sol, n_used, n_decoded - n_used, blur, BLUR_FLAG_PX, time_s, source_id)


def _planar_pose_of_agreeing_tags(ground: np.ndarray, uv: np.ndarray, keep: np.ndarray, sigma_all: np.ndarray,
                                  tol2_px2: np.ndarray, camera: Camera, prior: AttitudePrior | None,
                                  mount: np.ndarray, min_tags: int):
    """Planar pose of the ``keep`` tags (floor points ``(T, n, 2)``, ideal pixels ``(T, n, 2)``),
    every decoded tag re-judged by it until the kept set stops changing (at most 4 rounds):
    (the pose solution, the mask ``(T,)`` of the tags it was solved from)."""
    n_tiles = ground.shape[1]
    flat3 = np.zeros((ground.shape[0] * n_tiles, 3))
    flat3[:, :2] = ground.reshape(-1, 2)
    uv_flat = uv.reshape(-1, 2)
    for _ in range(4):
        n_keep = int(np.count_nonzero(keep))
        if n_keep < min_tags:
            raise EstimationError(f"{len(keep)} decoded tags but only {n_keep} agree with the "
                                  f"field layout; need {min_tags}")
        used = keep
        sigma_tag = np.repeat(sigma_all[used], n_tiles)
        # The planar (IPPE) pose is well inside the tolerances below; the final solve refines.
        sol = _solve(ground[used].reshape(-1, 2), uv[used].reshape(-1, 2), camera.K, prior, mount, sigma_tag,
                     iterations=0)
        # Every decoded tag is re-judged by this pose: tags the vote missed come back, tags
        # off by more than the tolerance (misreads) leave.
        d = _project(sol.state, flat3, camera.K, mount) - uv_flat
        with np.errstate(invalid="ignore"):
            new_keep = np.einsum("ij,ij->i", d, d).reshape(-1, n_tiles).max(axis=1) < tol2_px2
        if np.count_nonzero(new_keep) < min_tags:
            raise EstimationError(f"{n_keep} decoded tags agreed on a place but only "
                                  f"{int(new_keep.sum())} fit one camera pose; need {min_tags}")
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return sol, used


def _guided_tiles(det: TileDetections, field: TagField, camera: Camera, state: np.ndarray,
                  mount: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Loose tiles (not in a decoded tag) matching a field tile's predicted pixel (within a
    fifth of a tile) and colour: (floor points (K, 2), ideal pixels (K, 2), sizes (K,))."""
    loose = ~det.blob_in_tag
    if not loose.any():
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    uv_loose = ideal_pixels(camera, det.blobs_px[loose])
    size = det.blob_size_px[loose]
    digit = det.blob_digit[loose]
    # Only tags the camera can reach: the view's half-diagonal plus a generous 20 deg of
    # tilt, capped at 80 deg from nadir.
    half_diag = math.atan(math.hypot(camera.width, camera.height) / 2.0 / min(camera.fx, camera.fy))
    reach_m = max(state[2], 0.1) * math.tan(min(half_diag + math.radians(20.0), math.radians(80.0)))
    near = np.flatnonzero(np.linalg.norm(field.centres_m() - state[:2], axis=1) < reach_m + field.spacing_m)
    ground = field.tile_points_m(near).reshape(-1, 2)
    expected = field.tile_digits()[near].ravel()
    proj = _project(state, np.concatenate((ground, np.zeros((len(ground), 1))), axis=1), camera.K, mount)
    with np.errstate(invalid="ignore"):
        ok = ((proj[:, 0] > -1.0) & (proj[:, 0] < camera.width) & (proj[:, 1] > -1.0)
              & (proj[:, 1] < camera.height))
    if not ok.any():
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    cand = proj[ok]
    dist, j = cKDTree(cand).query(uv_loose, k=1)
    src = np.flatnonzero(ok)[np.minimum(j, len(cand) - 1)]
    match = (dist < 0.2 * size) & (expected[src] == digit)
    # One blob per field tile.
    _, first = np.unique(src[match], return_index=True)
    sel = np.flatnonzero(match)[first]
    return ground[src[sel]], uv_loose[sel], size[sel]
