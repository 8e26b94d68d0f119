"""Remap tables: geometry against the foundation models and against a pinhole render."""

from __future__ import annotations

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose
from skyfix.datasets.render import GroundTexture, render_ground
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.mapping.correct import Undistortion, _maps_generic
from skyfix.mapping.lens import barrel_camera


def _texture() -> GroundTexture:
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 255, (64, 64)).astype(np.float32)
    img = np.kron(img, np.ones((8, 8), np.float32))  # 512 px blocks: smooth enough to resample
    import cv2

    img = cv2.GaussianBlur(img, (0, 0), 2.0)
    return GroundTexture(img, 0.05, LocalFrame(40.0, -8.0, 0.0))


@pytest.mark.parametrize("distortion", [BrownConrady(-0.25, 0.07, 0.001, -0.0005, -0.01),
                                        Fisheye(0.05, -0.01, 0.002, 0.0)])
def test_opencv_tables_equal_foundation_projection(distortion):
    cam = Camera(320, 240, 260.0, 262.0, 161.0, 118.5, distortion)
    u = Undistortion.for_camera(cam)
    mx, my = _maps_generic(cam, u.output)
    assert np.max(np.abs(u.map_x - mx)) < 2e-3
    assert np.max(np.abs(u.map_y - my)) < 2e-3


@pytest.mark.parametrize("distortion", [Barrel(0.05, -0.15, 0.0), BrownConrady(-0.2, 0.05)])
def test_corrected_render_equals_pinhole_render(distortion):
    tex = _texture()
    cam = (barrel_camera(distortion, 320, 240, 300.0) if isinstance(distortion, Barrel)
           else Camera(320, 240, 300.0, 300.0, 159.5, 119.5, distortion))
    pose = CameraPose(40.0, -8.0, 6.0, yaw_deg=20.0)
    raw = render_ground(tex, cam, pose, supersample=2).image
    u = Undistortion.for_camera(cam, crop=True)
    corrected = u.apply(raw)
    truth = render_ground(tex, u.output, pose, supersample=2).image
    # Bilinear resampling of a smooth texture: well under one grey level on average.
    assert np.mean(np.abs(corrected - truth)) < 1.0
    assert u.valid.all()


def test_crop_keeps_only_valid_pixels_and_shifts_principal_point():
    cam = Camera(320, 240, 200.0, 200.0, 159.5, 119.5, BrownConrady(0.3))  # pincushion: corners leave the image
    full = Undistortion.for_camera(cam)
    cropped = Undistortion.for_camera(cam, crop=True)
    assert not full.valid.all() and cropped.valid.all()
    assert cropped.output.width < 320 and cropped.output.height < 240
    assert cropped.output.width / cropped.output.height == pytest.approx(320 / 240, rel=0.02)
    x0 = round(full.output.cx - cropped.output.cx)
    y0 = round(full.output.cy - cropped.output.cy)
    assert np.array_equal(cropped.map_x, full.map_x[y0:y0 + cropped.output.height, x0:x0 + cropped.output.width])


def test_apply_rejects_wrong_shape_and_options():
    u = Undistortion.for_barrel(Barrel(0.1, -0.32, 0.0), 64, 48)
    with pytest.raises(InputError):
        u.apply(np.zeros((48, 65), np.uint8))
    with pytest.raises(InputError):
        u.apply(np.zeros((48, 64), np.uint8), interpolation="bicubic-ish")
    img = np.arange(48 * 64, dtype=np.uint16).reshape(48, 64)
    out = u.apply(img)
    assert out.shape == (48, 64) and out.dtype == np.uint16
    assert img[0, 0] == 0  # caller's array untouched


@pytest.mark.parametrize("crop", [False, True])
@pytest.mark.parametrize("interpolation", ["nearest", "linear", "cubic", "lanczos"])
@pytest.mark.parametrize("border", ["replicate", "constant"])
def test_banded_apply_equals_one_remap(crop, interpolation, border):
    """apply() remaps band by band, each band's raw rows read first (speed only): every pixel must be the one
    a single cv2.remap of the whole table gives, whatever the interpolation's taps, border, dtype or channels,
    including bands whose samples run off the raw image (a barrel's corners)."""
    import cv2

    tables = Undistortion.for_barrel(Barrel(0.1, -0.32, 0.0), 301, 203, crop=crop)
    rng = np.random.default_rng(5)
    flags = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC,
             "lanczos": cv2.INTER_LANCZOS4}[interpolation]
    mode = cv2.BORDER_REPLICATE if border == "replicate" else cv2.BORDER_CONSTANT
    for shape, dtype in (((203, 301, 4), np.uint8), ((203, 301, 3), np.uint8), ((203, 301), np.uint16),
                         ((203, 301, 2), np.float32)):
        image = (rng.uniform(0, 1, shape) * (255 if dtype == np.uint8 else 4000)).astype(dtype)
        want = cv2.remap(image, tables.map_x, tables.map_y, flags, borderMode=mode)
        got = tables.apply(image, interpolation, border)
        assert got.dtype == want.dtype and got.shape == want.shape
        assert np.array_equal(got, want)
    assert len(tables._bands) > 1  # 203 rows: several bands of 64


def test_band_rows_of_a_table_with_unmappable_samples():
    """NaN marks a sample a table cannot map: a band of them reads every raw row (nothing to narrow it to),
    a band with some keeps its finite samples' rows plus the widest interpolation's taps."""
    from skyfix.mapping.correct import _source_rows

    map_y = np.full((6, 4), np.nan, np.float32)
    map_y[3:, :] = [[10.2], [11.0], [12.7]]
    assert _source_rows(map_y, 3, 100) == ((0, 3, 0, 100), (3, 6, 6, 18))  # floor(10.2) - 4, ceil(12.7) + 4 + 1
