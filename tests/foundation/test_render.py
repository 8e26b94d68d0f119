"""skyfix.datasets.render_ground: rendered pixels agree with the camera geometry."""

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose, ground_intersection, world_to_pixel
from skyfix.datasets import GroundTexture, render_ground
from skyfix.distortion import BrownConrady
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame

FRAME = LocalFrame(47.37, 8.54, 410.0)


def _dot_texture(colrow, size=2001, mpp=0.05):
    tex = np.zeros((size, size), np.float32)
    c, r = colrow
    tex[r - 1:r + 2, c - 1:c + 2] = 1000.0  # 3x3 texels centred on (c, r)
    return GroundTexture(tex, mpp, FRAME)


def _centroid(img, threshold):
    vv, uu = np.nonzero(img > threshold)
    w = img[vv, uu]
    return np.array([(uu * w).sum() / w.sum(), (vv * w).sum() / w.sum()])


POSES = [
    CameraPose(47.37, 8.54, 460.0, yaw_deg=20.0),
    CameraPose(47.37, 8.54, 470.0, roll_deg=8.0, pitch_deg=-6.0, yaw_deg=-130.0,
               gimbal_pitch_deg=-65.0, stabilized=False),
    CameraPose(47.3701, 8.5399, 440.0, roll_deg=-12.0, pitch_deg=9.0, yaw_deg=75.0,
               gimbal_pitch_deg=-80.0, gimbal_yaw_deg=15.0, stabilized=False),
]


@pytest.mark.parametrize("pose", POSES)
@pytest.mark.parametrize("distortion", [None, BrownConrady(k1=-0.12, k2=0.02)])
def test_rendered_ground_point_projects_back_within_half_a_pixel(pose, distortion):
    cam = Camera.from_fov(640, 480, 60.0, distortion=distortion)
    # Put the dot where pixel (401.3, 177.8) sees the ground, then find it in the render.
    ground = ground_intersection(cam, pose, np.array([[401.3, 177.8]]), FRAME.alt0_m, FRAME)
    probe = _dot_texture((1000, 1000))
    colrow = np.round(probe.en_to_px(ground[:, :2])[0]).astype(int)
    tex = _dot_texture(tuple(colrow))
    rendered = render_ground(tex, cam, pose, supersample=3)
    found = _centroid(rendered.image, 1.0)
    expected = world_to_pixel(cam, pose, FRAME, tex.px_to_enu(colrow[None, :].astype(float)))[0]
    assert np.linalg.norm(found - expected) < 0.5


def test_return_ground_matches_ground_intersection():
    cam = Camera.from_fov(320, 240, 60.0)
    pose = POSES[1]
    tex = GroundTexture(np.ones((4000, 4000), np.float32), 0.1, FRAME)
    rendered = render_ground(tex, cam, pose, return_ground=True)
    uv = np.array([[10, 20], [160, 120], [300, 200]])
    exact = ground_intersection(cam, pose, uv.astype(float), FRAME.alt0_m, FRAME)
    # The texture is the tangent plane at the frame origin; within ~100 m it departs from the
    # curved ground by d^2 / 2R < 1 mm horizontally after projection along the ray.
    got = rendered.ground_enu_m[uv[:, 1], uv[:, 0]]
    assert np.max(np.abs(got[:, :2] - exact[:, :2])) < 0.05


def test_sky_and_outside_texture_get_background_and_mask():
    cam = Camera.from_fov(320, 240, 90.0)
    pose = CameraPose(47.37, 8.54, 420.0, gimbal_pitch_deg=-20.0)  # horizon in view
    tex = GroundTexture(np.full((200, 200), 5.0, np.float32), 0.1, FRAME)
    rendered = render_ground(tex, cam, pose, background=-1.0)
    assert rendered.image.shape == (240, 320)
    assert np.all(rendered.image[~rendered.mask] == -1.0)
    assert np.all(rendered.image[0] == -1.0)  # top row is sky
    assert np.allclose(rendered.image[rendered.mask], 5.0, atol=1e-4)


def test_effects_change_the_image_as_documented():
    cam = Camera.from_fov(160, 120, 40.0)
    pose = CameraPose(47.37, 8.54, 430.0)
    tex = GroundTexture(np.full((800, 800, 3), 100.0, np.float32), 0.05, FRAME)
    plain = render_ground(tex, cam, pose).image
    assert plain.shape == (120, 160, 3)
    vign = render_ground(tex, cam, pose, vignetting=0.4).image
    assert vign[0, 0, 0] == pytest.approx(60.0, abs=0.5)  # corner gain 1 - 0.4
    assert vign[60, 80, 0] == pytest.approx(100.0, abs=0.2)
    noisy = render_ground(tex, cam, pose, noise_sigma=2.0, rng=np.random.default_rng(0)).image
    assert np.std(noisy - plain) == pytest.approx(2.0, rel=0.05)


def test_render_rejects_bad_input():
    cam = Camera.from_fov(160, 120, 40.0)
    tex = GroundTexture(np.zeros((100, 100), np.float32), 0.1, FRAME)
    with pytest.raises(GeometryError):
        render_ground(tex, cam, CameraPose(47.37, 8.54, 400.0))  # below the texture plane
    with pytest.raises(InputError):
        render_ground(tex, cam, CameraPose(47.37, 8.54, 430.0), supersample=0)
    with pytest.raises(InputError):
        render_ground(tex, cam, CameraPose(47.37, 8.54, 430.0), noise_sigma=-1.0)
    with pytest.raises(InputError):
        GroundTexture(np.zeros((10,), np.float32), 0.1, FRAME)
    with pytest.raises(InputError):
        GroundTexture(np.zeros((10, 10), np.float32), 0.0, FRAME)
