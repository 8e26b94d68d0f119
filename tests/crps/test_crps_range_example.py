"""``skyfix crps range`` on the example image the repository ships, and on a truncated copy of it."""

from __future__ import annotations

import json
from pathlib import Path

from skyfix.cli import main

EXAMPLE = Path(__file__).resolve().parents[2] / "crps" / "examples" / "drone_sky_40m.jpg"


def test_the_readme_ranging_example_finds_the_drone_at_40_m(tmp_path):
    # the README's command (a 0.5 m quad rendered 40.0 m away, pose as documented)
    assert main(["-q", "crps", "range", str(EXAMPLE), "--camera", "60", "--size-m", "0.5",
                 "--pose", "46.52,6.63,420,0,0,32,8", "-o", str(tmp_path / "r")]) == 0
    (det,) = json.loads((tmp_path / "r.json").read_text())["detections"]
    assert abs(det["range_m"] - 40.0) < 2.0 * det["range_sigma_m"]


def test_a_truncated_jpeg_is_a_one_line_error(tmp_path, capsys):
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(EXAMPLE.read_bytes()[: EXAMPLE.stat().st_size // 2])
    assert main(["-q", "crps", "range", str(cut), "--camera", "60", "--size-m", "0.5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cut.jpg" in err[0] and "truncated" in err[0]
    assert not (tmp_path / "cut_range.json").exists()
