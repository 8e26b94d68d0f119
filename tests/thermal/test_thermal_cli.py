"""``skyfix thermal``: simulate -> locate -> GeoJSON near the truth; detect; help; errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from skyfix.cli import main
from skyfix.geo import inverse


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("flight")
    assert main(["-q", "datasets", "thermal-flight", str(out), "--fires", "2", "--frames", "10", "--size", "320x256",
                 "--agl", "60", "--dropout", "0.0", "--smoke", "0.0", "--seed", "3"]) == 0
    return out


def test_simulate_then_locate_finds_the_fires(flight, tmp_path, capsys):
    out = tmp_path / "fires.geojson"
    rc = main(["-q", "thermal", "locate", str(flight / "frames"), "--poses", str(flight / "poses.csv"),
               "--camera", str(flight / "camera.json"), "--ground-alt", "30", "-o", str(out)])
    assert rc == 0
    assert "fire(s) from 10 frame(s)" in capsys.readouterr().out
    feats = json.loads(out.read_text())["features"]
    points = [f for f in feats if f["geometry"]["type"] == "Point"]
    assert any(f["geometry"]["type"] == "LineString" for f in feats)
    truth = json.loads((flight / "truth.json").read_text())["fires"]
    assert len(points) == len(truth) == 2
    for t in truth:
        errs = [float(inverse(t["lat_deg"], t["lon_deg"], p["geometry"]["coordinates"][1],
                              p["geometry"]["coordinates"][0])[1]) for p in points]
        # Perfect poses: centimetres; the bound leaves room for perspective and growth.
        assert min(errs) < 0.3
    assert (tmp_path / "fires_map.png").stat().st_size > 1000
    assert (tmp_path / "fires_last_frame.png").stat().st_size > 1000
    assert all(p["properties"]["alt_datum"] == "WGS84 ellipsoid" for p in points)


def test_detect_command(flight, tmp_path):
    out = tmp_path / "hotspots.geojson"
    frames = sorted((flight / "frames").glob("*.png"))[:3]
    rc = main(["-q", "thermal", "detect", *map(str, frames), "--pose", str(flight / "poses.csv"),
               "--camera", str(flight / "camera.json"), "--ground-alt", "30", "-o", str(out)])
    assert rc == 0
    feats = json.loads(out.read_text())["features"]
    assert len(feats) >= 3 and {f["properties"]["frame"] for f in feats} == {p.name for p in frames}
    assert out.with_suffix(".png").exists()


def test_simulated_camera_file_is_the_one_format_and_old_files_still_read(flight, tmp_path):
    raw = json.loads((flight / "camera.json").read_text())
    assert {"fx_px", "fy_px", "cx_px", "cy_px"} <= set(raw) and raw["model"] == "pinhole"
    assert (raw["width"], raw["height"]) == (320, 256)
    # A camera file in the form thermal wrote before skyfix.camera_io (fx, fy, cx, cy) locates
    # the same fires, to the last digit.
    legacy = {"width": raw["width"], "height": raw["height"], "fx": raw["fx_px"], "fy": raw["fy_px"],
              "cx": raw["cx_px"], "cy": raw["cy_px"]}
    (tmp_path / "legacy.json").write_text(json.dumps(legacy))
    outs = []
    for cam in (flight / "camera.json", tmp_path / "legacy.json"):
        outs.append(tmp_path / f"{cam.stem}.geojson")
        assert main(["-q", "thermal", "locate", str(flight / "frames"), "--poses", str(flight / "poses.csv"),
                     "--camera", str(cam), "--ground-alt", "30", "-o", str(outs[-1])]) == 0
    assert outs[0].read_text() == outs[1].read_text()


def test_ground_must_be_unambiguous(flight, tmp_path):
    base = ["-q", "thermal", "locate", str(flight / "frames"), "--poses", str(flight / "poses.csv"),
            "--camera", str(flight / "camera.json"), "-o", str(tmp_path / "x.geojson")]
    assert main(base) == 2
    assert main([*base, "--ground-alt", "30", "--ground-amsl", "63"]) == 2
    assert main([*base, "--ground-amsl", "63"]) == 2  # no geoid undulation


def test_ambiguous_pose_columns_are_refused(flight, tmp_path):
    csv = (flight / "poses.csv").read_text().replace("alt_ellipsoid_m", "alt", 1)
    (tmp_path / "poses.csv").write_text(csv)
    rc = main(["-q", "thermal", "locate", str(flight / "frames"), "--poses", str(tmp_path / "poses.csv"),
               "--camera", str(flight / "camera.json"), "--ground-alt", "30", "-o", str(tmp_path / "x.geojson")])
    assert rc == 2


@pytest.mark.parametrize("sub", [[], ["detect"], ["locate"], ["simulate"]])
def test_help(sub, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["thermal", *sub, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "usage: skyfix thermal" in text
    if sub in (["detect"], ["locate"]):
        assert "--ground-alt" in text and "ellipsoid" in text


@pytest.mark.slow
def test_mountain_flight_joint_locate_outputs_and_dem_coverage(tmp_path, capsys, caplog):
    import csv

    sim = tmp_path / "mt"
    assert main(["-q", "datasets", "thermal-flight", str(sim), "--mountain", "orbit", "--frames", "20", "--fires", "2",
                 "--size", "320x256", "--seed", "5"]) == 0
    out = tmp_path / "out" / "fires.geojson"
    common = ["-q", "thermal", "locate", str(sim / "frames"), "--poses", str(sim / "poses.csv"), "--camera",
              str(sim / "camera.json"), "--dem-datum", "amsl", "--joint", "-o", str(out)]
    assert main(common + ["--dem", str(sim / "dem.tif")]) == 0
    truth = json.loads((sim / "truth.json").read_text())
    feats = json.loads(out.read_text())["features"]
    points = [f for f in feats if f["geometry"]["type"] == "Point"]
    ellipses = [f for f in feats if f["geometry"]["type"] == "Polygon"]
    assert len(points) == len(ellipses) == len(truth["fires"]) == 2
    assert {"first_seen_s", "last_seen_s", "ellipse95_semi_major_m"} <= set(points[0]["properties"])
    for t in truth["fires"]:
        errs = [float(inverse(t["lat_deg"], t["lon_deg"], p["geometry"]["coordinates"][1],
                              p["geometry"]["coordinates"][0])[1]) for p in points]
        k = int(np.argmin(errs))
        # A consumer drone's GNSS wander (1.5 m) is not averaged away in 20 s: a few metres,
        # which the stated covariance carries. sqrt(11.6 / 5.99) = 1.39: inside the 99.7 %
        # ellipse's major axis.
        a95_m = points[k]["properties"]["ellipse95_semi_major_m"]
        assert errs[k] < 6.0 and errs[k] < 1.39 * a95_m
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    assert len(rows) == 2
    assert sorted(float(r["ellipse95_semi_major_m"]) for r in rows) == pytest.approx(
        sorted(p["properties"]["ellipse95_semi_major_m"] for p in points), abs=1e-3)
    # The calibration: 20 s of orbit pins little, but what it states covers the truth
    # (3-dof chi-square 99.7 % for the boresight, 3 sigma for the clock).
    cal = json.loads((out.parent / "fires_calibration.json").read_text())
    d = np.array(cal["boresight_deg"]) - truth["boresight_deg"]
    assert d @ np.linalg.solve(np.array(cal["boresight_cov_deg2"]), d) < 14.2
    assert abs(cal["time_offset_s"] - truth["time_offset_s"]) < 3 * cal["time_offset_sigma_s"]
    assert (out.parent / "fires_map.png").stat().st_size > 5000
    # A DEM that does not cover the flight: one error line naming it (skyfix's CLI exit
    # status for a refused input is 2).
    import rasterio
    from rasterio.transform import from_origin

    far = tmp_path / "far.tif"
    with rasterio.open(far, "w", driver="GTiff", width=20, height=20, count=1, dtype="float32", crs="EPSG:32632",
                       transform=from_origin(100000.0, 5000000.0, 10.0, 10.0)) as dst:
        dst.write(np.full((20, 20), 500.0, np.float32), 1)
    caplog.clear()
    assert main(common + ["--dem", str(far)]) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "does not cover the flight" in errors[0] and "poses.csv" in errors[0]


def _locate(frames_dir, flight, out):
    return main(["-q", "thermal", "locate", str(frames_dir), "--poses", str(flight / "poses.csv"),
                 "--camera", str(flight / "camera.json"), "--ground-alt", "30", "-o", str(out)])


def test_locate_refuses_a_folder_without_frames(flight, tmp_path, caplog):
    (tmp_path / "empty").mkdir()
    (tmp_path / "text").mkdir()
    (tmp_path / "text" / "notes.txt").write_text("no frames here")
    for folder, said in (("missing", "does not exist"), ("empty", "holds no frame"), ("text", "holds no frame")):
        caplog.clear()
        assert _locate(tmp_path / folder, flight, tmp_path / "x.geojson") == 2
        errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
        assert len(errors) == 1 and said in errors[0] and folder in errors[0]
    assert not (tmp_path / "x.geojson").exists()


def test_locate_names_frames_without_pose_rows_and_missing_frames(flight, tmp_path, caplog):
    import shutil

    frames = tmp_path / "frames"
    shutil.copytree(flight / "frames", frames)
    (frames / "00001.png").unlink()
    shutil.copy(frames / "00002.png", frames / "stray.png")
    assert _locate(frames, flight, tmp_path / "x.geojson") == 0
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("listed in" in m and "are not in" in m and "00001.png" in m for m in said)
    assert not any("no row" in m and "00001.png" in m for m in said)  # a missing file is not a missing row
    assert any("have no row in" in m and "stray.png" in m for m in said)


def test_thermal_simulate_is_a_deprecated_alias_that_says_where_it_went(tmp_path, caplog):
    args = [str(tmp_path), "--fires", "1", "--frames", "2", "--size", "160x128"]
    assert main(["-q", "thermal", "simulate", *args]) == 0
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("deprecated" in m and "skyfix datasets thermal-flight" in m for m in said)
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["00000.png", "00001.png"]


def test_simulate_refuses_a_used_folder_unless_overwrite(tmp_path):
    args = ["-q", "datasets", "thermal-flight", str(tmp_path), "--fires", "1", "--frames", "2", "--size", "160x128"]
    assert main(args) == 0
    (tmp_path / "frames" / "99999.png").write_bytes(b"old")
    assert main(args) == 2
    assert main([*args, "--overwrite"]) == 0
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["00000.png", "00001.png"]
