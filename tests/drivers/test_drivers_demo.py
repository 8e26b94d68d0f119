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
    assert all(summary["checks"].values()) and len(summary["checks"]) == 6
    # skyfix.fusion places the GPS-less vehicle from its velocity and two helpers' observations
    # (3 % range, 0.2 deg bearing at 5-20 m: decimetres) plus telemetry time-stamp jitter of a
    # simulator running 8x real time (0.35-0.8 m RMS seen); its autopilot follows the injected fixes
    assert summary["figures"]["fused_position_error_rms_m"] < 1.5
    assert summary["figures"]["gps_input_estimate_error_rms_m"] < 1.5
    assert summary["injected_position_source"].startswith("skyfix.fusion")
    assert main(["-q", "fusion", "replay", str(tmp_path / "fusion.jsonl"), "-o", str(tmp_path / "replay")]) == 0
    assert (tmp_path / "replay" / "trajectory.png").stat().st_size > 20_000
    assert (tmp_path / "trajectory.png").stat().st_size > 20_000
    rows = list(csv.DictReader(open(tmp_path / "trajectory.csv")))
    assert {r["system_id"] for r in rows} == {"1", "2", "3"}
    injected = [r for r in rows if r["gps_input"] == "1"]
    assert injected and all(r["system_id"] == "2" for r in injected)
    assert any(r["mode"] == "RTL" and r["system_id"] == "3" for r in rows)
