"""skyfix.camera: intrinsics, distortion round trips, poses and ground intersection."""

import math

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose, ground_intersection, world_to_pixel
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame, destination, inverse

MODELS = {
    "brown-conrady": BrownConrady(k1=-0.18, k2=0.035, p1=0.0012, p2=-0.0008, k3=-0.002),
    "fisheye": Fisheye(k1=0.08, k2=-0.03, k3=0.01, k4=-0.002),
    "barrel": Barrel(0.1, -0.32, 0.0),  # the source platform's GoPro correction
}


def _image_grid(camera, step=7):
    u, v = np.meshgrid(np.arange(-0.5, camera.width, step), np.arange(-0.5, camera.height, step))
    return np.stack((u.ravel(), v.ravel()), axis=1)


def test_pinhole_ray_round_trip_is_exact():
    cam = Camera(1920, 1080, 1400.0, 1395.0, 955.3, 541.7)
    uv = _image_grid(cam)
    rays = cam.pixel_to_ray(uv)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    assert np.max(np.abs(cam.project(rays * 37.0) - uv)) <= 1e-6


@pytest.mark.parametrize("name", sorted(MODELS))
def test_distorted_ray_round_trip_within_a_thousandth_of_a_pixel(name):
    cam = Camera.from_fov(1600, 1200, 90.0, distortion=MODELS[name])
    uv = _image_grid(cam)
    back = cam.project(cam.pixel_to_ray(uv))
    assert np.max(np.abs(back - uv)) <= 1e-3


def test_distortion_models_actually_distort():
    for model in MODELS.values():
        cam = Camera.from_fov(1600, 1200, 90.0, distortion=model)
        corner = np.array([[10.0, 10.0]])
        assert np.linalg.norm(model.distort(corner, cam) - corner) > 5.0


def test_barrel_known_value_imagemagick_semantics():
    # 101x101 image: centre (50, 50), normaliser 50.5 px. A pixel at r = 1 maps to itself;
    # at r = 0.5 the source radius is (a/8 + b/4 + c/2 + d) * 0.5.
    cam = Camera.from_fov(101, 101, 60.0)
    model = Barrel(0.1, -0.32, 0.0)
    d = 1.0 - 0.1 + 0.32
    out = model.distort(np.array([[50.0 + 50.5, 50.0], [50.0, 50.0 - 25.25]]), cam)
    assert out[0] == pytest.approx([100.5, 50.0], abs=1e-12)
    factor = 0.1 * 0.125 - 0.32 * 0.25 + d
    assert out[1] == pytest.approx([50.0, 50.0 - 25.25 * factor], abs=1e-12)


def test_folding_distortion_raises_instead_of_returning_garbage():
    # k1 = -0.28 with these k2, k3 folds over before the corner of a 90 deg image.
    cam = Camera.from_fov(1600, 1200, 90.0, distortion=BrownConrady(k1=-0.28, k2=0.09, k3=-0.012))
    with pytest.raises(GeometryError, match="invertible"):
        cam.pixel_to_ray(np.array([[0.0, 0.0]]))


def test_from_fov_edges_see_half_the_field_of_view():
    cam = Camera.from_fov(640, 512, 50.0)
    ray = cam.pixel_to_ray(np.array([[-0.5, cam.cy], [cam.cx, cam.height - 0.5]]))
    assert math.degrees(math.atan2(-ray[0, 0], ray[0, 2])) == pytest.approx(25.0, abs=1e-9)
    assert cam.hfov_deg == pytest.approx(50.0)
    assert cam.vfov_deg == pytest.approx(2 * math.degrees(math.atan(256 / cam.fy)))


def test_scaled_camera_keeps_rays():
    cam = Camera.from_fov(640, 512, 50.0)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 256)
    ray_full = cam.pixel_to_ray(np.array([[99.5, 199.5]]))  # edge of pixel block (99..100, 199..200)
    ray_half = half.pixel_to_ray(np.array([[49.5, 99.5]]))
    assert np.allclose(ray_full, ray_half, atol=1e-12)


def test_project_behind_camera_is_nan():
    cam = Camera.from_fov(640, 512, 50.0)
    uv = cam.project(np.array([[0.0, 0.0, 5.0], [1.0, 1.0, -5.0]]))
    assert np.all(np.isfinite(uv[0])) and np.all(np.isnan(uv[1]))


# ---- poses and ground intersection -------------------------------------------------

LAT0, LON0, GROUND = 46.5, 6.6, 400.0
H = 100.0  # camera height above ground, m


