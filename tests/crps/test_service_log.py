"""The MCAP log written through the node: opens with the mcap reader, replays to the same
estimates, and a log whose tail a crash cut off still reads up to the cut."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
from mcap.reader import make_reader

from skyfix.crps.node import Node
from skyfix.drivers.state import GnssFix, VehicleState, Velocity
from skyfix.errors import DataError
from skyfix.fusion.log_mcap import McapLog, iter_messages, read_mcap_log
from skyfix.fusion.replay import replay
from skyfix.geo import LocalFrame

ORIGIN = (46.52, 6.63, 420.0)


def fly(node: Node, seconds: float = 8.0, seed: int = 3) -> list:
    """Two drones at 10 Hz: drone 1 GNSS + velocity throughout, drone 2 loses GNSS after 4 s and is
    then placed by drone 1's camera observations (3 % range, 0.2 deg bearing)."""
    from skyfix.datasets.observations import relative_observation

    rng = np.random.default_rng(seed)
    frame = LocalFrame(*ORIGIN)
    v = {"1": np.array([2.0, 1.0, 0.0]), "2": np.array([-1.0, 2.0, 0.0])}
    p0 = {"1": np.array([0.0, 0.0, 20.0]), "2": np.array([30.0, 10.0, 25.0])}
    estimates = []
    for k in range(int(seconds * 10)):
        t = 0.1 * k
        for d in ("1", "2"):
            p = p0[d] + v[d] * t
            lat, lon, alt = (float(c) for c in frame.to_geodetic(*(p + rng.normal(0, [0.8, 0.8, 1.5]))))
            gps = GnssFix(fix_type=3, satellites=12, h_acc_m=0.8, v_acc_m=1.5, hdop=0.9, vdop=1.2, lat_deg=lat,
                            lon_deg=lon, alt_amsl_m=alt, alt_ellipsoid_m=alt, alt_ellipsoid_source="autopilot",
                            time_s=t)
            vn = v[d] + rng.normal(0, 0.1, 3)
            state = VehicleState(1, velocity=Velocity(vn[1], vn[0], -vn[2], t), gps=gps)
            node.add_telemetry(d, state, lambda m: m.time_s, use_gnss=(d == "1" or t < 4.0))
        node.add_relative(relative_observation(frame, "1", "2", t, p0["1"] + v["1"] * t, p0["2"] + v["2"] * t, rng))
        estimates += node.update()
    return estimates


def test_mcap_log_replays_to_the_same_estimates(tmp_path):
    path = tmp_path / "drone.mcap"
    node = Node("1", ORIGIN, make_sink=lambda header: McapLog(path, header))
    logged = fly(node)
    node.close()
    with open(path, "rb") as f:  # the plain mcap library opens it, with a summary
        reader = make_reader(f)
        topics = {c.topic for c in reader.get_summary().channels.values()}
        assert {"/fusion/gnss", "/fusion/velocity", "/fusion/relative", "/fusion/update"} <= topics
    result = replay(path, show_progress=False)
    assert len(result.estimates) == len(logged) > 140
    for a, b in zip(logged, result.estimates, strict=True):
        assert a.drone_id == b.drone_id and a.time_s == b.time_s
        np.testing.assert_allclose(b.enu_m, a.enu_m, atol=1e-9)
        np.testing.assert_allclose(b.cov_enu_m2, a.cov_enu_m2, atol=1e-12)
    # the GPS-less drone stays within a few metres (relative observations at ~30 m: 3 % = ~1 m)
    last2 = [e for e in logged if e.drone_id == "2"][-1]
    truth2 = np.array([30.0, 10.0, 25.0]) + np.array([-1.0, 2.0, 0.0]) * last2.time_s
    assert math.hypot(*(last2.enu_m - truth2)[:2]) < 3.0


def test_a_cut_tail_is_read_up_to_the_cut(tmp_path):
    path = tmp_path / "whole.mcap"
    node = Node("1", ORIGIN, make_sink=lambda header: McapLog(path, header, flush_s=0.01))
    fly(node, seconds=4.0)
    node.close()
    n_all = sum(1 for _ in iter_messages(path))
    counts = []
    for frac in (0.3, 0.6, 0.97):
        cut = tmp_path / f"cut{frac}.mcap"
        shutil.copy(path, cut)
        with open(cut, "r+b") as f:
            f.truncate(int(path.stat().st_size * frac))
        header, records = read_mcap_log(cut)
        counts.append(sum(1 for _ in records))
        assert header["origin"] == list(ORIGIN)
        replay(cut, show_progress=False)  # replays what is there without raising
    assert 0 < counts[0] < counts[1] <= counts[2] <= n_all  # the last cut may only take the index


def test_not_an_mcap_file(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(DataError):
        read_mcap_log(bad)


def test_the_writer_holds_nothing_per_record(tmp_path):
    """Hours of flight: memory held by the log does not grow with the records written and flushed."""
    import tracemalloc

    log = McapLog(tmp_path / "long.mcap", {"origin": list(ORIGIN)}, flush_s=10.0)
    args = {"drone_id": "1", "time_s": 0.0, "vel_enu_mps": [1.0, 2.0, 0.0], "sigma_mps": 0.2}
    tracemalloc.start()
    held = []
    for _block in range(4):
        for _ in range(2000):
            log.record("velocity", args)
            log.flush()  # a flush per record: the worst case (the service flushes every 50 ms)
        held.append(tracemalloc.get_traced_memory()[0])
    tracemalloc.stop()
    log.close()
    assert held[-1] - held[0] < 20_000, held  # 6000 more records and flushes: no per-record memory
    assert sum(1 for _ in iter_messages(tmp_path / "long.mcap")) == 8000
