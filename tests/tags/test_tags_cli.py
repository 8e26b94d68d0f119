import csv

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


def test_locate_unknown_field_fails_cleanly(tmp_path):
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((48, 64, 3), 128, np.uint8))
    assert main(["-q", "tags", "locate", str(tmp_path / "grey.png"), "--field", str(tmp_path / "nope.json"),
                 "--hfov-deg", "60"]) == 1


def test_board_and_dimension(tmp_path, capsys):
    assert main(["-q", "tags", "board", "-o", str(tmp_path / "b.json"), "--rows", "3", "--cols", "3",
                 "--dpi", "20"]) == 0
    assert (tmp_path / "b.png").is_file()
    assert main(["tags", "dimension", "--area-m", "5", "5", "--min-height-m", "1", "--max-height-m", "3"]) == 0
    assert '"pareto"' in capsys.readouterr().out
