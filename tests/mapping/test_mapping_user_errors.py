"""Issue 20 (a first hour without surprises) for lens, plan and map: one-line errors naming
the flag, no third-party chatter, limits checked before the work, missions that start
with home, split surveys that start near the drones, progress on long stages."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skyfix.cli import main
from skyfix.geo import destination

DATA = Path(__file__).parent / "data"
LAT0, LON0 = 40.6303, -8.6575
CORNERS = ["40.6303,-8.6575", "40.6303,-8.65717", "40.630615,-8.6575"]  # 28 m x 35 m


def _at(bearing_deg: float, dist_m: float) -> tuple[float, float]:
    lat, lon = destination(LAT0, LON0, bearing_deg, dist_m)
    return float(lat), float(lon)


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


@pytest.mark.parametrize("step", ["0.01", "0.1"])
def test_step_too_fine_for_a_mission_is_refused_up_front(step, tmp_path, capsys):
    # 0.01 m over 28 x 35 m is 9.8 million waypoints (killed for memory before); a MAVLink
    # mission numbers its items with a uint16, so the limit is checked before any array exists.
    rc = main(["plan", "corners", "--corners", *CORNERS, "--step", step, "--alt", "10", "-o", str(tmp_path / "p")])
    line = _one_error_line(capsys)
    assert rc == 2 and "--step" in line and "step_m" not in line and "waypoints" in line
    assert not (tmp_path / "p").exists()


def test_errors_name_the_flags_not_the_parameters(tmp_path, capsys):
    rc = main(["plan", "corners", "--corners", *CORNERS, "--step", "7", "--alt", "10", "--hold", "-3",
               "-o", str(tmp_path / "p")])
    line = _one_error_line(capsys)
    assert rc == 2 and "--hold" in line and "hold_s" not in line
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(DATA / "IMG_0459.jpg", src)
    rc = main(["lens", "correct", str(src), str(tmp_path / "out"), "--barrel", "0.1 -0.32 0", "--quality", "300"])
    line = _one_error_line(capsys)
    assert rc == 2 and "--quality" in line and "jpeg_quality" not in line


@pytest.mark.parametrize(("flag", "value"), [("--sfm-threads", "0"), ("--threads", "-4"), ("--match-threads", "0")])
def test_map_thread_counts_checked_before_colmap(flag, value, tmp_path, capsys):
    # COLMAP aborts the whole process on a thread count of 0 or below -1 (a CHECK, no exception).
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(DATA / "IMG_0459.jpg", src)
    rc = main(["map", str(src), "-o", str(tmp_path / "m"), flag, value])
    line = _one_error_line(capsys)
    assert rc == 2 and flag in line and value in line and "sfm_threads" not in line and "match_threads" not in line


@pytest.mark.parametrize("polygon", ["bad.geojson", "area.txt", "missing.geojson", "40.1,-8.1;40.2"])
def test_polygon_that_is_not_geojson_is_one_line(polygon, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.geojson").write_text("not json")
    (tmp_path / "area.txt").write_text('{"type": "Point", "coordinates": [1, 2]}')
    rc = main(["plan", "polygon", "--polygon", polygon, "--hfov", "60", "--size", "1200x900", "--alt", "60",
               "-o", "out"])
    line = _one_error_line(capsys)
    assert rc == 2 and "--polygon" in line


def test_split_survey_starts_near_drones_waiting_at_one_edge():
    # Both drones wait at the south-west corner of a 300 x 170 m field whose default line
    # layout starts at the north edge: before, both parts began ~170 m away. Now the part
    # nearest them starts at the lines' corner next to them: the turn-around margin along
    # the line and half a line spacing across it (plus the 14 m the drones stand off).
    from skyfix.camera import Camera
    from skyfix.mapping.split import split_survey
    from skyfix.mapping.survey import plan_polygon

    area = [(40.6303, -8.6575), (40.6303, -8.6540), (40.6318, -8.6540), (40.6318, -8.6575)]
    plan = plan_polygon(area, Camera.from_fov(1200, 900, 60.0), 60.0, 0.75, 0.65)
    drones = {"A": (40.6302, -8.6576), "B": (40.6302, -8.6575)}
    start_far = np.linalg.norm(plan.waypoints_en_m[0] - plan.frame.to_enu(40.6302, -8.6576, 0.0)[0:2])
    assert start_far > 150.0  # the layout as planned starts at the far edge
    parts = split_survey(plan, drones)
    near = min(p.approach_m for p in parts)
    assert near <= math.hypot(plan.turnaround_m, plan.step_m / 2.0) + 14.0 + 1.0
    assert sum(p.length_m for p in parts) == pytest.approx(plan.path_length_m, rel=1e-6)
    photos_before = len(plan.photo_positions_en_m()[0])
    assert sum(len(p.plan.photo_positions_en_m()[0]) for p in parts) == pytest.approx(photos_before, abs=2)


def test_plan_mission_files_start_with_home(tmp_path, capsys):
    # ArduPilot and Mission Planner take item 0 as home: a take-off there is lost.
    out = tmp_path / "p"
    drone = _at(225, 20)
    assert main(["plan", "corners", "--corners", *CORNERS, "--step", "7", "--alt", "10",
                 "--drone", f"A={drone[0]},{drone[1]}", "--drone", f"B={_at(0, 40)[0]},{_at(0, 40)[1]}",
                 "-o", str(out)]) == 0
    rows = [line.split("\t") for line in (out / "plan_A.waypoints").read_text().splitlines()[1:]]
    seq, current, frame, command = (int(v) for v in rows[0][:4])
    assert (seq, current, frame, command) == (0, 1, 0, 16)  # home: MAV_FRAME_GLOBAL, NAV_WAYPOINT
    assert (float(rows[0][8]), float(rows[0][9])) == pytest.approx(drone, abs=1e-7)
    assert int(rows[1][3]) == 22 and int(rows[1][2]) == 3  # TAKEOFF, relative altitude, as item 1


def test_torch_backend_without_torch_fails_once_before_any_photo(tmp_path, capsys, monkeypatch):
    src = tmp_path / "in"
    src.mkdir()
    for name in ("a.jpg", "b.jpg", "c.jpg"):
        shutil.copy(DATA / "IMG_0459.jpg", src / name)
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch raises ImportError
    rc = main(["lens", "correct", str(src), str(tmp_path / "out"), "--barrel", "0.1 -0.32 0", "--backend", "torch"])
    line = _one_error_line(capsys)
    assert rc == 2 and "torch" in line
    assert line.index("pip install torch") < line.index(".[gpu]")  # the README's order: torch first
    assert not (tmp_path / "out").exists()


def test_bad_photos_named_once_and_libjpeg_quiet(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    (src / "fake.jpg").write_text("hello")
    data = bytearray((DATA / "IMG_0459.jpg").read_bytes())
    data[len(data) // 2:len(data) // 2 + 20000] = bytes(20000)  # damaged scan data, end marker intact
    (src / "damaged.jpg").write_bytes(bytes(data))
    cmd = [sys.executable, "-m", "skyfix.cli", "lens", "correct", str(src), str(tmp_path / "out"),
           "--barrel", "0.1 -0.32 0"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert run.returncode == 1  # nothing corrected
    text = run.stdout + run.stderr
    assert "fake.jpg: corrupt JPEG" in text and "fake.jpg: fake.jpg" not in text
    assert "damaged.jpg: corrupt JPEG (Corrupt JPEG data" in text  # refused, with libjpeg's reason
    assert not any(line.startswith("Corrupt JPEG data") for line in text.splitlines())  # no raw libjpeg line
    run = subprocess.run([sys.executable, "-m", "skyfix.cli", "map", str(src), "-o", str(tmp_path / "m")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "fake.jpg: corrupt JPEG" in run.stderr and "fake.jpg: fake.jpg" not in run.stderr
    assert run.stderr.strip().splitlines()[-1].startswith("ERROR") and "Traceback" not in run.stderr


def test_features_and_matching_show_progress(tmp_path, capsys):
    from skyfix import progress
    from skyfix.mapping import sfm
    from skyfix.mapping.photos import load_photos

    photos_dir = tmp_path / "photos"
    photos_dir.mkdir()
    for p in sorted((DATA.parent.parent / "data" / "seneca").glob("*.jpg"))[1:4]:
        shutil.copy(p, photos_dir / p.name)
    photos, _ = load_photos(photos_dir)
    db = tmp_path / "database.db"
    progress.set_enabled(True)
    try:
        sfm.extract(db, photos_dir, photos, max_image_size_px=800, max_features=1000, threads=2)
        sfm.match(db, photos, threads=2)
    finally:
        progress.set_enabled(None)
    err = capsys.readouterr().err
    assert "map: features" in err and "3/3" in err
    assert "map: matching" in err


def test_map_prints_no_colmap_or_opencv_lines_unless_verbose(tmp_path):
    import re

    photos_dir = tmp_path / "photos"
    photos_dir.mkdir()
    for p in sorted((DATA.parent.parent / "data" / "seneca").glob("*.jpg"))[1:4]:
        shutil.copy(p, photos_dir / p.name)
    cmd = [sys.executable, "-m", "skyfix.cli", "map", str(photos_dir), "-o", str(tmp_path / "m"), "--threads", "2",
           "--max-image-size", "800", "--sparse-dsm"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    glog = re.compile(r"^[IWE]\d{8} ", re.MULTILINE)  # glog's line prefix (COLMAP, Ceres)
    assert not glog.search(run.stdout + run.stderr)
    assert "Bundle adjustment report" not in run.stdout + run.stderr
