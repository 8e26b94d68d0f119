"""FusionEngine.set_lag: a lag that grows at run time takes late observations in; replay follows it."""

import numpy as np
import pytest
from fusion_sim import ORIGIN, WHITE_GNSS, Line, fly, gnss_args, relative, velocity_args

from skyfix.errors import InputError
from skyfix.fusion import FusionEngine, HealthState
from skyfix.fusion.replay import replay

EAST = Line((0.0, 0.0, 80.0), (8.0, 0.0, 0.0))
LINES = {"A": EAST, "B": Line((-30.0, -40.0, 90.0), (8.0, 0.0, 0.0))}
LATE_S = 4.0  # every observation of A reaches the engine this late (a loaded companion's camera pipeline)


def fly_late(engine: FusionEngine, new_lag_s: float | None, seed: int = 3) -> int:
    """A loses GNSS at 8 s; from then B's observations of A arrive LATE_S late. Returns the inputs refused."""
    rng = np.random.default_rng(seed)
    fly(engine, rng, LINES, 8.0)
    if new_lag_s is not None:
        engine.set_lag(new_lag_s)
    refused = 0
    for i in range(1, 121):
        t = 8.0 + i / 10.0
        for d, line in LINES.items():
            engine.add_velocity(d, t, **velocity_args(rng, line))
        if i % 2 == 0:
            engine.add_gnss("B", t, **gnss_args(rng, LINES["B"], t))
            t_obs = t - LATE_S
            try:
                engine.add_relative(relative(rng, "B", "A", LINES["B"].at(t_obs), EAST.at(t_obs), t_obs))
            except InputError:
                refused += 1
        engine.update()
    return refused


def test_a_grown_lag_fuses_observations_later_than_the_old_one():
    fixed = FusionEngine(ORIGIN, lag_s=2.0, config=WHITE_GNSS)
    assert fly_late(fixed, None) == 60  # every late observation refused: A is on dead reckoning
    grown = FusionEngine(ORIGIN, lag_s=2.0, config=WHITE_GNSS)
    refused = fly_late(grown, 6.0)
    # steps marginalised before the change stay gone: only the first ~LATE_S - 2 s of observations are refused
    assert refused <= 12
    est = grown.estimate("A")
    assert est.health["gnss"].state is HealthState.LOST
    # observations LATE_S old arrive every 0.2 s: with the time-out moved by the lag's growth B is not silent
    assert "relative:B" in est.sources and grown.health("A")["relative:B"].state is HealthState.OK
    # one helper 50 m away, 3 % range and 0.2 deg, carried LATE_S forward on 0.05 m/s velocity: well under 2 m
    assert np.hypot(*(est.enu_m - EAST.at(est.time_s))[:2]) < 2.0


def test_a_shorter_lag_refuses_what_the_longer_one_took():
    engine = FusionEngine(ORIGIN, lag_s=6.0, config=WHITE_GNSS)
    rng = np.random.default_rng(4)
    fly(engine, rng, {"A": EAST}, 10.0)
    engine.add_gnss("A", 6.0, **gnss_args(rng, EAST, 6.0))  # 4 s late: inside 6 s
    engine.set_lag(2.0)
    fly(engine, rng, {"A": EAST}, 0.2, t0_s=10.1)  # an update marginalises down to the new lag
    with pytest.raises(InputError, match="older than the fusion lag"):
        engine.add_gnss("A", 6.5, **gnss_args(rng, EAST, 6.5))
    with pytest.raises(InputError, match="at least 3 state steps"):
        engine.set_lag(0.1)


def test_replay_follows_the_recorded_lag_changes(tmp_path):
    path = tmp_path / "run.jsonl"
    with FusionEngine(ORIGIN, lag_s=2.0, config=WHITE_GNSS, log_path=path) as engine:
        fly_late(engine, 6.0)
        live = engine.estimate("A")
    result = replay(path, show_progress=False)
    again = result.estimates[-1] if result.estimates[-1].drone_id == "A" else result.estimates[-2]
    np.testing.assert_allclose(again.enu_m, live.enu_m, atol=1e-9)
