"""Input-image checks shared by the tile and AprilTag/ArUco locators."""

from __future__ import annotations

import numpy as np

from skyfix.errors import InputError


def as_rgb_u8(image, name: str = "image") -> np.ndarray:
    """An ``(H, W, 3)`` RGB (uint8, or float in [0, 1]) image as contiguous uint8.

    Greyscale ``(H, W)`` is accepted and replicated to three channels.
    """
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 16:
        raise InputError(f"{name} must be an (H, W, 3) RGB or (H, W) image of at least 16 px, got {img.shape}")
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if np.issubdtype(img.dtype, np.floating):
        if not np.all(np.isfinite(img)):
            raise InputError(f"{name} contains NaN or infinite pixels")
        return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    raise InputError(f"{name} must be uint8 or float in [0, 1], got dtype {img.dtype}")
