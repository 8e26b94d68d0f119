"""skyfix.datasets.sitl: three ArduPilot SITL instances at once (ports, system ids,
working folders), all stopped at the end; a clear reason where the firmware is missing."""

from __future__ import annotations

import time

import pytest

from skyfix.datasets import sitl
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import ConfigurationError
from skyfix.geo import inverse
from skyfix.geoid import geoid_undulation_m


@pytest.mark.sitl
@pytest.mark.slow
@pytest.mark.skipif(bool(sitl.missing_reason()), reason=sitl.missing_reason() or "-")
def test_three_instances_start_fly_apart_and_stop(tmp_path):
    fleet = sitl.SitlFleet(3, speedup=5.0, workdir=tmp_path, first_system_id=11,
                           params={"WPNAV_SPEED": 750, "GPS2_TYPE": 14})
    with fleet:
        assert len({i.port for i in fleet}) == 3 and len({i.workdir for i in fleet}) == 3
        vehicles = []
        try:
            for inst in fleet:
                vehicles.append(Vehicle.connect(inst.url, timeout_s=30.0))
            assert [v.system_id for v in vehicles] == [11, 12, 13]
            homes = [v.wait_until(lambda s: s.home is not None, 60.0, what="home").home for v in vehicles]
            # default homes 20 m apart along east
            assert homes[1].lon_deg - homes[0].lon_deg == pytest.approx(2.6e-4, abs=2e-6)
            for inst in fleet:
                assert (inst.workdir / "eeprom.bin").exists()
            # parameters given to the fleet are in force from the first boot (GPS2_TYPE needs one)
            assert vehicles[2].get_param("GPS2_TYPE") == 14
            assert vehicles[2].get_param("WPNAV_SPEED") == pytest.approx(750.0)
            # the truth tap: SIM_STATE on the second port agrees with the autopilot's own fix
            truth = sitl.SitlTruth.connect(fleet[0].url_secondary, fleet.homes[0][2], speedup=5.0)
            try:
                truth.wait(10.0)
                t = truth.truth()
                pos = vehicles[0].wait_until(lambda s: s.position is not None, 30.0).position
                assert float(inverse(t["lat_deg"], t["lon_deg"], pos.lat_deg, pos.lon_deg)[1]) < 1.5
                assert abs(t["alt_rel_m"]) < 0.5
                # SITL's world has no geoid: its receiver's alt_ellipsoid is its AMSL, and so is the truth's
                gps = vehicles[0].wait_until(lambda s: s.gps is not None and s.gps.fix_type >= 3, 30.0).gps
                assert t["alt_m"] == t["alt_amsl_m"] and gps.alt_ellipsoid_source == "autopilot"
                assert abs(gps.alt_ellipsoid_m - t["alt_m"]) < 2.0  # the receiver's noise
                egm96 = sitl.SitlTruth(truth._own, fleet.homes[0][2], geoid_m=None)  # the real world's N
                egm96.wait(5.0)
                assert egm96.truth()["alt_m"] - t["alt_amsl_m"] == pytest.approx(
                    float(geoid_undulation_m(46.52, 6.63)), abs=0.5)
                assert t["age_s"] < 1.0 and truth.target_pose().lat_deg == pytest.approx(t["lat_deg"], abs=1e-6)
            finally:
                truth.close()
        finally:
            for v in vehicles:
                v.close()
        procs = [inst.process for inst in fleet]
        ports = [inst.port for inst in fleet]
    assert all(p.poll() is not None for p in procs)  # stopped, no orphan firmware
    assert fleet.instances == []
    deadline = time.monotonic() + 5.0
    while not all(sitl._port_free(p) for p in ports) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert all(sitl._port_free(p) for p in ports)



@pytest.mark.sitl
@pytest.mark.skipif(bool(sitl.missing_reason()), reason=sitl.missing_reason() or "-")
def test_a_failed_block_keeps_the_firmware_output(caplog):
    """A link that stays silent is explained by the firmware's own output: the temporary folder
    holding it outlives a ``with`` block that raised (its path logged); a clean block removes it."""
    import shutil

    with sitl.SitlFleet(1, speedup=5.0) as fleet:
        clean = fleet.workdir
    assert not clean.exists()
    with pytest.raises(RuntimeError, match="the flight failed"), sitl.SitlFleet(1, speedup=5.0) as fleet:
        kept = fleet.workdir
        raise RuntimeError("the flight failed")
    try:
        assert fleet.instances == [] and kept.is_dir()
        assert list(kept.glob("sitl*/sitl.out")), sorted(kept.rglob("*"))
        assert str(kept) in caplog.text and "RuntimeError" in caplog.text
    finally:
        shutil.rmtree(kept, ignore_errors=True)

def test_missing_firmware_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv(sitl.ENV_DIR, str(tmp_path))
    monkeypatch.setattr(sitl, "sitl_dir", lambda: None)
    assert str(tmp_path) in sitl.missing_reason()
    with pytest.raises(ConfigurationError, match="SITL not found"):
        sitl.SitlFleet(1).start()


def test_env_var_points_elsewhere(tmp_path, monkeypatch):
    (tmp_path / "run-sitl.sh").write_text("#!/bin/sh\n")
    (tmp_path / "arducopter").write_text("")
    monkeypatch.setenv(sitl.ENV_DIR, str(tmp_path))
    assert sitl.sitl_dir() == tmp_path


def test_sitl_clock_stamps_on_the_other_clock_by_the_least_delayed_message(monkeypatch):
    """A record is stamped with its own boot-clock time moved onto the other clock, however late it is
    processed; the offset is the smallest link delay seen, and follows a drift once the window has passed."""
    from types import SimpleNamespace

    wall = [1000.0]
    monkeypatch.setattr(sitl.time, "time", lambda: wall[0])
    other = [50.0]  # the simulator's clock, s; the firmware booted 30 s of its time before it
    clock = sitl.SitlClock(lambda: other[0], speedup=2.0, window_s=5.0)

    def rec(t_boot_s: float, received_wall_s: float):
        return SimpleNamespace(autopilot_time_s=t_boot_s, time_s=received_wall_s)

    # sent at boot 20.0 (= 50.0 on the other clock), received 0.01 wall s later, processed 0.5 wall s later
    wall[0], other[0] = 1000.5, 51.0
    assert clock(rec(20.0, 1000.01)) == pytest.approx(50.02, abs=1e-9)  # 0.01 wall s of link delay x 2
    # a later message with more link delay: stamped with the smaller offset seen, not its own
    wall[0], other[0] = 1001.5, 53.0
    assert clock(rec(21.0, 1001.2)) == pytest.approx(51.02, abs=1e-9)
    assert clock(SimpleNamespace(autopilot_time_s=float("nan"), time_s=wall[0])) == 53.0  # no stamp: now
    # a receiver without a fix repeats its last fix's time: its report is stamped when it came (0.1 wall s ago)
    assert clock(SimpleNamespace(autopilot_time_s=12.0, time_s=1001.4, fix_type=1)) == pytest.approx(52.8)
    assert clock(SimpleNamespace(autopilot_time_s=21.0, time_s=1001.2, fix_type=3)) == pytest.approx(51.02)
    # the firmware fell 1 s behind (short of CPU): once the window has passed, the new offset rules
    wall[0], other[0] = 1010.0, 70.0
    assert clock(rec(39.0, 1010.0)) == pytest.approx(70.0, abs=1e-9)
