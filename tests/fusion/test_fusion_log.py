"""Measurement log: replay reproduces the recorded estimates; damaged or foreign logs are handled."""

import json

import numpy as np
import pytest
from fusion_sim import ORIGIN, Line, fly

from skyfix.cli import main
from skyfix.errors import DataError, InputError
from skyfix.fusion import FusionEngine, read_log
from skyfix.fusion.replay import (
    replay,  # the package attribute "replay" is the submodule once it is imported
)

EAST = Line((0.0, 0.0, 80.0), (8.0, 0.0, 0.0))
LINES = {"A": EAST, "B": Line((-30.0, -40.0, 90.0), (8.0, 0.0, 0.0))}


def record(path, duration_s=20.0):
    """Fly A and B (B observes A; A loses GNSS at 10 s), record, and keep every estimate taken."""
    rng = np.random.default_rng(21)
    live = []
    with FusionEngine(ORIGIN, log_path=path) as engine:
        def take(t):
            for d in ("A", "B"):
                live.append(engine.estimate(d))
                engine.record_truth(d, t, *(float(c) for c in engine.frame.to_geodetic(*LINES[d].at(t))))
        fly(engine, rng, LINES, duration_s, gnss_off={"A": lambda t: t >= 10.0}, observers=("B",), target="A",
            on_tick=take)
    return live


def test_replay_reproduces_the_recorded_estimates_exactly(tmp_path):
    path = tmp_path / "run.jsonl"
    live = record(path)
    result = replay(path, show_progress=False)
    assert result.n_rejected_inputs == 0
    assert len(result.estimates) == len(live)
    for a, b in zip(live, result.estimates, strict=True):
        assert a.drone_id == b.drone_id and a.time_s == b.time_s
        assert np.array_equal(a.enu_m, b.enu_m)
        assert np.array_equal(a.cov_enu_m2, b.cov_enu_m2)
        assert a.health.keys() == b.health.keys()
    header, records = read_log(path)
    assert header["format"] == "skyfix.fusion.log" and header["version"] == 1
    assert tuple(header["origin"]) == ORIGIN
    ops = {r["op"] for r in records}
    assert ops == {"gnss", "velocity", "relative", "update", "truth"}
    assert len(result.truth_enu_m["A"]) == 201


def test_truncated_last_line_and_unknown_ops_are_skipped(tmp_path):
    path = tmp_path / "run.jsonl"
    record(path, duration_s=5.0)
    full = replay(path, show_progress=False)
    text = path.read_text()
    damaged = tmp_path / "damaged.jsonl"
    damaged.write_text(text + json.dumps({"op": "teleport", "args": {}}) + "\n" + '{"op": "gnss", "ar')
    again = replay(damaged, show_progress=False)
    assert len(again.estimates) == len(full.estimates)
    assert np.array_equal(again.estimates[-1].enu_m, full.estimates[-1].enu_m)


def test_foreign_or_newer_logs_are_refused(tmp_path):
    other = tmp_path / "other.jsonl"
    other.write_text('{"format": "something else"}\n')
    with pytest.raises(DataError, match="not a skyfix.fusion.log"):
        read_log(other)
    newer = tmp_path / "newer.jsonl"
    newer.write_text('{"format": "skyfix.fusion.log", "version": 99}\n')
    with pytest.raises(DataError, match="version 99"):
        read_log(newer)
    with pytest.raises(InputError, match="does not exist"):
        read_log(tmp_path / "missing.jsonl")


def test_the_log_is_never_overwritten(tmp_path):
    path = tmp_path / "run.jsonl"
    path.write_text("precious\n")
    with pytest.raises(InputError, match="already exists"):
        FusionEngine(ORIGIN, log_path=path)
    assert path.read_text() == "precious\n"


