"""Tile-tag localisation: detect, decode, reference-map, then solve the pose."""

from __future__ import annotations

import numpy as np

from skyfix.camera import Camera
from skyfix.errors import EstimationError, InputError
from skyfix.tags.detect import TileDetections, detect_tiles
from skyfix.tags.field import TagField
from skyfix.tags.image import as_rgb_u8
from skyfix.tags.pose import DOWN_MOUNT, AttitudePrior, TagFix, make_fix, solve_pose
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
                 source_id: str = "", detections: TileDetections | None = None) -> TagFix:
    """Position and heading of the camera's vehicle over ``field`` from one RGB frame.

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
    keep = consistent_tags(ground, uv, field.spacing_m, field.geometry.pitch_m, min_support=min_tags)
    if keep.sum() < min_tags:
        raise EstimationError(f"{int(known.sum())} decoded tags but only {int(keep.sum())} agree with the "
                              f"field layout; need {min_tags}")
    blur = det.motion_blur_px
    sizes = det.tile_size_px[known][keep]
    sigma = np.repeat(tile_pixel_sigma(sizes, blur), ground.shape[1])
    sol = solve_pose(ground[keep].reshape(-1, 2), uv[keep].reshape(-1, 2), camera.K, prior=prior,
                     mount=mount, sigma_px=sigma)
    if sol.rms_px > 3.0:
        raise EstimationError(f"tag points fit the pose with {sol.rms_px:.1f} px RMS; expected < 3 px")
    return make_fix(sol, int(keep.sum()), n_decoded - int(keep.sum()), blur, BLUR_FLAG_PX,
                    time_s, source_id)