def _frame():
    return LocalFrame(LAT0, LON0, GROUND)


def _centre(cam):
    return np.array([[cam.cx, cam.cy]])


def _dcm_third_column(yaw, pitch, roll):
    """Textbook Z-Y-X direction cosine matrix, body z axis in NED."""
    cy, sy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    cp, sp = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    cr, sr = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    return np.array([cy * sp * cr + sy * sr, sy * sp * cr - cy * sr, cp * cr])


# The local tangent plane drops d^2/2R below it: 100 m away that is 0.8 mm.
CURVATURE_TOL_M = 5e-3


def test_nadir_image_top_points_along_heading():
    cam = Camera.from_fov(640, 512, 50.0)
    pose = CameraPose(LAT0, LON0, GROUND + H, yaw_deg=0.0)
    top = ground_intersection(cam, pose, np.array([[cam.cx, -0.5]]), GROUND, _frame())[0]
    right = ground_intersection(cam, pose, np.array([[cam.width - 0.5, cam.cy]]), GROUND, _frame())[0]
    half_v = H * 256 / cam.fy
    assert top == pytest.approx([0.0, half_v, 0.0], abs=CURVATURE_TOL_M)
    assert right == pytest.approx([H * math.tan(math.radians(25.0)), 0.0, 0.0], abs=CURVATURE_TOL_M)


def test_stabilized_gimbal_ignores_vehicle_roll_and_pitch():
    cam = Camera.from_fov(640, 512, 50.0)
    pose = CameraPose(LAT0, LON0, GROUND + H, roll_deg=20.0, pitch_deg=10.0, yaw_deg=90.0,
                      gimbal_pitch_deg=-45.0, stabilized=True)
    hit = ground_intersection(cam, pose, _centre(cam), GROUND, _frame())[0]
    assert hit == pytest.approx([H, 0.0, 0.0], abs=CURVATURE_TOL_M)  # 45 deg down, looking east


def test_stabilized_gimbal_yaw_is_relative_to_heading():
    cam = Camera.from_fov(640, 512, 50.0)
    pose = CameraPose(LAT0, LON0, GROUND + H, yaw_deg=30.0, gimbal_pitch_deg=-45.0, gimbal_yaw_deg=60.0)
    hit = ground_intersection(cam, pose, _centre(cam), GROUND, _frame())[0]
    assert hit == pytest.approx([H, 0.0, 0.0], abs=CURVATURE_TOL_M)  # 30 + 60 = due east


def test_hard_mounted_roll_right_wing_down_looks_left():
    cam = Camera.from_fov(640, 512, 50.0)
    pose = CameraPose(LAT0, LON0, GROUND + H, roll_deg=10.0, stabilized=False)
    hit = ground_intersection(cam, pose, _centre(cam), GROUND, _frame())[0]
    assert hit == pytest.approx([-H * math.tan(math.radians(10.0)), 0.0, 0.0], abs=CURVATURE_TOL_M)


def test_hard_mounted_nose_up_looks_ahead_along_heading():
    cam = Camera.from_fov(640, 512, 50.0)
    pose = CameraPose(LAT0, LON0, GROUND + H, pitch_deg=15.0, yaw_deg=30.0, stabilized=False)
    hit = ground_intersection(cam, pose, _centre(cam), GROUND, _frame())[0]
    d = H * math.tan(math.radians(15.0))
    assert hit == pytest.approx([d * math.sin(math.radians(30)), d * math.cos(math.radians(30)), 0.0],
                                abs=CURVATURE_TOL_M)


@pytest.mark.parametrize("yaw,pitch,roll", [(37.0, -8.0, 12.0), (-120.0, 14.0, -9.0), (200.0, 5.0, 25.0)])
def test_hard_mounted_full_attitude_matches_textbook_dcm(yaw, pitch, roll):
    cam = Camera.from_fov(640, 512, 50.0)
    pose = CameraPose(LAT0, LON0, GROUND + H, roll_deg=roll, pitch_deg=pitch, yaw_deg=yaw, stabilized=False)
    hit = ground_intersection(cam, pose, _centre(cam), GROUND, _frame())[0]
    z_ned = _dcm_third_column(yaw, pitch, roll)
    expected_en = [H * z_ned[1] / z_ned[2], H * z_ned[0] / z_ned[2]]
    assert hit[:2] == pytest.approx(expected_en, abs=CURVATURE_TOL_M)


