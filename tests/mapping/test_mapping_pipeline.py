"""End to end on six real Seneca photos (one flight line), plus a corrupt and a GPS-less one.

Bounds: the photos' consumer GPS is good to a few metres, so camera centres fitted by a
similarity must agree with it within 5 m RMS; SfM with SIFT at 800 px reaches well under
1 px mean reprojection error; the ground is ~64 m below the cameras (Seneca flew ~283 m
AMSL over ~219 m AMSL fields), so the DSM must sit 40-90 m below the GPS altitudes.
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
        b = ds.bounds
        # The mosaic covers every camera's nadir point, and is not much larger than the
        # strip: 150 m of flight line plus one footprint (about 85 m x 65 m at 64 m AGL).
        assert np.all((east > b.left) & (east < b.right) & (north > b.bottom) & (north < b.top))
        assert (b.right - b.left) < 300 and (b.top - b.bottom) < 300
        alpha = ds.read(4, out_shape=(ds.height // 8, ds.width // 8))
        assert 0.2 < (alpha > 0).mean() < 1.0
    assert 3.0 < report.gsd_cm < 12.0
    with rasterio.open(out / "dsm.tif") as ds:
        assert ds.crs.to_epsg() == 32617
        dsm = ds.read(1, masked=True)
    cam_alt = np.array([f["properties"]["gps_alt_amsl_m"] for f in cams if f["properties"]["gps_alt_amsl_m"]])
    depth = cam_alt.mean() - float(np.ma.median(dsm))
    assert 40.0 < depth < 90.0


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
