"""A healthy consumer receiver, as an autopilot streams it, is never refused (issue 18).

The world: a drone on the ground, then a climb and survey legs at 8 m/s with turns; its receiver
(skyfix.datasets.sim.gps.GpsReceiver, issue 15's consumer figure: 1.5 m per axis wandering over 60 s
+ 0.3 m white) computes a fix every 0.2 s; the autopilot sends its latest fix every 0.18 s stamped
with the SEND time (ArduPilot's GPS_RAW_INT: the fix's time plus the time since it), so a fix is
up to 0.2 s older than its stamp (the engine is told so: ``gnss_fix_age_max_s``, as skyfix serve
tells it) and now and then the same fix goes out twice. Velocity: the
autopilot's, exact, at the telemetry's 0.2 m/s stated sigma.

Before the fix fusion fused a re-sent fix twice and ignored the fixes' age: innovations' mean NIS 3.8-4.7
instead of 3, and 'gnss rejected: 2 consecutive innovation-gate failures' (a false GNSS loss) in 3 of
these 6 flights; after it: mean NIS 2.4-3.1, no rejection.
"""

from __future__ import annotations

import numpy as np

from skyfix.datasets.sim.gps import GpsReceiver
from skyfix.fusion import FusionConfig, FusionEngine
from skyfix.fusion.health import HealthState
from skyfix.geo import LocalFrame

ORIGIN = (47.0, 8.0, 400.0)
FRAME = LocalFrame(*ORIGIN)
RX_PERIOD_S, SEND_PERIOD_S, DT_S = 0.2, 0.18, 0.02


def _velocity_cmd(t_s: float) -> np.ndarray:
    """Commanded velocity (ENU m/s): 4 s on the ground, climb 2.5 m/s for 6 s, then 8 m/s legs of 6 s, reversing."""
    if t_s < 4.0:
        return np.zeros(3)
    if t_s < 10.0:
        return np.array([0.0, 0.0, 2.5])
    leg = int((t_s - 10.0) // 6.0)
    return np.array([0.0, 8.0 if leg % 2 == 0 else -8.0, 0.0])


def _fly(seed: int, duration_s: float = 40.0) -> list:
    """The GNSS health after every fix of one flight."""
    rx = GpsReceiver(seed, bias_sigma_m=1.5, bias_tau_s=60.0, noise_sigma_m=0.3)
    rx.step(1200.0)  # its wandering error from the steady state
    engine = FusionEngine(ORIGIN, lag_s=2.0, config=FusionConfig(gnss_fix_age_max_s=RX_PERIOD_S))
    pos, vel = np.zeros(3), np.zeros(3)
    fix, next_fix_s, next_send_s = None, 0.0, 0.05
    health = []
    for i in range(int(duration_s / DT_S)):
        t = i * DT_S
        vel += np.clip(_velocity_cmd(t) - vel, -4.0 * DT_S, 4.0 * DT_S)  # 4 m/s2: take-off and turns accelerate
        pos = pos + vel * DT_S
        rx.step(DT_S)
        if t >= next_fix_s - 1e-9:
            next_fix_s += RX_PERIOD_S
            fix = rx.read(t, pos, vel).pos_enu_m
        if t < next_send_s - 1e-9 or fix is None:
            continue
        next_send_s += SEND_PERIOD_S
        engine.add_velocity("d", t, vel, 0.2)
        lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*fix))
        engine.add_gnss("d", t, lat, lon, alt, h_sigma_m=0.8, v_sigma_m=1.2, satellites=14, hdop=1.2)
        engine.update()
        engine.estimate("d")
        health.append(engine.health("d")["gnss"])
    return health


def test_a_healthy_receiver_streamed_by_an_autopilot_is_never_rejected():
    outliers = 0
    for seed in range(6):
        health = _fly(seed)
        assert not [h for h in health if h.state is HealthState.REJECTED], f"seed {seed}: a healthy receiver rejected"
        outliers += sum(h.reason == "innovation outlier dropped" for h in health)
    # ~1200 fixes through a 99.9 % gate: ~1.2 outliers expected of honest innovations (Poisson: <= 5 at
    # 99.8 %); before the fix 20 (and 3 of the 6 flights rejected GNSS)
    assert outliers <= 5
