"""Pipeline parts on synthetic inputs: GPS overlap check, camera groups, lens pass-through,
UTM <-> ENU grid maths, DSM from points, configuration errors."""

from __future__ import annotations

import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import ConfigurationError, DataError, InputError
from skyfix.geo import LocalFrame, destination
from skyfix.mapping.dsm import build_dsm
from skyfix.mapping.grid import Grid, UtmToEnu, enu_to_utm, utm_epsg
from skyfix.mapping.photos import Photo, camera_groups, check_gps_overlap
from skyfix.mapping.pipeline import PipelineConfig
from skyfix.mapping.sfm import colmap_camera

LAT0, LON0 = 41.0364, -83.3059


def _photo(name: str, lat: float | None, lon: float | None, model: str = "ELPH", focal_px: float = 925.0) -> Photo:
    return Photo(name, f"/x/{name}", 1200, 900, "Canon", model, focal_px, 1, lat, lon,
                 None if lat is None else 283.0)


def test_overlap_check_flags_the_far_photo():
    # 120 m AGL with f = 925 px: footprint diagonal 120 * 1500 / 925 = 195 m.
    near = [_photo(f"p{i}", *map(float, destination(LAT0, LON0, 45.0, 25.0 * i))) for i in range(4)]
    far = _photo("far", *map(float, destination(LAT0, LON0, 180.0, 400.0)))
    check = check_gps_overlap([*near, far, _photo("nogps", None, None)], max_agl_m=120.0)
    assert check.isolated == ["far"]
    assert check.footprint_m[0] == pytest.approx(120.0 * 1500.0 / 925.0)
    assert check.nearest_m[1] == pytest.approx(25.0, abs=0.01)
    assert check_gps_overlap(near).ok
    with pytest.raises(InputError):
        check_gps_overlap(near, max_agl_m=-1.0)


def test_mixed_cameras_are_grouped():
    photos = [_photo("a", LAT0, LON0), _photo("b", LAT0, LON0), _photo("c", LAT0, LON0, model="GoPro", focal_px=600.0)]
    groups = camera_groups(photos)
    assert sorted(len(v) for v in groups.values()) == [1, 2]


def test_calibrated_lenses_pass_through():
    p = _photo("a", LAT0, LON0)
    assert colmap_camera(p).model == "SIMPLE_RADIAL"
    assert colmap_camera(p).params[:3] == (925.0, 600.0, 450.0)
    bc = Camera(2400, 1800, 1850.0, 1851.0, 1199.5, 899.5, BrownConrady(k1=-0.1, k2=0.02, p1=1e-4, p2=-1e-4, k3=0.0))
    cam = colmap_camera(p, bc)  # rescaled by 1/2, pixel centres shifted to pycolmap's +0.5
    assert cam.model == "FULL_OPENCV" and cam.fixed
    assert cam.params[:4] == pytest.approx((925.0, 925.5, 600.0, 450.0))
    assert cam.params[4:8] == (-0.1, 0.02, 1e-4, -1e-4)
    fish = colmap_camera(p, Camera(1200, 900, 500.0, 500.0, 599.5, 449.5, Fisheye(0.1, 0.01, 0.0, 0.0)))
    assert fish.model == "OPENCV_FISHEYE" and len(fish.params) == 8
    with pytest.raises(ConfigurationError, match="barrel"):
        colmap_camera(p, Camera(1200, 900, 500.0, 500.0, 599.5, 449.5, Barrel(0.1, -0.32, 0.0)))
    with pytest.raises(ConfigurationError, match="aspect"):
        colmap_camera(p, Camera(1000, 1000, 500.0, 500.0, 499.5, 499.5))


