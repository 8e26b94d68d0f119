"""A camera observer that was only silent is fused again at its first consistent observation (issue 18: the
observers of a drone whose MAVLink link dropped went silent for 5 s under load, and 5 s of probation then kept
it on dead reckoning, 5-8 m off); a receiver that was silent still goes on probation."""

import numpy as np

from skyfix.fusion import FusionConfig, FusionEngine, HealthState, SourceMonitor
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation

ORIGIN = (47.0, 8.0, 400.0)
FRAME = LocalFrame(*ORIGIN)
TARGET = np.array([0.0, 0.0, 50.0])
HELPER = np.array([30.0, 0.0, 45.0])


def _observe(eng: FusionEngine, t_s: float) -> None:
    los = TARGET - HELPER
    r = float(np.linalg.norm(los))
    lat, lon, alt = FRAME.to_geodetic(*HELPER)
    eng.add_relative(RelativeObservation("h", "a", t_s, los / r, r, np.eye(3) * 0.25, float(lat), float(lon), float(alt)))


def test_a_silent_observer_is_fused_at_its_next_consistent_observation():
    eng = FusionEngine(ORIGIN, lag_s=2.0, config=FusionConfig(roster=("a", "h")))
    gap = (6.0, 13.0)  # no observation: longer than the relative time-out (2 s)
    for t in np.arange(0.0, 16.0, 0.2):
        t = round(float(t), 6)
        for d, p in (("a", TARGET), ("h", HELPER)):
            eng.add_velocity(d, t, np.zeros(3), 0.1)
            lat, lon, alt = FRAME.to_geodetic(*p)
            eng.add_gnss(d, t, float(lat), float(lon), float(alt), h_sigma_m=0.5, v_sigma_m=0.8,
                         fix_type=0 if d == "a" and t >= 2.0 else 3)  # 'a' has lost its receiver
        if t >= 2.0 and abs(t * 2 - round(t * 2)) < 1e-9 and not gap[0] <= t < gap[1]:
            _observe(eng, t)
        eng.update()
        if gap[0] + 3.0 <= t < gap[1]:
            assert eng.health("a")["relative:h"].state is HealthState.LOST
        if t == gap[1]:
            est = eng.estimate("a")
            assert eng.health("a")["relative:h"].state is HealthState.OK
            assert "relative:h" in est.sources
            # 7 s of a 30 m/s walk without observations, then one 0.5 m observation: back to about a metre
            assert est.sigma_horizontal_m < 1.5


def test_a_silent_receiver_still_goes_on_probation():
    monitor = SourceMonitor(timeout_s=1.0, reject_after=2, readmit_after_s=5.0, now_s=0.0)
    assert monitor.judge(0.0, True)
    monitor.tick(3.0)
    assert monitor.state is HealthState.LOST and monitor.on_probation
    assert not monitor.judge(3.2, True)
    quiet = SourceMonitor(timeout_s=1.0, reject_after=2, readmit_after_s=5.0, now_s=0.0, probation_after_silence=False)
    assert quiet.judge(0.0, True)
    quiet.tick(3.0)
    assert quiet.state is HealthState.LOST and not quiet.on_probation
    assert quiet.judge(3.2, True) and quiet.state is HealthState.OK
