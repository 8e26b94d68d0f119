import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.datasets.tag_scene import SceneEffects, field_texture, render_tag_frame
from skyfix.errors import EstimationError, InputError
from skyfix.tags.aruco import ArucoField, fix_from_corners, locate_aruco
from skyfix.tags.pose import DOWN_MOUNT, AttitudePrior, _project


@pytest.fixture(scope="module")
def board():
    return ArucoField("apriltag_36h11", 8, 8, 0.15, 0.25)


def test_board_fix_matches_truth(board, camera):
    tex = field_texture(board)
    fr = render_tag_frame(tex, camera, 0.9, 0.8, 1.8, -30.0, 8.0, 5.0,
                          effects=SceneEffects(noise_sigma=0.01), rng=np.random.default_rng(0))
    fix = locate_aruco(fr.image, board, camera, prior=AttitudePrior(fr.roll_deg, fr.pitch_deg, 1.0))
    assert fix.n_tags >= 6
    assert np.hypot(fix.x_m - fr.x_m, fix.y_m - fr.y_m) < 0.01
    assert abs(fix.yaw_deg - fr.yaw_deg) < 0.3


def test_unknown_dictionary_and_grey(board, camera):
    with pytest.raises(InputError, match="unknown marker dictionary"):
        ArucoField("apriltag_99h99")
    with pytest.raises(EstimationError, match="no markers"):
        locate_aruco(np.full((480, 640, 3), 128, np.uint8), board, camera)


def _single_marker_corners(board, camera, state, rng):
    ground = np.concatenate((board.corners_m([board.first_id + 9])[0], np.zeros((4, 1))), axis=1)
    uv = _project(state, ground, camera.K, DOWN_MOUNT)
    return uv + rng.normal(0.0, 0.5, uv.shape)


def test_single_face_on_marker_flip_is_resolved_by_imu(board):
    # A small, far marker seen almost face-on: the two IPPE poses fit the corners nearly
    # equally; the IMU's roll/pitch must pick the true one, and the result must say so.
    camera = Camera.from_fov(640, 480, 60.0)
    rng = np.random.default_rng(5)
    truth = np.array([0.25 + 0.1, 0.25 + 0.05, 6.0, 20.0, 6.0, -4.0])
    picked_truth, flips = 0, 0
    for _ in range(20):
        uv = _single_marker_corners(board, camera, truth, rng)
        fix = fix_from_corners(uv[None], [board.first_id + 9], board, camera,
                               prior=AttitudePrior(truth[5], truth[4], 1.0))
        picked_truth += abs(fix.roll_deg - truth[5]) < 3.0 and abs(fix.pitch_deg - truth[4]) < 3.0
        flips += "flip_resolved_by_imu" in fix.flags
    assert picked_truth == 20
    assert flips >= 1      # the image alone preferred the mirror pose at least once


def test_single_marker_without_imu_is_flagged_not_silent(board):
    camera = Camera.from_fov(640, 480, 60.0)
    rng = np.random.default_rng(6)
    truth = np.array([0.35, 0.3, 4.0, 20.0, 6.0, -4.0])
    for _ in range(5):
        uv = _single_marker_corners(board, camera, truth, rng)
        fix = fix_from_corners(uv[None], [board.first_id + 9], board, camera)
        wrong = abs(fix.roll_deg - truth[5]) > 2.0 or abs(fix.pitch_deg - truth[4]) > 2.0
        if wrong:
            assert "ambiguous" in fix.flags


def test_board_print(tmp_path, board):
    import cv2

    png = board.write_png(tmp_path / "b.png", dpi=50)
    img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    found, ids, _ = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)).detectMarkers(img)
    assert ids is not None and set(ids.ravel().tolist()) == set(range(64))
