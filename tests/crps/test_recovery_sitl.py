"""The collaborative recovery with the real autopilot as the lost drone: ArduPilot Copter
SITL (``../shared/sitl``, or ``$SKYFIX_SITL_DIR``) surveys between two simulated helpers,
loses its GNSS receiver (SIM_GPS1_ENABLE 0) and returns home on the position skyfix fuses
from the helpers' camera frames (rendered from the truth: the simulator's for the helpers,
SIM_STATE for the SITL drone) and injects as its second GPS (GPS_INPUT, gps_id 1). SITL's own receiver
carries the area's common GNSS error, as the simulated drones' receivers do (its glitch offsets,
:mod:`skyfix.datasets.sitl_gnss`), from before take-off: the home it records shares it, as a real drone's would.

Nothing that positions the lost drone comes from its truth: only pixels, the helpers' own
fused poses and gimbal reports. Scored against SIM_STATE. Real time (simulator and firmware at speed
1): at speed 2 under load the helpers' frames reached the lost drone 3-10 s late (three services, two
renderers and the simulator share one interpreter here, where each drone has its own computer), and the
firmware's clock does not wait for them. About 2.5 minutes; skipped with the reason where the firmware is absent.

One flight, two tests: the safety test (landed within 10 m of home, first fix, separation, detection) and the
issue's precision goals (home within 3 m, error <= 5 m). The second was a non-strict xfail from 2026-11-29, when a
quiet full suite landed 4.15 m from home (and two suites at once 3.87 m); it is a plain test again since 2026-11-30:
23 copies of the test in 24 loaded suites (two at once, 01:00-09:43 UTC that day) passed it (the 24th could not
start its SITL: a connection time-out, the safety test errored with it), and
``benchmarks/recovery_sitl_loaded.py --at-once 2 --rounds 2`` flew 10 of 10 within its goals (10:11-10:17 UTC on
60be747, 11:19-11:25 UTC on a0810f8: landed 0.62-1.40 m from home, worst errors 1.68-3.06 m). Before that, a plain
test since the held injected fix keeps its accuracy while landing (crps.service): six runs
(2026-11-28 21:01-21:35 UTC, speed 1, each alone under the heavy-job lock; two on 3eab040, the change before its
rebase, four on d37f077) landed home and disarmed, 0.63-1.36 m from home. Before it, 5 of 7: twice the copter
stood on the ground still armed (its EKF walked ~0.5 m/s on the held fix whose stated accuracy kept growing).
"""

from __future__ import annotations

import math

import pytest

from skyfix.datasets import sitl

pytestmark = [pytest.mark.sitl, pytest.mark.slow,
              pytest.mark.skipif(bool(sitl.missing_reason()), reason=sitl.missing_reason() or "-")]

HOME = (46.52, 6.63, 372.0, 0.0)  # the SITL drone's home: lat, lon (deg), alt AMSL (m), heading (deg)
SPEED = 1.0


SAFE_LANDING_M = 10.0  # landed this close to home at worst: no flyaway, no landing among the fields


@pytest.fixture(scope="module")
def flight():
    """One flight of the flow (about 2 minutes), its result and its timeline as text; both tests judge it."""
    from skyfix.crps.recovery import RecoveryConfig, run_recovery
    from skyfix.drivers.injection import ARDUPILOT_INJECTED_GPS2_PARAMS

    # ArduPilot's own speeds (WPNAV_SPEED 1000 cm/s: surveys and returns at 10 m/s, twice the simulated helpers'):
    # the lost drone's service lowers RTL_SPEED to the helpers' 5 m/s for the recovery (crps/return_speed.py)
    params = dict(ARDUPILOT_INJECTED_GPS2_PARAMS)
    with sitl.SitlFleet(1, speedup=SPEED, homes=[HOME], params=params) as fleet:
        fleet[0].release_start_wait()  # the truth link (second port) may connect before the drone's service
        cfg = RecoveryConfig(seed=0, speed=SPEED, lost_vehicle_url=fleet[0].url,
                             lost_vehicle_truth_url=fleet[0].url_secondary, lost_vehicle_home=HOME[:3],
                             loss_time_s=12.0, max_after_loss_s=100.0)  # home and landed ~60 s after the loss
        result = run_recovery(cfg)
        # the services have stopped: what the autopilot keeps of its return speed (a new link to its first port)
        from skyfix.drivers.vehicle import Vehicle

        check = Vehicle.connect(fleet[0].url, timeout_s=10.0)
        try:
            rtl_speed_after = check.get_param("RTL_SPEED", timeout_s=2.0)
        finally:
            check.close()
    story = "\n".join(f"{t:7.1f} s  {what}" for t, what in result.timeline)
    print(f"SITL recovery: outcome {result.outcome}, landed {result.landing_error_m:.2f} m from home, first fix "
          f"{result.loss_to_first_fused_fix_s:.1f} s, max error {result.max_recovery_error_h_m:.2f} m, separation "
          f"{result.min_separation_m:.1f} m, detected {100 * result.detection_share:.0f} %, final height "
          f"{result.figures.get('final_alt_rel_m', math.nan):.1f} m, fastest 2 s on the way home "
          f"{result.figures.get('return_speed_max_mps', math.nan):.1f} m/s")  # -rP shows it
    return result, story, rtl_speed_after


def test_sitl_lost_drone_lands_safely_near_home_on_the_helpers_cameras(flight):
    """What must hold every time: landed (not airborne, not lost) within SAFE_LANDING_M of home, the first fused
    fix within 15 s, helpers >= 10 m away, and it was their cameras (the target detected in their frames)."""
    result, story, _ = flight
    assert result.outcome in ("home", "landed_elsewhere"), story
    assert result.landing_error_m <= SAFE_LANDING_M, story
    assert result.loss_to_first_fused_fix_s <= 15.0, story
    assert result.min_separation_m >= 10.0, story
    assert math.isfinite(result.detection_share) and result.detection_share > 0.3, story


def test_sitl_lost_drone_returns_home_within_3_m(flight):
    """The issue's goals: home and disarmed, <= 3 m from home (the injected fix's error at touchdown plus the
    firmware's own landing spread, 0.2 m on perfect positions, judged on SIM_STATE), <= 5 m error while
    recovering."""
    result, story, _ = flight
    assert result.outcome == "home", story
    assert result.landing_error_m <= 3.0, story
    assert result.max_recovery_error_h_m <= 5.0, story


def test_sitl_lost_drone_returns_no_faster_than_its_helpers(flight):
    """Stock ArduPilot returns at 10 m/s; the lost drone's service lowered RTL_SPEED to the helpers' 5 m/s before
    its return (the helpers keep it in view) and wrote the old value back once it had landed, or at the latest
    when it stopped."""
    result, story, rtl_speed_after = flight
    events = [what for _, what in result.timeline]
    limited = [i for i, e in enumerate(events) if "return speed limited to the helpers' 5 m/s" in e and "was 1000" in e]
    returning = [i for i, e in enumerate(events) if "return_home" in e]
    assert limited and returning and limited[0] < returning[0], story
    # and the firmware flew it: SIM_STATE's truth on the way home, 5 m/s plus its speed control's overshoot
    # (unlimited it would fly 10 m/s)
    assert result.figures["return_speed_max_mps"] <= 6.0, (result.figures["return_speed_max_mps"], story)
    assert rtl_speed_after == 0, story  # written back as found
