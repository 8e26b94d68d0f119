"""The photo-to-model pipeline on a rendered DJI-like survey with exact ground truth.

A nadir grid (3 lines x 5 photos, 512x288, 16:9 crop of a 3:2 sensor) flown 30 m above
the take-off point over hills, buildings and trees (skyfix.datasets.survey_scene). The
EXIF 35 mm equivalent (24 mm) scaled by the image diagonal is 4.5 % short of the true
focal length, as on real cropped frames; the XMP carries DJI's calibrated focal length.
GPS has a correlated random-walk error (0.4 m horizontal, 0.2 m vertical per photo).

Bounds: a focal length off by 4.5 % would put the ground 1.35 m (4.5 % of 30 m) off; the
issue asks for 0.3 m median. GPS noise over a 28 m x 32 m block leaves a scale error of
~0.2 % (6 cm at 30 m), well inside it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from skyfix.datasets.survey_scene import make_scene, survey_camera, write_survey
from skyfix.mapping.exif import read_metadata
from skyfix.mapping.pipeline import PipelineConfig, run_pipeline

FAST = {"threads": 2}


@pytest.fixture(scope="module")
def scene():
    return make_scene()


@pytest.fixture(scope="module")
def survey(scene, tmp_path_factory) -> tuple[Path, list]:
    folder = tmp_path_factory.mktemp("survey")
    return folder, write_survey(folder, scene)


@pytest.fixture(scope="module")
def run(survey, tmp_path_factory):
    out = tmp_path_factory.mktemp("project")
    return run_pipeline(PipelineConfig(survey[0], out, **FAST)), out


def _dsm_errors(scene, path: Path) -> tuple[np.ndarray, float]:
    """Model DSM minus true surface at every valid cell (m), and the valid share."""
    import rasterio

    from skyfix.mapping.grid import UtmToEnu

    with rasterio.open(path) as ds:
        z = ds.read(1, masked=True).filled(np.nan)
        rows, cols = np.nonzero(np.isfinite(z))
        t = ds.transform
        east, north = t.c + t.a * (cols + 0.5), t.f + t.e * (rows + 0.5)
        to_enu = UtmToEnu(scene.frame, ds.crs.to_epsg(), (east.min(), north.min(), east.max(), north.max()))
    enu = to_enu(np.asarray(east), np.asarray(north), z[rows, cols])
    return enu[:, 2] - scene.height_at(enu[:, 0], enu[:, 1]), float(np.isfinite(z).mean())


def test_focal_prior_from_sensor_geometry(scene, tmp_path):
    true_f = survey_camera().fx
    with_xmp = write_survey(tmp_path / "a", scene, lines=1, per_line=1)[0]
    meta = read_metadata(Path(with_xmp.path).read_bytes())
    assert meta.focal_estimate(512, 288).source == "xmp-calibrated"
    assert meta.focal_estimate(512, 288).focal_px == pytest.approx(true_f, rel=1e-6)
    # The diagonal rule on the 35 mm equivalent alone: 24 * hypot(512, 288) / 43.27 mm is 4.5 % short.
    f35 = 24 * math.hypot(512, 288) / math.hypot(36, 24)
    assert f35 / true_f == pytest.approx(0.955, abs=0.002)
    plain = write_survey(tmp_path / "b", scene, lines=1, per_line=1, calibrated_focal=False)[0]
    meta = read_metadata(Path(plain.path).read_bytes())
    assert meta.xmp["RelativeAltitude"] == pytest.approx(30.0, abs=0.5)
    estimate = meta.focal_estimate(512, 288)  # FC6310 is in the sensor table: 13.2 mm wide
    assert (estimate.source, estimate.focal_px) == ("sensor-table", pytest.approx(true_f, rel=1e-3))
    plane = write_survey(tmp_path / "c", scene, lines=1, per_line=1, calibrated_focal=False, focal_plane=True)[0]
    estimate = read_metadata(Path(plane.path).read_bytes()).focal_estimate(512, 288)
    assert (estimate.source, estimate.focal_px) == ("focal-plane", pytest.approx(true_f, rel=1e-3))


def test_focal_plane_resolution_checked_against_the_sensor_table():
    # The real Seneca photos (Canon ELPH 300 HS, 1/2.3-inch: 6.17 mm) were downscaled
    # 4000 -> 1200 px with FocalPlaneXResolution divided by 3 instead of 3.33: it implies a
    # 1200 px / (5464.48 px/in) = 5.58 mm sensor, 9.6 % off the table, so the table decides.
    # Sensors of one type differ by ~2 %; the tolerance is 5 %.
    data = (Path(__file__).parents[1] / "data" / "seneca" / "IMG_0474.jpg").read_bytes()
    meta = read_metadata(data)
    assert 1200 / meta.focal_plane_px_per_mm == pytest.approx(5.578, abs=0.002)
    estimate = meta.focal_estimate(1200, 900)
    assert (estimate.source, estimate.focal_px) == ("sensor-table", pytest.approx(4.3 * 1200 / 6.17, rel=1e-6))
    # A density consistent with the table (the same photo at its original 4000 px width) is trusted.
    from dataclasses import replace

    at_4000 = replace(meta, focal_plane_px_per_mm=4000 / 6.2)
    assert at_4000.focal_estimate(4000, 3000).source == "focal-plane"


@pytest.mark.slow
def test_ground_heights_match_truth(run, scene, survey):
    report, out = run
    assert len(report.registered) == 15
    assert report.camera_groups[0]["focal_source"] == "xmp-calibrated"
    assert report.camera_groups[0]["focal_refined"] is False
    errors, _ = _dsm_errors(scene, out / "dsm.tif")
    assert len(errors) > 300
    assert abs(float(np.nanmedian(errors))) <= 0.3
    assert float(np.nanmedian(np.abs(errors))) <= 0.3
    # The height check: model height above its ground vs the photos' barometric relative
    # altitude differ by the true ground height below the cameras (terrain, +-1.5 m).
    centres = np.array([p.centre_enu_m for p in survey[1]])
    ground_below = float(np.median(scene.height_at(centres[:, 0], centres[:, 1])))
    fh = report.flying_height
    assert fh["photos"] == 15 and "relative altitude" in fh["line"]
    assert fh["difference_m"] == pytest.approx(-ground_below, abs=0.3)
    assert not any("probably wrong" in w for w in report.warnings)


@pytest.mark.slow
def test_same_output_twice(run, survey, tmp_path):
    import rasterio

    first_report, first = run
    second_report = run_pipeline(PipelineConfig(survey[0], tmp_path, **FAST))
    assert second_report.points == first_report.points
    assert (tmp_path / "points.ply").read_bytes() == (first / "points.ply").read_bytes()
    for name in ("dsm.tif", "orthophoto.tif"):
        with rasterio.open(first / name) as a, rasterio.open(tmp_path / name) as b:
            assert a.transform == b.transform
            assert np.array_equal(a.read(), b.read())


@pytest.mark.slow
def test_matching_repeats(run, survey, tmp_path):
    """The pipeline's matching, done again on its own database, gives the same raw matches
    every round. With COLMAP's matcher threads in parallel (--match-threads -1) 2 of 40
    rounds lost matches in 2 of the 105 pairs (benchmarks/mapping_repeat.py), and a
    whole photo's pairs in the loaded suite that failed test_same_output_twice."""
    import shutil
    import sqlite3

    from skyfix.mapping import sfm
    from skyfix.mapping.photos import load_photos

    def matches(db: Path) -> dict:
        con = sqlite3.connect(db)
        try:
            return {pair: (n, data) for pair, n, data in con.execute("SELECT pair_id, rows, data FROM matches")}
        finally:
            con.close()

    _, out = run
    reference = matches(out / "work" / "database.db")
    assert len(reference) == 105
    photos, _ = load_photos(survey[0])
    threads = PipelineConfig(survey[0], tmp_path).match_threads
    for round_ in range(8):
        db = tmp_path / f"round{round_}.db"
        shutil.copy(out / "work" / "database.db", db)
        con = sqlite3.connect(db)
        con.execute("DELETE FROM matches")
        con.execute("DELETE FROM two_view_geometries")
        con.commit()
        con.close()
        sfm.match(db, photos, threads=threads)
        found = matches(db)
        assert [p for p in reference if found.get(p) != reference[p]] == [], f"round {round_}"


