"""crps.service.fusion_config: a helper whose camera observations reach the node late (inside the
fusion lag) keeps counting as a live, contributing source; with the engine's 2 s defaults the same
stream is called silent between frames and goes on probation."""

import numpy as np
import pytest
from helpnet import ALT0, LAT0, LON0

from skyfix.crps.service import fusion_config
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.engine import FusionEngine
from skyfix.fusion.health import HealthState
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation

FRAME = LocalFrame(LAT0, LON0, ALT0)
TARGET = np.array([0.0, 0.0, 50.0])
HELPER = np.array([30.0, 0.0, 45.0])
LATE_S = 2.6     # exposure -> requester's fusion: a loaded camera pipeline at speed 2
FRAME_DT_S = 0.8  # one observation per helper frame
LAG_S = 3.0


def _fly(config: FusionConfig) -> list[tuple[HealthState, bool]]:
    """Target 'a' loses GNSS at 4 s; helper 'h' observes it from then on, each observation LATE_S late.
    Per 0.2 s after 10 s: the relative source's state and whether the estimate rests on it."""
    rng = np.random.default_rng(3)
    eng = FusionEngine((LAT0, LON0, ALT0), lag_s=LAG_S, config=config)
    out, t_obs_next = [], 4.0
    for t in np.arange(0.0, 17.0, 0.2):
        t = round(float(t), 6)
        for d, p in (("a", TARGET), ("h", HELPER)):
            eng.add_velocity(d, t, rng.normal(0, 0.05, 3), 0.1)
            lat, lon, alt = FRAME.to_geodetic(*(p + rng.normal(0, 0.3, 3)))
            eng.add_gnss(d, t, float(lat), float(lon), float(alt), h_sigma_m=0.5, v_sigma_m=0.8,
                         fix_type=0 if d == "a" and t >= 4.0 else 3)
        while t_obs_next + LATE_S <= t + 1e-9:  # delivered now, exposed LATE_S ago
            los = TARGET - HELPER
            r = float(np.linalg.norm(los))
            cov = np.eye(3) * (2e-3 * r) ** 2 + np.outer(los, los) / r**2 * (0.02 * r) ** 2
            lat, lon, alt = FRAME.to_geodetic(*HELPER)
            eng.add_relative(RelativeObservation("h", "a", t_obs_next, los / r, r * (1 + rng.normal(0, 0.02)),
                                                 cov, float(lat), float(lon), float(alt)))
            t_obs_next = round(t_obs_next + FRAME_DT_S, 6)
        eng.update()
        if t >= 10.0:
            state = eng.health("a")["relative:h"].state
            out.append((state, "relative:h" in eng.estimate("a").sources))
    return out


def test_late_observations_inside_the_lag_keep_the_helper_live_and_contributing():
    cfg = fusion_config(("a", "h"), LAG_S)
    base = FusionConfig()
    assert cfg.relative_timeout_s == pytest.approx(LAG_S + base.relative_timeout_s)
    assert cfg.contributing_window_s == pytest.approx(LAG_S + base.contributing_window_s)
    assert cfg.roster == ("a", "h") and fusion_config(None, 1.0).roster == ()
    tuned = _fly(cfg)
    assert all(state is HealthState.OK and used for state, used in tuned)
    # the engine's defaults (2 s) call the same stream silent: not fused while on probation
    default = _fly(FusionConfig(roster=("a", "h")))
    assert sum(state is not HealthState.OK or not used for state, used in default) > len(default) // 2


def test_velocity_of_an_autopilot_flying_on_the_injected_fix_is_fused_with_the_echo_sigma():
    """While the autopilot flies on skyfix's injected fix its velocity echoes that fix: fused with the echo's
    error spread over its correlation time (the engine takes each state step as independent), else the EKF's."""
    from skyfix.crps.node import (
        ECHO_CORRELATION_S,
        ECHO_VELOCITY_SIGMA_MPS,
        TELEMETRY_VELOCITY_SIGMA_MPS,
        Node,
    )
    from skyfix.drivers.state import VehicleState, Velocity

    class Sink:
        def __init__(self):
            self.sigmas = []

        def record(self, op, args=None):
            if op == "velocity":
                self.sigmas.append(float(np.max(args["sigma_mps"])))

        def truth(self, *args):
            pass

        def close(self):
            pass

    sink = Sink()
    node = Node("a", (LAT0, LON0, ALT0), make_sink=lambda _header: sink)
    state = VehicleState(1, velocity=Velocity(1.0, 0.0, 0.0, 0.0))
    node.add_telemetry("a", state, lambda m: m.time_s)
    node.add_telemetry("a", state, lambda m: 0.2, velocity_sigma_mps=ECHO_VELOCITY_SIGMA_MPS)
    node.close()
    step_s = node.engine.config.state_dt_s
    assert sink.sigmas[0] == TELEMETRY_VELOCITY_SIGMA_MPS
    assert sink.sigmas[1] == pytest.approx(ECHO_VELOCITY_SIGMA_MPS * np.sqrt(ECHO_CORRELATION_S / step_s))
    assert sink.sigmas[1] > 5 * TELEMETRY_VELOCITY_SIGMA_MPS  # the helpers' observations, not the echo, place it
