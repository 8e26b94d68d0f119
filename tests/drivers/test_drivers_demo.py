"""``skyfix demo`` flies end to end on the simulator and writes its files."""

from __future__ import annotations

import csv
import json

from skyfix.cli import main


def test_demo_runs_and_writes_files(tmp_path, capsys):
    assert main(["-q", "demo", "-o", str(tmp_path), "--speed", "8"]) == 0
    out = capsys.readouterr().out
    assert "FAILED" not in out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert all(summary["checks"].values()) and len(summary["checks"]) == 5
    # the GPS-less vehicle's autopilot estimate follows the injected 0.7 m-noise fixes
    assert summary["figures"]["gps_input_estimate_error_rms_m"] < 1.5
    assert (tmp_path / "trajectory.png").stat().st_size > 20_000
    rows = list(csv.DictReader(open(tmp_path / "trajectory.csv")))
    assert {r["system_id"] for r in rows} == {"1", "2", "3"}
    injected = [r for r in rows if r["gps_input"] == "1"]
    assert injected and all(r["system_id"] == "2" for r in injected)
    assert any(r["mode"] == "RTL" and r["system_id"] == "3" for r in rows)