def _ortho_vs_truth(scene, path: Path) -> tuple[float, float]:
    """(detail kept, large-error share) of the orthophoto near buildings and trees.

    Detail kept: Laplacian energy of the orthophoto over that of the true texture within
    about 0.6 m of anything over 2.5 m tall: ghosting (two half-transparent copies) and
    feathering of views that disagree wash detail out (0.71 for a feathered mean on a
    sparse surface). Large-error share: pixels more than 30 grey levels from the truth
    even allowing a 2-pixel shift (a roof edge in the wrong place, a doubled crown)."""
    import cv2
    import rasterio

    from skyfix.mapping.grid import UtmToEnu

    with rasterio.open(path) as ds:
        rgba = np.moveaxis(ds.read(), 0, 2)
        rows, cols = np.mgrid[0:ds.height, 0:ds.width]
        t = ds.transform
        east, north = t.c + t.a * (cols.ravel() + 0.5), t.f + t.e * (rows.ravel() + 0.5)
        epsg = ds.crs.to_epsg()
    east, north = np.asarray(east), np.asarray(north)
    to_enu = UtmToEnu(scene.frame, epsg, (east.min(), north.min(), east.max(), north.max()))
    enu = to_enu(east, north, np.full(east.shape, scene.frame.alt0_m))
    shape = rgba.shape[:2]
    truth = scene.colour_at(enu[:, 0], enu[:, 1], blur_px=1.0).reshape(*shape, 3)
    height = np.nan_to_num(scene.height_at(enu[:, 0], enu[:, 1]).reshape(shape))
    near = cv2.dilate((height > 2.5).astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
    near &= rgba[..., 3] > 0
    grey_o = cv2.cvtColor(rgba[..., :3], cv2.COLOR_RGB2GRAY).astype(np.float32)
    grey_t = cv2.cvtColor(np.clip(truth, 0, 255).astype(np.uint8), cv2.COLOR_BGR2GRAY).astype(np.float32)

    def detail(x):
        return np.abs(cv2.Laplacian(cv2.GaussianBlur(x, (0, 0), 0.7), cv2.CV_32F))[near].mean()

    best = np.full(shape, np.inf, np.float32)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            best = np.minimum(best, np.abs(grey_o - np.roll(np.roll(grey_t, dy, 0), dx, 1)))
    return float(detail(grey_o) / detail(grey_t)), float((best[near] > 30).mean())


@pytest.mark.slow
def test_orthophoto_without_ghosts(run, scene):
    report, out = run
    assert report.dense_points > 100_000 and report.dsm_valid_share >= 0.8
    kept, wrong = _ortho_vs_truth(scene, out / "orthophoto.tif")
    assert kept >= 0.95
    assert wrong <= 0.08
    with rasterio_open(out / "orthophoto.tif") as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG" and ds.overviews(1)


def rasterio_open(path: Path):
    import rasterio

    return rasterio.open(path)


@pytest.mark.slow
def test_gps_time_lag_estimated_and_removed(run, scene, tmp_path):
    """Tags 0.8 s stale at 5 m/s trail the cameras by 4 m, in opposite directions on
    alternate lines; the model from the same pixels (the run above) reveals the lag."""
    import pycolmap

    from skyfix.mapping import sfm
    from skyfix.mapping.georef import georeference, survey_frame
    from skyfix.mapping.gps_lag import gps_velocities
    from skyfix.mapping.photos import load_photos

    write_survey(tmp_path, scene, gps_lag_s=0.8)
    photos, _ = load_photos(tmp_path)
    frame = survey_frame(photos)
    model = sfm.load_models(run[1] / "work" / "sparse")[0]
    plain = georeference(pycolmap.Reconstruction(model), photos, frame)
    fixed = georeference(model, photos, frame, velocities=gps_velocities(photos, frame))
    assert plain.rms_m > 2.5  # 4 m along-track trailing
    assert fixed.gps_lag["applied"]
    assert fixed.gps_lag["lag_s"] == pytest.approx(0.8, abs=0.1)
    assert fixed.rms_m < 0.25 * plain.rms_m
    assert not run[0].models[0]["gps_lag"].get("applied")  # the unlagged survey shows none


@pytest.mark.slow
def test_dsm_fill_passes_add_cells_on_the_true_surface(run, scene):
    """The mirrored band pass and the coarser SGBM passes only fill cells the first pass left
    empty, and what they add lies on the true surface: 0.3 m median (the issue's bound for
    the DSM) and 1 m for 90 % (the first pass: 0.06 m median, 0.17 m for 90 %, 4 % over 1 m;
    benchmarks/mapping_dsm_truth.py prints these figures)."""
    import json

    from skyfix.geo import LocalFrame
    from skyfix.mapping import sfm
    from skyfix.mapping.dense import dense_dsm
    from skyfix.mapping.grid import EnuToUtm, Grid, UtmToEnu
    from skyfix.mapping.ortho import load_views
    from skyfix.mapping.surface_stages import points

    report, out = run
    stages = out / "work" / "stages"
    frame = LocalFrame(*json.loads((stages / "georef.json").read_text())["frame"])
    grid = Grid(**json.loads((stages / "dsm.json").read_text())["grid"])
    models = sfm.load_models(out / "work" / "georef")
    sparse, _ = points(models)
    views = load_views(models, Path(report.photos_dir))
    lo, hi = sparse[:, :2].min(axis=0), sparse[:, :2].max(axis=0)
    up = (float(sparse[:, 2].min()) - 20.0, float(sparse[:, 2].max()) + 20.0)
    to_utm = EnuToUtm(frame, grid.epsg, (lo[0], lo[1], hi[0], hi[1]), up)
    paths = {v.name: v.path for v in views}
    first, _ = dense_dsm(views, paths, sparse, to_utm, grid, fill_scales=(), band_fill=False)
    both, cloud = dense_dsm(views, paths, sparse, to_utm, grid)
    assert cloud.fills[0]["band"] and cloud.fills[0]["cells_added"] > 0
    kept = np.isfinite(first.surface_m)
    assert np.array_equal(both.surface_m[kept], first.surface_m[kept])
    added = np.isfinite(both.surface_m) & ~kept
    assert added.sum() == sum(f["cells_added"] for f in cloud.fills) > 0
    rows, cols = np.nonzero(added)
    east, north = grid.centres_m(rows, cols)
    to_enu = UtmToEnu(scene.frame, grid.epsg, grid.bounds_m)  # the truth's frame (the model's is the survey's)
    enu = to_enu(np.asarray(east, float), np.asarray(north, float), both.surface_m[rows, cols].astype(float))
    errors = np.abs(enu[:, 2] - scene.height_at(enu[:, 0], enu[:, 1]))
    # Coarse passes smear roofs and crowns into the ground beside them; without the
    # smooth-ground and rim checks 10 % of the filled cells here were 9-10 m off, and the
    # mirrored band without them 16 % over 1 m (edge matches on the photos' borders).
    assert float(np.nanmedian(errors)) <= 0.3
    assert float(np.nanpercentile(errors, 90)) <= 1.0