def test_utm_zone_and_utm_to_enu_match_pyproj():
    assert utm_epsg(LAT0, LON0) == 32617
    assert utm_epsg(-33.9, 18.4) == 32734  # Cape Town: zone 34 S
    frame = LocalFrame(LAT0, LON0, 283.0)
    enu = np.array([[-400.0, -300.0, -64.0], [0.0, 0.0, 0.0], [350.0, 420.0, -60.0], [120.0, -250.0, 10.0]])
    utm = enu_to_utm(frame, enu, 32617)
    box = (utm[:, 0].min() - 50, utm[:, 1].min() - 50, utm[:, 0].max() + 50, utm[:, 1].max() + 50)
    to_enu = UtmToEnu(frame, 32617, box)
    assert to_enu.max_residual_m < 1e-3
    # Round trip ENU -> UTM (exact) -> ENU (fitted): mm agreement, heights included.
    np.testing.assert_allclose(to_enu(utm[:, 0], utm[:, 1], utm[:, 2]), enu, atol=1e-3)


def test_grid_pixel_centres_round_trip():
    grid = Grid.covering(32617, 306010.2, 4545180.7, 306400.9, 4545560.1, 0.5)
    assert grid.west_m == 306010.0 and grid.north_m == 4545560.5
    west, south, east, north = grid.bounds_m
    assert west <= 306010.2 and south <= 4545180.7 and east >= 306400.9 and north >= 4545560.1
    rows, cols = np.array([0, 10, grid.height - 1]), np.array([0, 7, grid.width - 1])
    e, n = grid.centres_m(rows, cols)
    c, r = grid.to_pixel(e, n)
    np.testing.assert_allclose(np.c_[r, c], np.c_[rows, cols], atol=1e-9)
    assert e[0] == 306010.25 and n[0] == 4545560.25


def test_dsm_recovers_a_sloped_plane_and_drops_spikes():
    rng = np.random.default_rng(3)
    east = rng.uniform(1000.0, 1200.0, 3000)
    north = rng.uniform(5000.0, 5150.0, 3000)
    height = 220.0 + 0.02 * (east - 1000.0) - 0.01 * (north - 5000.0)
    height[:15] += 40.0  # mis-triangulated points
    grid = Grid.covering(32617, 1000.0, 5000.0, 1200.0, 5150.0, 5.0)
    dsm = build_dsm(np.c_[east, north, height], grid)
    rr, cc = np.mgrid[0:grid.height, 0:grid.width]
    e, n = grid.centres_m(rr, cc)
    truth = 220.0 + 0.02 * (e - 1000.0) - 0.01 * (n - 5000.0)
    inside = np.isfinite(dsm.surface_m)
    assert inside.mean() > 0.9
    # Cell medians of a plane with 5 m cells: error below slope * half cell = 0.06 m.
    assert np.abs(dsm.surface_m[inside] - truth[inside]).max() < 0.1
    assert np.isfinite(dsm.filled_m).all()
    with pytest.raises(DataError):
        build_dsm(np.array([[0.0, 0.0, 1.0]]), grid)


def test_config_errors():
    with pytest.raises(ConfigurationError):
        PipelineConfig("a", "b", barrel=Barrel(0.1, -0.32, 0.0), calibration=Camera(10, 10, 5.0, 5.0, 4.5, 4.5))
    with pytest.raises(ConfigurationError, match="stage"):
        PipelineConfig("a", "b", force=("nope",))
    with pytest.raises(InputError):
        PipelineConfig("a", "b", resolution_cm=-2.0)
    with pytest.raises(InputError, match="dense_local_norm_px"):
        PipelineConfig("a", "b", dense_local_norm_px=2)