def test_cli_replay_writes_csv_geojson_and_png(tmp_path, capsys):
    path = tmp_path / "run.jsonl"
    record(path, duration_s=12.0)
    out = tmp_path / "out"
    assert main(["-q", "fusion", "replay", str(path), "-o", str(out)]) == 0
    rows = (out / "estimates.csv").read_text().splitlines()
    assert rows[0].startswith("time_s,drone_id,lat_deg,lon_deg")
    assert len(rows) == 1 + 2 * 121
    geo = json.loads((out / "tracks.geojson").read_text())
    assert {f["properties"]["drone_id"] for f in geo["features"]} == {"A", "B"}
    lon, lat, _ = geo["features"][0]["geometry"]["coordinates"][-1]
    assert abs(lat - ORIGIN[0]) < 0.01 and abs(lon - ORIGIN[1]) < 0.01
    png = (out / "trajectory.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    printed = capsys.readouterr().out
    assert "horizontal error vs truth" in printed
    assert main(["-q", "fusion", "replay", str(tmp_path / "nope.jsonl")]) != 0
    # a drone that is not in the log: one line naming it, exit 2, nothing written
    capsys.readouterr()
    assert main(["-q", "fusion", "replay", str(path), "-o", str(tmp_path / "z"), "--drone", "Z"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--drone Z" in err[0] and "A, B" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "z").exists()


def test_a_drone_silent_longer_than_the_lag_has_no_estimate_and_the_replay_goes_on(tmp_path):
    """B reports once and falls silent; A goes on for longer than the lag. Asking for B's newest estimate is
    'not available' (as for a drone not yet localised), not a bad argument, so a replay of the log, which asks
    for every drone's estimate after each update, runs to the end (a live node skipped it the same way; the
    replay of a loaded demo's log stopped there with exit 2)."""
    from skyfix.errors import NotAvailableError

    path = tmp_path / "silent.jsonl"
    with FusionEngine(ORIGIN, lag_s=2.0, log_path=path) as engine:
        engine.add_gnss("B", 1.0, 47.0, 8.0, 400.0, h_sigma_m=1.5, v_sigma_m=3.0)
        for k in range(40):
            t = 1.0 + 0.2 * k
            engine.add_gnss("A", t, 47.0, 8.0 + 1e-6 * k, 400.0, h_sigma_m=1.5, v_sigma_m=3.0)
            engine.update()
        assert engine.estimate("A").time_s == pytest.approx(8.8)
        with pytest.raises(NotAvailableError, match="silent for longer than"):
            engine.estimate("B")
        with pytest.raises(InputError, match="before drone 'B'"):
            engine.estimate("B", time_s=1.0)
    result = replay(path, show_progress=False)
    assert result.n_rejected_inputs == 0
    assert len(result.fused["A"].arrays()[0]) >= 30 and "B" in result.fused


def test_what_if_replay_with_other_settings_and_edited_records(tmp_path):
    """replay(config=..., edit=...) feeds the same log to an engine with other settings or altered inputs:
    B's observations of A with 100 times their variance leave A (GNSS lost at 10 s) less certain; a larger
    wandering GNSS error leaves B less certain; the plain replay is untouched by either."""
    import dataclasses

    from skyfix.fusion.config import FusionConfig

    path = tmp_path / "run.jsonl"
    record(path)
    plain = replay(path, show_progress=False)

    def coarse(rec: dict) -> dict:
        if rec["op"] != "relative":
            return rec
        obs = rec["args"]["obs"]
        return dict(rec, args={"obs": dataclasses.replace(obs, cov_enu_m2=obs.cov_enu_m2 * 100.0)})

    edited = replay(path, show_progress=False, edit=coarse)
    header, _ = read_log(path)
    wander = dataclasses.replace(FusionConfig.from_dict(header["config"]), gnss_gm_h_sigma_m=3.0)
    other = replay(path, show_progress=False, config=wander)

    def last_sigma(result, drone: str) -> float:
        return [e for e in result.estimates if e.drone_id == drone][-1].sigma_horizontal_m

    # A's variance is B's wandering GNSS part (1.5 m, the same in both) plus the observations' noise averaged
    # over many: ~0.01 m2 as recorded, a hundred times that edited; so it must grow by well over 0.5 m2
    assert last_sigma(edited, "A") ** 2 - last_sigma(plain, "A") ** 2 > 0.5
    assert last_sigma(other, "B") > 1.2 * last_sigma(plain, "B")
    assert last_sigma(replay(path, show_progress=False), "A") == last_sigma(plain, "A")
