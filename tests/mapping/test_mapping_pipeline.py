"""End to end on six real Seneca photos (one flight line), plus a corrupt and a GPS-less one.

Bounds: the photos' consumer GPS is good to a few metres, so camera centres fitted by a
similarity must agree with it within 5 m RMS; SfM with SIFT at 800 px reaches well under
1 px mean reprojection error. Heights: see test_geotiff_crs_and_extent.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from skyfix.errors import InputError
from skyfix.mapping.pipeline import PipelineConfig, run_pipeline

DATA = Path(__file__).parents[1] / "data" / "seneca"
GOOD = sorted(DATA.glob("*.jpg"))
FAST = {"max_image_size_px": 1200, "max_features": 4000, "threads": 2}
FOCAL_PX = 836.30  # 4.3 mm x 1200 px / 6.17 mm (the 1/2.3-inch sensor of the sensor table), held in BA:
# the photos' focal-plane resolution implies a 5.58 mm sensor (it was divided by 3 for a
# 4000 -> 1200 px downscale), which made the focal length 11 % long (925.09 px).
# Flying height above the ground: 62.5 m, the full Seneca survey's reconstruction (32 photos,
# three lines, whose cross-line baselines fix the tilt: GSD 7.4 cm at 836 px, mapping/README,
# benchmarks/mapping.py, run of 28 Nov 2026 17:45 UTC; 64.8 m with the 925 px focal length).
# One line of six photos leaves each model's pitch to the photos
# alone over flat fields: 1 deg of pitch moves the ground 16 px against the ~370 px of
# parallax between neighbours, 4.4 % (2.8 m) of the depth. This line's two three-photo
# models put their sparse ground 63 and 70 m below their cameras (run of 28 Nov 2026,
# 15:03 UTC, 925 px), 1.5-2 deg of pitch apart; 7 m covers that. A 10 m height error (a focal
# length 15 % off, a datum applied twice) falls outside.
FLYING_HEIGHT_M, FLYING_HEIGHT_TOL_M = 62.5, 7.0


@pytest.fixture(scope="module")
def photos_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("photos")
    for p in GOOD:
        shutil.copy(p, folder / p.name)
    (folder / "IMG_9998.jpg").write_text("not a photo")
    (folder / "IMG_9999.jpg").write_bytes(GOOD[0].read_bytes()[:50_000])  # truncated
    return folder


@pytest.fixture(scope="module")
def run(photos_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("project")
    return run_pipeline(PipelineConfig(photos_dir, out, **FAST)), out


def test_registers_and_georeferences(run):
    report, _ = run
    assert len(report.photos_used) == 6
    assert len(report.registered) >= 5
    assert len(report.models) >= 1
    assert report.mean_reprojection_error_px <= 1.0
    assert report.georeferenced
    assert report.georef_rms_m <= 5.0
    assert report.crs_epsg == 32617  # Ohio, 83.3 W: UTM zone 17 N


def test_bad_photos_reported(run):
    report, out = run
    reasons = {r["photo"]: r["reason"] for r in report.rejected}
    assert set(reasons) == {"IMG_9998.jpg", "IMG_9999.jpg"}
    assert "truncated" in reasons["IMG_9999.jpg"] and "JPEG" in reasons["IMG_9998.jpg"]
    assert report.photos_found == 8 and report.without_gps == []
    saved = json.loads((out / "report.json").read_text())
    assert {r["photo"] for r in saved["rejected"]} == set(reasons)
    assert any("rejected IMG_9999.jpg" in w for w in saved["warnings"])


def test_geotiff_crs_and_extent(run):
    import rasterio
    from pyproj import Transformer

    report, out = run
    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32617", always_xy=True)
    cams = json.loads((out / "cameras.geojson").read_text())["features"]
    lon, lat = np.array([f["geometry"]["coordinates"][:2] for f in cams]).T
    east, north = to_utm.transform(lon, lat)
    with rasterio.open(out / "orthophoto.tif") as ds:
        assert ds.crs.to_epsg() == 32617
        assert ds.count == 4 and ds.overviews(1)
        assert ds.colorinterp[3] == rasterio.enums.ColorInterp.alpha  # nodata is transparent
        b = ds.bounds
        # The mosaic covers every camera's nadir point, and each photo's footprint (1200 x
        # 900 px at the GSD, any heading): on each axis it spans the cameras plus at least
        # the footprint's short side and at most its diagonal (1500 px).
        assert np.all((east > b.left) & (east < b.right) & (north > b.bottom) & (north < b.top))
        gsd_m = report.gsd_cm / 100.0
        for extent_m, cameras_m in ((b.right - b.left, np.ptp(east)), (b.top - b.bottom, np.ptp(north))):
            assert cameras_m + 900 * gsd_m - 2.0 <= extent_m <= cameras_m + 1500 * gsd_m + 2.0
        alpha = ds.read(4, out_shape=(ds.height // 8, ds.width // 8))
        assert 0.2 < (alpha > 0).mean() < 1.0
    with rasterio.open(out / "dsm.tif") as ds:
        assert ds.crs.to_epsg() == 32617
        dsm = ds.read(1, masked=True)
    cam_alt = np.array([f["properties"]["gps_alt_amsl_m"] for f in cams if f["properties"]["gps_alt_amsl_m"]])
    depth = cam_alt.mean() - float(np.ma.median(dsm))
    assert abs(depth - FLYING_HEIGHT_M) <= FLYING_HEIGHT_TOL_M, depth
    # GSD = the cameras' height above the DSM / the focal length. The report takes the
    # model's camera heights, ``depth`` the GPS ones: they differ by the model's vertical
    # residuals to GPS (under 1 m RMS here), so 2 m; and the band follows from the height's.
    assert abs(report.gsd_cm / 100.0 * FOCAL_PX - depth) <= 2.0
    assert (FLYING_HEIGHT_M - FLYING_HEIGHT_TOL_M) / FOCAL_PX < report.gsd_cm / 100.0 \
        < (FLYING_HEIGHT_M + FLYING_HEIGHT_TOL_M) / FOCAL_PX


def test_point_cloud_and_report_files(run):
    _, out = run
    head = (out / "points.ply").read_bytes()[:400].decode("ascii", "replace")
    n = int(head.split("element vertex ")[1].split("\n")[0])
    assert n > 200
    assert (out / "report.png").stat().st_size > 10_000
    assert (out / "orthophoto.png").stat().st_size > 10_000


def test_rerun_resumes_everything(run, photos_dir):
    report, out = run
    again = run_pipeline(PipelineConfig(photos_dir, out, **FAST))
    assert {"features", "matches", "mapping", "georef", "dsm", "ortho", "export"} <= set(again.resumed_stages)
    assert again.registered == report.registered


def test_empty_folder(tmp_path):
    (tmp_path / "in").mkdir()
    with pytest.raises(InputError, match="no JPEG"):
        run_pipeline(PipelineConfig(tmp_path / "in", tmp_path / "out"))
    saved = json.loads((tmp_path / "out" / "report.json").read_text())
    assert "no JPEG" in saved["error"] and saved["photos_found"] == 0


def _frame_and_photos(out, photos_dir):
    from skyfix.geo import LocalFrame
    from skyfix.mapping.photos import load_photos

    frame = LocalFrame(*json.loads((out / "work" / "stages" / "georef.json").read_text())["frame"])
    return frame, load_photos(photos_dir)[0]


def _placed_by_two_view(run, photos_dir, tmp_path, photo: str, photos=None):
    """``photo`` taken out of the main model and placed again by its two-view model with
    its best registered partner: (pair model, PairModel, attach_pair's verdict, main model)."""
    from skyfix.mapping import sfm
    from skyfix.mapping.georef import ModelGeoref, attach_pair

    report, out = run
    frame, own_photos = _frame_and_photos(out, photos_dir)
    m = report.models[0]
    inliers = sorted(set(m["residuals_enu_m"]) - set(m["outliers"]))
    main = sfm.load_models(out / "work" / "georef")[0]
    main_georef = ModelGeoref(0, m["registered"], True, inliers=inliers, residuals_enu_m=m["residuals_enu_m"])
    without = sfm.load_models(out / "work" / "georef")[0]
    without.deregister_frame(next(im.frame_id for im in without.images.values() if im.name == photo))
    [(pair_rec, pair)] = sfm.pair_models(out / "work" / "database.db", photos_dir, tmp_path, {photo}, [without])
    found = attach_pair(pair_rec, main, main_georef, pair, photos or own_photos, frame, 1)
    return pair_rec, pair, found, main


def test_photo_overlapping_one_neighbour_joins_the_line(run, photos_dir, tmp_path):
    # IMG_0474 starts the line: it overlaps only IMG_0475 (no third photo sees that ground).
    # COLMAP's mapper built 0477-0479, tried 0474+0475 alone (too small, discarded) and
    # stopped; the pass over the photos it left out starts from that pair (an initial pair
    # needs no third photo), grows through 0476-0477 and is joined: one model of all six.
    report, out = run
    assert len(report.models) == 1 and report.models[0]["registered"] == len(GOOD) == 6
    assert sorted(report.registered) == [p.name for p in GOOD] and report.registered_two_view == []
    names = [f["properties"]["photo"] for f in json.loads((out / "cameras.geojson").read_text())["features"]]
    assert sorted(names) == sorted(set(names))  # each photo once, even where two models shared it
    # Left out of the model, it is still placed by its two-view model with IMG_0475 (the
    # fallback for a photo no mapping pass places), within the 5 m GPS check.
    _, pair, found, _ = _placed_by_two_view(run, photos_dir, tmp_path, "IMG_0474.jpg")
    assert (pair.photo, pair.partner) == ("IMG_0474.jpg", "IMG_0475.jpg") and pair.inliers >= 30
    assert found.georeferenced, found.reason
    assert found.two_view["offset_m"] <= 5.0


def test_two_view_pose_agrees_with_bundle_adjusted_pose(run, photos_dir, tmp_path):
    # IMG_0479 is registered by the main model (bundle adjusted over the line); placed
    # again from its two-view model with IMG_0478 alone it must land on the same pose.
    # Centre: the two-view scale comes from the median ground depth under IMG_0478 (flat
    # fields, ~64 m), the ~56 m baseline then agrees to a few per cent -> within 3 m;
    # orientation: 776 inliers fix the relative rotation to well under a degree -> 1 deg.
    pair_rec, pair, found, main = _placed_by_two_view(run, photos_dir, tmp_path, "IMG_0479.jpg")
    assert (pair.photo, pair.partner) == ("IMG_0479.jpg", "IMG_0478.jpg")
    assert found.georeferenced, found.reason
    [placed] = [im for im in pair_rec.images.values() if im.has_pose]
    [truth] = [im for im in main.images.values() if im.name == "IMG_0479.jpg"]
    assert np.linalg.norm(placed.projection_center() - truth.projection_center()) < 3.0
    r_delta = placed.cam_from_world().rotation.matrix() @ truth.cam_from_world().rotation.matrix().T
    angle_deg = np.degrees(np.arccos(np.clip((np.trace(r_delta) - 1.0) / 2.0, -1.0, 1.0)))
    assert angle_deg < 1.0


def test_two_view_placement_inconsistent_with_gps_is_refused(run, photos_dir, tmp_path):
    # The same pair with IMG_0479's GPS moved 30 m east: the two-view model puts the photo
    # (scaled from the ground depth, not from GPS) ~30 m from that position, far beyond the
    # 5 m limit, so it is not counted.
    import dataclasses

    frame, photos = _frame_and_photos(run[1], photos_dir)
    moved = []
    for p in photos:
        if p.name == "IMG_0479.jpg":
            e, n, u = frame.to_enu_points(np.array([[p.gps_lat_deg, p.gps_lon_deg, p.gps_alt_amsl_m]]))[0]
            lat, lon, _ = frame.to_geodetic_points(np.array([[e + 30.0, n, u]]))[0]
            p = dataclasses.replace(p, gps_lat_deg=float(lat), gps_lon_deg=float(lon))
        moved.append(p)
    pair_rec, _, found, _ = _placed_by_two_view(run, photos_dir, tmp_path, "IMG_0479.jpg", moved)
    assert not found.georeferenced
    assert "from its GPS" in found.reason and found.two_view["offset_m"] > 20.0
    assert pair_rec.num_reg_images() == 2  # left as it was