def test_map_command_help(capsys):
    from skyfix.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["map", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "--resolution-cm" in out and "--barrel" in out and "--calibration" in out and "resumes" in out


def test_enclosed_holes_only_small_ones_inside_measured_cells():
    from skyfix.mapping.dsm import enclosed_holes

    observed = np.ones((30, 30), bool)
    observed[5:7, 5:7] = False      # 4 cells, enclosed: interpolated
    observed[12:18, 12:18] = False  # 36 cells, enclosed but larger than the limit
    observed[0:3, 20:23] = False    # touches the grid's edge: open, never filled
    observed[25, 3] = observed[26, 4] = False  # diagonal neighbours: two separate 1-cell holes
    holes = enclosed_holes(observed, max_cells=16)
    assert holes[5:7, 5:7].all() and holes[25, 3] and holes[26, 4]
    assert not holes[12:18, 12:18].any() and not holes[0:3, 20:23].any()
    assert holes.sum() == 6 and not (holes & observed).any()


def test_pair_offsets_single_out_the_pair_off_the_others():
    # Ground at 100 m. Pairs a, b, c measure cells 0-5999 (5 cm noise, stereo at survey
    # scale); d measures 3000-8999 but 8 m low (a wrong relative pose); e measures
    # 5000-9999 right. d is judged where a, b, c agree (3000-5999); a on 0-2999 (b and c
    # agree; where d joins them they do not); e nowhere: its cells shared with two or
    # more others hold d's wrong heights too, so it is neither judged nor dropped.
    from skyfix.mapping.dense import pair_offsets_m

    rng = np.random.default_rng(3)

    def pair(lo, hi, offset_m):
        cells = np.repeat(np.arange(lo, hi), 3)
        return cells, 100.0 + offset_m + rng.normal(0.0, 0.05, len(cells))

    offsets = pair_offsets_m({0: pair(0, 6000, 0.0), 1: pair(0, 6000, 0.0), 2: pair(0, 6000, 0.0),
                              3: pair(3000, 9000, -8.0), 4: pair(5000, 10000, 0.0)})
    assert abs(offsets[3] + 8.0) < 0.1
    assert all(abs(offsets[n]) < 0.1 for n in (0, 1, 2)) and 4 not in offsets


def test_stereo_pairs_stay_inside_one_model():
    # Six nadir photos 25 m apart along a line at 65 m (footprints ~84 m long: they all
    # overlap). Photos of models 0 and 1 were georeferenced by different similarity fits
    # and never pair; model 2 holds one photo placed on its partner's ground, which may
    # pair with any.
    import pycolmap

    from skyfix.mapping.dense import stereo_pairs
    from skyfix.mapping.ortho import View

    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=1200, height=900, params=[925.0, 600.0, 450.0])
    rot = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # camera x east, y south, z down
    views = []
    for k, model in enumerate((0, 0, 0, 1, 1, 2)):
        centre = np.array([25.0 * k, 0.0, 65.0])
        views.append(View(f"p{k}", "", np.hstack((rot, (-rot @ centre)[:, None])), camera, model))
    pairs = stereo_pairs(views, 65.0)
    assert (0, 1) in pairs and (3, 4) in pairs
    assert not any(views[i].model != views[j].model and 5 not in (i, j) for i, j in pairs)
    assert any(5 in p for p in pairs)


def test_stereo_pairs_cover_corner_overlaps():
    # Nadir photos at 65 m (footprints 84.3 m x 63.2 m). B, 70 m east and 50 m north of A
    # (baseline 86 m = 1.32x the height), overlaps A in a 14 m x 13.2 m corner (3.5 % of a
    # footprint) that neither photo's 3x3 lattice (1/4-3/4 of the frame) reaches: only the
    # footprint-overlap rule pairs them. With C between them, A and B's corner lies inside
    # C's overlaps with each, already covered, so A/B is not added.
    import pycolmap

    from skyfix.mapping.dense import stereo_pairs
    from skyfix.mapping.ortho import View

    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=1200, height=900, params=[925.0, 600.0, 450.0])
    rot = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])

    def view(name, east_m, north_m):
        centre = np.array([east_m, north_m, 65.0])
        return View(name, "", np.hstack((rot, (-rot @ centre)[:, None])), camera, 0)

    a, b, c = view("a", 0.0, 0.0), view("b", 70.0, 50.0), view("c", 35.0, 25.0)
    assert stereo_pairs([a, b], 65.0, 6, max_ratio=1.5, min_shared=1) == []
    assert stereo_pairs([a, b], 65.0, 6, max_ratio=1.5, min_shared=1, min_new_share=0.01) == [(0, 1)]
    assert stereo_pairs([a, b], 65.0, 6, max_ratio=1.5, min_shared=1, min_new_share=0.05) == []
    assert stereo_pairs([a, b], 65.0, 6, max_ratio=1.2, min_shared=1, min_new_share=0.01) == []  # baseline
    assert stereo_pairs([a, b, c], 65.0, 6, max_ratio=1.5, min_shared=1, min_new_share=0.01) == [(0, 2), (1, 2)]