def test_hard_mounted_oblique_mount_composes_with_attitude():
    # Mount 60 deg below the body's forward axis on a vehicle pitched 10 deg nose-down: the
    # optical axis ends 70 deg below the horizontal, straight ahead (north).
    cam = Camera.from_fov(640, 512, 50.0)
    pose = CameraPose(LAT0, LON0, GROUND + H, pitch_deg=-10.0, yaw_deg=0.0, gimbal_pitch_deg=-60.0,
                      stabilized=False)
    hit = ground_intersection(cam, pose, _centre(cam), GROUND, _frame())[0]
    assert hit == pytest.approx([0.0, H / math.tan(math.radians(70.0)), 0.0], abs=CURVATURE_TOL_M)


def test_ground_intersection_is_exact_far_from_the_frame_origin():
    cam = Camera.from_fov(640, 512, 50.0)
    lat, lon = destination(LAT0, LON0, 63.0, 12_000.0)
    pose = CameraPose(float(lat), float(lon), GROUND + H, roll_deg=5.0, pitch_deg=-3.0, yaw_deg=140.0,
                      gimbal_pitch_deg=-70.0, stabilized=False)
    uv = np.array([[10.0, 20.0], [320.0, 256.0], [600.0, 500.0]])
    far = _frame()
    near = LocalFrame(float(lat), float(lon), GROUND)
    p_far = far.to_geodetic_points(ground_intersection(cam, pose, uv, GROUND, far))
    p_near = near.to_geodetic_points(ground_intersection(cam, pose, uv, GROUND, near))
    _, dist = inverse(p_far[:, 0], p_far[:, 1], p_near[:, 0], p_near[:, 1])
    assert np.max(dist) < 1e-3
    assert np.max(np.abs(p_far[:, 2] - GROUND)) < 1e-3


def test_world_to_pixel_inverts_ground_intersection():
    cam = Camera.from_fov(1280, 960, 70.0, distortion=MODELS["brown-conrady"])
    pose = CameraPose(LAT0, LON0, GROUND + 80.0, roll_deg=-7.0, pitch_deg=4.0, yaw_deg=250.0,
                      gimbal_pitch_deg=-75.0, gimbal_yaw_deg=10.0, stabilized=False)
    uv = _image_grid(cam, step=97)
    enu = ground_intersection(cam, pose, uv, GROUND, _frame())
    assert np.max(np.abs(world_to_pixel(cam, pose, _frame(), enu) - uv)) < 1e-3


def test_ray_at_or_above_horizon_raises_geometry_error():
    cam = Camera.from_fov(640, 512, 50.0)
    level = CameraPose(LAT0, LON0, GROUND + H, gimbal_pitch_deg=0.0)
    with pytest.raises(GeometryError, match="horizon"):
        ground_intersection(cam, level, _centre(cam), GROUND, _frame())
    with pytest.raises(GeometryError, match="horizon"):
        ground_intersection(cam, level, np.array([[320.0, 0.0]]), GROUND, _frame())


def test_camera_below_ground_raises():
    cam = Camera.from_fov(640, 512, 50.0)
    pose = CameraPose(LAT0, LON0, GROUND - 1.0)
    with pytest.raises(GeometryError, match="not above the ground"):
        ground_intersection(cam, pose, _centre(cam), GROUND, _frame())


@pytest.mark.parametrize("call", [
    lambda: CameraPose(LAT0, LON0, 100.0, roll_deg=float("nan")),
    lambda: CameraPose(LAT0, LON0, 100.0, yaw_deg=float("inf")),
    lambda: CameraPose(95.0, LON0, 100.0),
    lambda: CameraPose(LAT0, LON0, 100.0, pitch_deg=120.0),
    lambda: Camera(640, 0, 500.0, 500.0, 320.0, 240.0),
    lambda: Camera(640, 480, -500.0, 500.0, 320.0, 240.0),
    lambda: Camera(640, 480, 500.0, 500.0, 320.0, 240.0, distortion="barrel"),
    lambda: Camera.from_fov(640, 480, 180.0),
    lambda: Camera.from_fov(640, 480, 60.0).pixel_to_ray(np.zeros((5, 3))),
    lambda: Camera.from_fov(640, 480, 60.0).pixel_to_ray(np.array([[np.nan, 1.0]])),
    lambda: Camera.from_fov(640, 480, 60.0).project(np.zeros((2, 2))),
    lambda: BrownConrady(k1=float("nan")),
])
def test_bad_camera_input_raises_input_error(call):
    with pytest.raises(InputError):
        call()
