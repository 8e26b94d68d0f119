import csv
import json

import cv2
import numpy as np

from skyfix.cli import main
from skyfix.datasets.tag_scene import SceneEffects, field_texture, render_tag_frame
from skyfix.tags.field import TagField


def test_generate_then_locate(tmp_path, camera):
    field_path = tmp_path / "field.json"
    assert main(["-q", "tags", "generate", "-o", str(field_path), "--rows", "8", "--cols", "8",
                 "--time-limit-s", "0.5", "--dpi", "20"]) == 0
    assert field_path.with_suffix(".png").is_file() and field_path.with_suffix(".svg").is_file()
    field = TagField.load(field_path)
    fr = render_tag_frame(field_texture(field), camera, 0.9, 0.9, 1.3, 45.0, 2.0, -3.0,
                          effects=SceneEffects(noise_sigma=0.01), rng=np.random.default_rng(0))
    cv2.imwrite(str(tmp_path / "frame.png"), cv2.cvtColor(fr.image, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((480, 640, 3), 128, np.uint8))
    out = tmp_path / "fixes.csv"
    rc = main(["-q", "tags", "locate", str(tmp_path / "frame.png"), str(tmp_path / "grey.png"),
               "--field", str(field_path), "--hfov-deg", "60", "--roll-deg", "-3", "--pitch-deg", "2",
               "-o", str(out)])
    assert rc == 0
    rows = list(csv.DictReader(out.open()))
    assert [r["status"] for r in rows] == ["ok", "no_fix"]
    assert abs(float(rows[0]["x_m"]) - fr.x_m) < 0.01 and abs(float(rows[0]["y_m"]) - fr.y_m) < 0.01
    assert (tmp_path / "frame_tags.png").is_file() and (tmp_path / "grey_tags.png").is_file()


def test_locate_reads_camera_files_and_rescales_them(tmp_path, camera, caplog):
    """--camera takes skyfix.camera_io files: one calibrated at twice the frame size gives the
    same camera as --hfov-deg; an old fx/fy/cx/cy file without a size takes the frame's;
    a file of another aspect ratio is refused."""
    from skyfix.camera import Camera
    from skyfix.camera_io import save_camera

    field_path = tmp_path / "field.json"
    assert main(["-q", "tags", "generate", "-o", str(field_path), "--rows", "8", "--cols", "8",
                 "--time-limit-s", "0.5", "--dpi", "20"]) == 0
    fr = render_tag_frame(field_texture(TagField.load(field_path)), camera, 0.9, 0.9, 1.3, 45.0, 2.0, -3.0,
                          effects=SceneEffects(noise_sigma=0.01), rng=np.random.default_rng(0))
    cv2.imwrite(str(tmp_path / "frame.png"), cv2.cvtColor(fr.image, cv2.COLOR_RGB2BGR))
    save_camera(tmp_path / "big.json", Camera.from_fov(1280, 960, 60.0))
    (tmp_path / "old.json").write_text(json.dumps({"fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
                                                   "cy": camera.cy}))
    save_camera(tmp_path / "wide.json", Camera.from_fov(1280, 720, 60.0))
    fixes = {}
    for name, cam_args in (("hfov", ["--hfov-deg", "60"]), ("big", ["--camera", str(tmp_path / "big.json")]),
                           ("old", ["--camera", str(tmp_path / "old.json")])):
        out = tmp_path / f"{name}.csv"
        assert main(["-q", "tags", "locate", str(tmp_path / "frame.png"), "--field", str(field_path), *cam_args,
                     "--roll-deg", "-3", "--pitch-deg", "2", "-o", str(out)]) == 0
        (row,) = csv.DictReader(out.open())
        fixes[name] = [float(row[k]) for k in ("x_m", "y_m", "z_m", "yaw_deg")]
    # Same intrinsics up to float rounding of the rescale: same fix to the CSV's printed digits.
    assert fixes["big"] == fixes["hfov"] and fixes["old"] == fixes["hfov"]
    assert abs(fixes["hfov"][0] - fr.x_m) < 0.01
    assert main(["-q", "tags", "locate", str(tmp_path / "frame.png"), "--field", str(field_path),
                 "--camera", str(tmp_path / "wide.json"), "-o", str(tmp_path / "wide.csv")]) == 2
    assert "wide.json: camera is 1280x720 px but the image is 640x480 px" in caplog.text


def test_locate_unknown_field_fails_cleanly(tmp_path):
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((48, 64, 3), 128, np.uint8))
    assert main(["-q", "tags", "locate", str(tmp_path / "grey.png"), "--field", str(tmp_path / "nope.json"),
                 "--hfov-deg", "60"]) == 2


def test_board_and_dimension(tmp_path, capsys):
    assert main(["-q", "tags", "board", "-o", str(tmp_path / "b.json"), "--rows", "3", "--cols", "3",
                 "--dpi", "20"]) == 0
    assert (tmp_path / "b.png").is_file()
    assert main(["tags", "dimension", "--area-m", "5", "5", "--min-height-m", "1", "--max-height-m", "3"]) == 0
    assert '"pareto"' in capsys.readouterr().out