def test_stereo_area_of_the_tried_pairs():
    # Three nadir photos 25 m apart along x at 65 m over flat ground at 0 (footprints
    # 2 x 600/925 x 65 = 84.3 m along x, 63.2 m along y; photo k spans 25 k -+ 42.16 m).
    # Seen by two or more: photo 1's span, [-17.16, 67.16]; by both photos of the one tried
    # pair (0, 1): [-17.16, 42.16], 59.3 / 84.3 = 0.703 of it.
    import pycolmap

    from skyfix.mapping.dense import stereo_area
    from skyfix.mapping.ortho import View

    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=1200, height=900, params=[925.0, 600.0, 450.0])
    rot = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    views = [View(f"p{k}", "", np.hstack((rot, (-rot @ np.array([25.0 * k, 0.0, 65.0]))[:, None])), camera, 0)
             for k in range(3)]
    grid = Grid(32632, -60.0, 40.0, 0.25, 640, 320)  # x -60..100 m, y -40..40 m

    def to_utm(enu):
        return np.asarray(enu)  # the ENU plane as the grid's easting/northing

    area = stereo_area(views, grid, to_utm, 0.0)
    tried = stereo_area(views, grid, to_utm, 0.0, pairs=[(0, 1)])
    rows, cols = np.nonzero(area)
    x_m = -60.0 + (cols + 0.5) * 0.25
    assert abs(x_m.min() + 17.16) < 0.3 and abs(x_m.max() - 67.16) < 0.3
    assert abs(rows.max() - rows.min() + 1 - 63.2 / 0.25) <= 3
    assert not (tried & ~area).any()
    assert abs(tried.sum() / area.sum() - 59.3 / 84.3) < 0.01


def test_local_contrast_ignores_the_photos_gain_and_offset():
    """The locally normalised photo dense matching falls back on (mapping.dense.local_contrast)
    is the same for one ground seen darker or brighter (exposure: gain and offset), gives faint
    texture the contrast of strong texture, and does not amplify flat ground past its noise."""
    from skyfix.mapping.dense import local_contrast

    rng = np.random.default_rng(0)
    texture = rng.normal(0.0, 1.0, (120, 160))
    faint = local_contrast(np.clip(30 + 3 * texture, 0, 255).astype(np.uint8), 15).astype(float)
    bright = local_contrast(np.clip(90 + 12 * texture, 0, 255).astype(np.uint8), 15).astype(float)
    inner = (slice(10, -10), slice(10, -10))
    # 3 and 12 grey levels of texture (1/4 the contrast) come out with nearly one contrast:
    # std / (std + 2 grey levels) each, 0.70 between them (10 %: rounding to grey levels).
    expected = (3 / (3 + 2)) / (12 / (12 + 2))
    assert faint[inner].std() / bright[inner].std() == pytest.approx(expected, rel=0.1)
    # Rounding to grey levels aside, the faint and bright photos match pixel by pixel.
    assert np.corrcoef(faint[inner].ravel(), bright[inner].ravel())[0, 1] > 0.9
    flat = local_contrast(np.clip(60 + rng.normal(0.0, 0.5, (120, 160)), 0, 255).astype(np.uint8), 15)
    assert flat[inner].astype(float).std() < 0.5 * faint[inner].std()  # noise stays below texture
