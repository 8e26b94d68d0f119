"""The 'skyfix lens' and 'skyfix plan' commands write the files they promise."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from skyfix.cli import main
from skyfix.geo import destination

DATA = Path(__file__).parent / "data"
LAT0, LON0 = 40.6303, -8.6575


def _ll(bearing_deg: float, dist_m: float) -> str:
    lat, lon = destination(LAT0, LON0, bearing_deg, dist_m)
    return f"{float(lat):.8f},{float(lon):.8f}"


def test_help_lists_subcommands(capsys):
    for argv in (["lens", "--help"], ["plan", "--help"], ["lens", "correct", "--help"], ["plan", "extend", "--help"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "correct" in out and "calibrate" in out and "handoff" in out and "50 %" in out


def test_lens_correct_writes_photos_report_and_camera(tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(DATA / "IMG_0459.jpg", src)
    (src / "bad.jpg").write_bytes(b"\xff\xd8 not really")
    out = tmp_path / "out"
    assert main(["-q", "lens", "correct", str(src), str(out), "--barrel", "0.1 -0.32 0", "--workers", "1"]) == 0
    assert (out / "IMG_0459.jpg").is_file() and (out / "correction_preview.png").is_file()
    report = json.loads((out / "correction_report.json").read_text())
    assert report["written"] == 1 and report["skipped"][0]["photo"].endswith("bad.jpg")
    cam = json.loads((out / "camera.json").read_text())
    assert cam["width"] == 1200 and cam["fx_px"] == pytest.approx(4.3 * 1200 / 6.17 / 1.22, rel=1e-4)  # sensor table (EXIF focal plane off)
    assert "skipped" in capsys.readouterr().out
    assert main(["-q", "lens", "correct", str(src), str(out), "--barrel", "0.1 -0.32"]) == 2  # bad coefficients: input error


def test_lens_convert(tmp_path, capsys):
    assert main(["lens", "convert", "--barrel", "0.1 -0.32 0", "--size", "1200x900", "-o", str(tmp_path / "c.json")]) == 0
    assert "OpenCV k1=" in capsys.readouterr().out
    assert main(["lens", "convert", "--calibration", str(tmp_path / "c.json")]) == 0
    assert "ImageMagick barrel" in capsys.readouterr().out


def test_plan_corners_extend_and_handoff(tmp_path):
    p1, p2, p3 = tmp_path / "p1", tmp_path / "p2", tmp_path / "p3"
    assert main(["-q", "plan", "corners", "--corners", f"{LAT0},{LON0}", _ll(90, 28), _ll(0, 35),
                 "--step", "7", "--alt", "10", "-o", str(p1)]) == 0
    assert json.loads((p1 / "plan_summary.json").read_text())["waypoints"] == 30
    assert main(["-q", "plan", "extend", str(p1 / "plan.json"), "--alarm", _ll(45, 20), "--joining", "2",
                 "--drone", f"A={LAT0},{LON0}", "--drone", f"B={_ll(0, 60)}", "--drone", f"C={_ll(90, 60)}",
                 "-o", str(p2)]) == 0
    summary = json.loads((p2 / "plan_summary.json").read_text())
    assert summary["waypoints"] == 56 and len(summary["parts"]) == 3
    for name in ("plan.geojson", "plan.kml", "plan.png", "plan_A.waypoints", "plan_B.waypoints", "plan_C.waypoints"):
        assert (p2 / name).is_file()
    assert main(["-q", "plan", "handoff", str(p2 / "plan.json"), "--next-index", "10",
                 "--available", f"X={_ll(0, 10)}", "-o", str(p3)]) == 0
    assert json.loads((p3 / "plan_summary.json").read_text())["handed_to"] == "X"


def test_plan_polygon_reports_coverage(tmp_path):
    out = tmp_path / "poly"
    poly = ";".join([f"{LAT0},{LON0}", _ll(90, 150), _ll(45, 160), _ll(0, 100)])
    assert main(["-q", "plan", "polygon", "--polygon", poly, "--hfov", "70", "--size", "4000x3000", "--alt", "50",
                 "--forward", "0.8", "--side", "0.7", "-o", str(out)]) == 0
    cov = json.loads((out / "plan_summary.json").read_text())["coverage"]
    assert cov["uncovered_m2"] == pytest.approx(0.0, abs=1e-6)
    assert cov["forward_overlap_min"] > 0.799 and cov["side_overlap_min"] > 0.699
    assert main(["-q", "plan", "polygon", "--polygon", poly, "--hfov", "70", "--size", "4000x3000", "--alt", "50",
                 "--side", "1.0", "-o", str(out)]) == 2  # out-of-range overlap: input error


def test_lens_calibrate_from_rendered_board_photos(tmp_path, capsys):
    import cv2

    from skyfix.camera import Camera
    from skyfix.camera_io import load_camera
    from skyfix.datasets.calibration_scene import render_calibration_views
    from skyfix.distortion import BrownConrady
    from skyfix.mapping.board import BoardSpec

    truth = Camera(480, 360, 380.0, 380.0, 240.5, 178.5, BrownConrady(-0.2, 0.05))
    shots = tmp_path / "board"
    shots.mkdir()
    for i, view in enumerate(render_calibration_views(truth, BoardSpec(), 10, seed=5, supersample=2)):
        cv2.imwrite(str(shots / f"view{i:02d}.png"), view.image)
    (shots / "broken.png").write_bytes(b"not an image")
    cal = tmp_path / "cal.json"
    assert main(["lens", "calibrate", str(shots), "--cols", "10", "--rows", "7", "-o", str(cal)]) == 0
    cam = load_camera(cal)
    assert cam.fx == pytest.approx(380.0, rel=0.01) and cam.distortion.k1 == pytest.approx(-0.2, abs=0.02)
    assert json.loads(cal.read_text())["rms_px"] <= 0.1
    assert cal.with_suffix(".png").is_file()
    assert "reprojection RMS" in capsys.readouterr().out
