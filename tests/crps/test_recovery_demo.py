"""``skyfix demo`` end to end: a drone loses GNSS, the helpers' cameras bring it home, the files open.

One seeded run of the whole flow (three services on the simulator, MAVLink over UDP, the swarm bus,
WorldCamera frames); the figures are checked against the issue's goals, the logs are replayed. The run is
the top README's own ``skyfix demo --seed 11`` (fixture ``readme_demo`` in tests/conftest.py: the command
runs once per session, as tests/test_readme_commands.py runs it).
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import re

import pytest

from skyfix.cli import main


@pytest.mark.slow
def test_demo_brings_the_lost_drone_home_and_writes_its_files(readme_demo):
    assert readme_demo.returncode == 0, readme_demo.stderr[-2000:]
    tmp_path, out = readme_demo.folder / "skyfix-demo", readme_demo.stdout
    assert "d2 landed home" in out and "open next:" in out and "A consistent estimate averages 3" in out
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["outcome"] == "home"
    assert report["landing_error_m"] <= 3.0                   # the landing goal
    assert report["loss_to_first_fused_fix_s"] <= 15.0        # helpers' cameras position it quickly
    assert report["max_recovery_error_h_m"] <= 5.0            # never flown on a fix further off than this
    assert report["min_separation_m"] >= 10.0                 # helpers kept their distance
    assert report["detection_share"] >= 0.5
    # the fused fix follows the truth within its stated covariance (3-D NEES averages ~3 when consistent)
    assert 0.1 < report["figures"]["recovery_mean_nees_3dof"] < 9.0
    # the error against the swarm's GNSS frame differs from the one against the truth by the shared GNSS error
    # (realistic receivers: 1.4 m per axis common), which the recorder must have seen
    common_m, frame_m = (report["figures"][k] for k in ("common_gnss_error_max_h_m", "max_recovery_error_gnss_frame_h_m"))
    assert 0.0 < common_m < 10.0 and abs(frame_m - report["max_recovery_error_h_m"]) <= common_m + 1e-9
    # the fix's largest error from the loss on counts every airborne sample, the recovering ones among them
    assert report["figures"]["fix_error_after_loss_max_h_m"] >= report["max_recovery_error_h_m"] - 1e-9
    events = [what for _, what in report["timeline"]]
    assert any("hold" in e for e in events) and any("return_home (positioned by helpers)" in e for e in events)
    assert any(e.startswith("d1: helping d2") or e.startswith("d3: helping d2") for e in events)
    assert any("released by d2" in e for e in events)  # helpers go back to their missions
    # a readable timeline: every release says why, on both sides
    assert all(re.search(r"released by d2 \(.+\)", e) for e in events if "released by d2" in e), events
    assigned = [e.split("helpers assigned: ")[1] for e in events if e.startswith("d2: helpers assigned: ")]
    for before, now in itertools.pairwise(assigned):  # a helper that left is named with its reason
        kept, _, why = now.partition(" (")
        for helper in set(before.partition(" (")[0].split(", ")) - set(kept.split(", ")) - {"none"}:
            assert f"{helper} " in why, (before, now)
    rows = list(csv.DictReader(open(tmp_path / "trajectory.csv")))
    assert rows and {"d1_east_m", "d2_east_m", "d3_east_m", "fused_east_m"} <= set(rows[-1]) | set(rows[len(rows) // 2])
    assert (tmp_path / "trajectory.png").stat().st_size > 20_000
    # every drone's onboard log replays (d2's fusion reproduced from its MCAP)
    assert main(["-q", "fusion", "replay", str(tmp_path / "d2.mcap"), "-o", str(tmp_path / "replay")]) == 0
    assert (tmp_path / "replay" / "trajectory.png").exists()
    assert math.isfinite(report["figures"]["wall_s"])


def test_demo_output_naming_a_file_is_a_one_line_error(tmp_path, capsys):
    target = tmp_path / "afile"
    target.write_text("x")
    assert main(["-q", "demo", "-o", str(target)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "afile" in err[0] and "Traceback" not in err[0]
