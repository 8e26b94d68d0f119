import numpy as np
import pytest

from skyfix.datasets.tag_scene import SceneEffects, field_texture, render_tag_frame
from skyfix.errors import EstimationError, InputError
from skyfix.tags.detect import detect_tiles
from skyfix.tags.field import TagField
from skyfix.tags.locate import locate_tiles
from skyfix.tags.pose import AttitudePrior

# One pixel on the floor is 0.9 mm at 1 m and 2.7 mm at 3 m with this camera; dozens of
# sub-pixel tile centroids put the fix well under 1 cm.
POS_TOL_M = 0.01
YAW_TOL_DEG = 0.2

POSES = [(1.4, 1.3, 1.0, 35.0, 6.0, -4.0), (1.5, 1.6, 2.0, -120.0, -12.0, 9.0),
         (1.6, 1.4, 3.0, 170.0, 14.0, 14.0)]


def _prior(frame):
    return AttitudePrior(frame.roll_deg + 0.3, frame.pitch_deg - 0.3, 1.0)


@pytest.mark.parametrize("pose", POSES)
def test_fix_matches_truth(pose, tag_field, tag_texture, camera, rng):
    eff = SceneEffects(lighting=0.4, noise_sigma=0.015, motion_blur_px=2.0)
    fr = render_tag_frame(tag_texture, camera, *pose, effects=eff, rng=rng)
    fix = locate_tiles(fr.image, tag_field, camera, prior=_prior(fr))
    assert np.hypot(fix.x_m - fr.x_m, fix.y_m - fr.y_m) < POS_TOL_M
    assert abs(fix.z_m - fr.z_m) < POS_TOL_M
    assert abs((fix.yaw_deg - fr.yaw_deg + 180) % 360 - 180) < YAW_TOL_DEG
    assert fix.n_tags >= 2 and fix.covariance.shape == (4, 4)
    # The reported sigma is honest: the actual error is within 5 sigma (+1 mm model floor).
    assert np.hypot(fix.x_m - fr.x_m, fix.y_m - fr.y_m) < 5 * fix.sigma_xy_m + 0.001


def test_every_visible_tag_decodes(tag_field, tag_texture, camera, rng):
    fr = render_tag_frame(tag_texture, camera, 1.5, 1.5, 2.0, 10.0, effects=SceneEffects(noise_sigma=0.01), rng=rng)
    det = detect_tiles(fr.image, tag_field.codec, tag_field.geometry)
    assert len(det.values) >= 20
    assert np.all(tag_field.index_of(det.values) >= 0)


def _misread_texture(field, truth_index, fake_value):
    """The field printed with one tag replaced by another value's colours (a misprint or a
    misread at print level), while the field file keeps the true layout."""
    v = field.values.copy().ravel()
    other = int(np.flatnonzero(v == fake_value)[0]) if fake_value in v else None
    if other is not None:
        v[other] = v[truth_index]
    v[truth_index] = fake_value
    printed = TagField(field.codec, field.geometry, field.spacing_m, v.reshape(field.values.shape))
    return field_texture(printed)


def test_misread_tag_is_rejected_and_does_not_move_fix(tag_field, tag_texture, camera, rng):
    pose = (1.5, 1.5, 1.6, 20.0, 4.0, -3.0)
    clean = render_tag_frame(tag_texture, camera, *pose, rng=np.random.default_rng(1))
    fix0 = locate_tiles(clean.image, tag_field, camera, prior=_prior(clean))
    # The tag nearest the image centre now shows the value of a far corner of the field.
    centre_index = int(np.argmin(np.linalg.norm(tag_field.centres_m() - [1.5, 1.5], axis=1)))
    bad_tex = _misread_texture(tag_field, centre_index, int(tag_field.values[-1, -1]))
    bad = render_tag_frame(bad_tex, camera, *pose, rng=np.random.default_rng(1))
    fix1 = locate_tiles(bad.image, tag_field, camera, prior=_prior(bad))
    assert fix1.rejected >= 1
    assert np.hypot(fix1.x_m - fix0.x_m, fix1.y_m - fix0.y_m) < 0.05
    assert np.hypot(fix1.x_m - bad.x_m, fix1.y_m - bad.y_m) < POS_TOL_M


