"""Synthetic calibration photos: a chessboard or ChArUco board seen by a distorting camera.

The board is a :class:`~skyfix.datasets.render.GroundTexture` lying flat; each view is
rendered by exact ray casting through the camera model (its distortion included), from
a pose that looks at the board from a different position, tilt and roll. The true pixel
position of every board corner is returned with each image, so calibration results can
be checked against the camera that made the pictures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from skyfix.camera import Camera, CameraPose, world_to_pixel
from skyfix.datasets.render import GroundTexture, render_ground
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.mapping.board import BoardSpec

__all__ = ["BoardSpec", "CalibrationView", "board_texture", "render_calibration_views"]

_FRAME = LocalFrame(40.6303, -8.6575, 0.0)


def board_texture(spec: BoardSpec, px_per_square: int = 48, margin_squares: float = 1.0) -> tuple[np.ndarray, int]:
    """Greyscale uint8 board image with a white margin, and the margin in pixels."""
    cols, rows = spec.squares
    margin = int(round(margin_squares * px_per_square))
    w, h = cols * px_per_square, rows * px_per_square
    if spec.kind == "chessboard":
        yy, xx = np.mgrid[0:h, 0:w]
        board = np.where(((xx // px_per_square) + (yy // px_per_square)) % 2 == 0, 0, 255).astype(np.uint8)
    else:
        board = spec.opencv_charuco_board().generateImage((w, h), marginSize=0, borderBits=1)
    return cv2.copyMakeBorder(board, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255), margin


@dataclass(frozen=True)
class CalibrationView:
    """One rendered view: ``image`` uint8 ``(H, W)``; ``corners_px`` ``(N, 2)`` true raw pixel
    positions of :meth:`BoardSpec.inner_corners_m` (NaN when behind the camera); ``pose``."""

    image: np.ndarray
    corners_px: np.ndarray
    pose: CameraPose


def render_calibration_views(camera: Camera, spec: BoardSpec, n_views: int = 12, *, seed: int = 0,
                             fill: float = 0.6, spread: float = 0.7, noise_sigma: float = 1.0,
                             px_per_square: int = 48, supersample: int = 3) -> list[CalibrationView]:
    """Render ``n_views`` photos of the board by ``camera`` from varied poses.

    The camera is tilted 0-40 deg from the board's normal and rolled freely, at a range
    where the board spans about ``fill`` of the image height; it aims up to ``spread``
    (fraction of the half image height) away from the board's centre so that, over the
    views, the board visits the image edges and corners where distortion is largest.
    Views in which the board is partly outside the image are kept (ChArUco copes; a
    chessboard detector will skip them). ``noise_sigma``: grey levels of Gaussian noise.
    """
    if isinstance(n_views, bool) or not isinstance(n_views, int) or n_views < 1:
        raise InputError(f"n_views must be a positive integer, got {n_views!r}")
    rng = np.random.default_rng(seed)
    tex_img, margin = board_texture(spec, px_per_square)
    m_per_px = spec.square_m / px_per_square
    texture = GroundTexture(tex_img.astype(np.float32), m_per_px, _FRAME)
    # Board metres (x right, y down from the top-left square corner) -> ENU of the texture.
    h_tex, w_tex = tex_img.shape
    corners_m = spec.inner_corners_m()
    colrow = np.stack((corners_m[:, 0] / m_per_px + margin - 0.5, corners_m[:, 1] / m_per_px + margin - 0.5), axis=1)
    corners_enu = texture.px_to_enu(colrow)
    board_w, board_h = spec.squares[0] * spec.square_m, spec.squares[1] * spec.square_m
    vfov = math.radians(camera.vfov_deg)
    views = []
    for _ in range(n_views):
        tilt = rng.uniform(0.0, 40.0)
        azimuth = rng.uniform(0.0, 360.0)
        roll = rng.uniform(-180.0, 180.0)
        scale = rng.uniform(0.9, 1.1)
        rng_m = scale * max(board_w, board_h) / fill / (2.0 * math.tan(vfov / 2.0))
        off_m = spread * math.sqrt(rng.uniform()) * rng_m * math.tan(vfov / 2.0)
        off_dir = rng.uniform(0.0, 2.0 * math.pi)
        target = off_m * np.array([math.cos(off_dir), math.sin(off_dir)])
        horiz = rng_m * math.sin(math.radians(tilt))
        up = rng_m * math.cos(math.radians(tilt))
        east = target[0] - horiz * math.sin(math.radians(azimuth))
        north = target[1] - horiz * math.cos(math.radians(azimuth))
        lat, lon, _ = _FRAME.to_geodetic(east, north, up)
        # Gimbal roll turns the view about the optical axis (the mount's x axis after pitch).
        pose = CameraPose(float(lat), float(lon), float(up), yaw_deg=azimuth, gimbal_pitch_deg=-(90.0 - tilt),
                          gimbal_roll_deg=roll)
        rendered = render_ground(texture, camera, pose, background=200.0, supersample=supersample,
                                 blur_sigma_px=0.4, noise_sigma=noise_sigma, rng=rng)
        image = np.clip(np.round(rendered.image), 0, 255).astype(np.uint8)
        views.append(CalibrationView(image, world_to_pixel(camera, pose, _FRAME, corners_enu), pose))
    return views

