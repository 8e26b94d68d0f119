"""A helper is 'localised' (may go on helping) while its GNSS is fused: one innovation outlier dropped does not
make it withdraw; a receiver with no fix does.

The demo flight (seed 11) lost both helpers for 10 s each this way: a helper braking at its vantage point had
one fix dropped by the gate (fusion: DEGRADED for 0.2 s), declared its own position lost, withdrew and was barred
from helping again for HelpConfig.exclude_s. Fusion, its health monitor and crps.Node are the real ones here.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from helpnet import ALT0, LAT0, LON0

from skyfix.crps.help_loop import HelpLoop
from skyfix.crps.node import Node
from skyfix.crps.service import fusion_config
from skyfix.drivers.state import Battery, GnssFix, Position, VehicleState, Velocity
from skyfix.fusion.health import HealthState
from skyfix.geo import LocalFrame

FRAME = LocalFrame(LAT0, LON0, ALT0)
HOVER = np.array([0.0, 0.0, 30.0])  # ENU m: the helper at its vantage point
LAG_S = 3.0


def _state(t_s: float, enu_m: np.ndarray, fix_type: int = 3) -> VehicleState:
    lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*enu_m))
    gps = GnssFix(fix_type=fix_type, satellites=14 if fix_type >= 3 else 0, h_acc_m=0.8, v_acc_m=1.2, hdop=1.2,
                  vdop=1.9, lat_deg=lat, lon_deg=lon, alt_amsl_m=alt, alt_ellipsoid_m=alt,
                  alt_ellipsoid_source="autopilot", time_s=t_s)
    return VehicleState(1, armed=True, velocity=Velocity(0.0, 0.0, 0.0, t_s), gps=gps,
                        position=Position(lat, lon, alt, 30.0, t_s), battery=Battery(15.8, 5.0, 80.0, t_s))


def _status(node: Node, t_s: float, state: VehicleState):
    """HelpLoop's own judgement of this drone (its _my_status), on a real node."""
    loop = SimpleNamespace(svc=SimpleNamespace(node=node), home=(LAT0, LON0, ALT0), eye=object(),
                           setup=SimpleNamespace(min_alt_rel_m=10.0), id="h1")
    gnss = node.engine.health("h1").get("gnss")
    return HelpLoop._my_status(loop, t_s, state, gnss), gnss


def test_one_dropped_gnss_outlier_leaves_a_helper_localised_and_a_lost_receiver_does_not():
    rng = np.random.default_rng(4)
    node = Node("h1", (LAT0, LON0, ALT0), lag_s=LAG_S, config=fusion_config(("h1",), LAG_S))
    t = 0.0
    for k in range(100):  # 20 s hovering, fixes at 5 Hz with 0.3 m noise
        t = round(0.2 * k, 6)
        node.add_telemetry("h1", _state(t, HOVER + rng.normal(0, 0.3, 3)), lambda m: m.time_s)
        node.update(("h1",))
    me, gnss = _status(node, t, _state(t, HOVER))
    assert gnss.state is HealthState.OK and me.localised and me.available

    t = round(t + 0.2, 6)  # one fix 12 m off (a multipath reflection): the gate drops it
    node.add_telemetry("h1", _state(t, HOVER + np.array([12.0, 0.0, 0.0])), lambda m: m.time_s)
    node.update(("h1",))
    me, gnss = _status(node, t, _state(t, HOVER))
    assert gnss.state is HealthState.DEGRADED, gnss  # fused no more, flagged
    assert node.latest["h1"].sigma_frame_horizontal_m < 1.0  # against the others (the shared GNSS error aside)
    assert me.localised  # still positioned by its receiver: it goes on helping

    for _ in range(15):  # the receiver loses its fix for 3 s
        t = round(t + 0.2, 6)
        node.add_telemetry("h1", _state(t, HOVER, fix_type=1), lambda m: m.time_s)
        node.update(("h1",))
    me, gnss = _status(node, t, _state(t, HOVER))
    assert gnss.state is HealthState.LOST
    assert not me.localised and math.isfinite(me.lat_deg)