def test_grey_and_noise_frames_give_no_fix(tag_field, camera, rng):
    with pytest.raises(EstimationError, match="need 2"):
        locate_tiles(np.full((480, 640, 3), 128, np.uint8), tag_field, camera)
    noise = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    with pytest.raises(EstimationError):
        locate_tiles(noise, tag_field, camera)


def test_frames_of_another_field_give_no_fix(tag_field, camera):
    # Values of another field's tags exist here too; a few can agree by chance, most cannot.
    other = TagField.generate(12, 12, tile_m=0.05, gap_m=0.02, spacing_m=0.25, time_limit_s=0.3, seed=99)
    tex = field_texture(other)
    rng = np.random.default_rng(12)
    for k in range(8):
        pose = (rng.uniform(1.0, 2.0), rng.uniform(1.0, 2.0), rng.uniform(1.0, 3.0), rng.uniform(-180, 180))
        eff = SceneEffects(occlusion_share=0.3 if k % 2 else 0.0, noise_sigma=0.01)
        fr = render_tag_frame(tex, camera, *pose, effects=eff, rng=np.random.default_rng(k))
        with pytest.raises(EstimationError):
            locate_tiles(fr.image, tag_field, camera)


def test_bad_arguments(tag_field, camera):
    with pytest.raises(InputError, match="image"):
        locate_tiles(np.zeros((480, 640)), tag_field, camera=camera.scaled(0.5))
    with pytest.raises(InputError, match="TagField"):
        locate_tiles(np.zeros((480, 640, 3)), "field.json", camera)
    with pytest.raises(InputError, match="NaN"):
        locate_tiles(np.full((480, 640, 3), np.nan), tag_field, camera)


def test_motion_blur_flag(tag_field, tag_texture, camera):
    # Streak along a tag edge (yaw 0: tag edges run along the image axes).
    sharp = render_tag_frame(tag_texture, camera, 1.5, 1.5, 1.5, 0.0, effects=SceneEffects(noise_sigma=0.01),
                             rng=np.random.default_rng(2))
    blurred = render_tag_frame(tag_texture, camera, 1.5, 1.5, 1.5, 0.0,
                               effects=SceneEffects(noise_sigma=0.01, motion_blur_px=10.0),
                               rng=np.random.default_rng(2))
    f0 = locate_tiles(sharp.image, tag_field, camera)
    f1 = locate_tiles(blurred.image, tag_field, camera)
    assert "motion_blur" not in f0.flags and "motion_blur" in f1.flags
    assert f1.motion_blur_px > f0.motion_blur_px + 3.0
    assert f1.sigma_xy_m > f0.sigma_xy_m


def test_occluded_frame_still_fixes(tag_field, tag_texture, camera, rng):
    eff = SceneEffects(occlusion_share=0.3, noise_sigma=0.01)
    fr = render_tag_frame(tag_texture, camera, 1.5, 1.5, 2.5, 60.0, effects=eff, rng=rng)
    assert 0.25 < fr.occluded_share < 0.5
    fix = locate_tiles(fr.image, tag_field, camera, prior=_prior(fr))
    assert np.hypot(fix.x_m - fr.x_m, fix.y_m - fr.y_m) < POS_TOL_M


def test_guided_tiles_add_geometry_under_occlusion(tag_field, tag_texture, camera):
    # Loose tiles of partly hidden tags join the solve: more constraint, same truth.
    eff = SceneEffects(occlusion_share=0.3, noise_sigma=0.01)
    fr = render_tag_frame(tag_texture, camera, 1.4, 1.6, 1.5, -70.0, effects=eff, rng=np.random.default_rng(4))
    sparse = locate_tiles(fr.image, tag_field, camera, prior=_prior(fr), densify_below=0)
    dense = locate_tiles(fr.image, tag_field, camera, prior=_prior(fr), densify_below=10**6)
    assert dense.sigma_xy_m < sparse.sigma_xy_m
    assert np.hypot(dense.x_m - fr.x_m, dense.y_m - fr.y_m) < POS_TOL_M
