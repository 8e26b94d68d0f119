"""Mission transfers survive packet loss (partial retransmission), both directions."""

from __future__ import annotations

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers.mission import MissionItem
from skyfix.drivers.vehicle import Vehicle


def _survey(lat0: float, lon0: float, n: int) -> list[MissionItem]:
    return [MissionItem.waypoint(lat0 + 1e-5 * (i % 20), lon0 + 1e-5 * (i // 20), 10.0 + i % 7, hold_s=i % 3)
            for i in range(n)]


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_upload_download_with_10_percent_loss(flavour):
    cfg = SimulatorConfig(vehicles=1, flavour=flavour, speed=2.0, loss_rate=0.10, seed=5)
    with Simulator(cfg) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            st = v.wait_until(lambda s: s.home is not None, 5.0)
            items = _survey(st.home.lat_deg, st.home.lon_deg, 200)
            stats = v.upload_mission(items, item_timeout_s=0.1)
            assert stats.items == 200
            # with 10 % loss each way about 19 % of exchanges lose a packet; some must be resent
            assert stats.retransmissions > 0
            stored = sim.vehicle(0).mission
            offset = 1 if flavour == "ardupilot" else 0
            assert len(stored) == 200 + offset
            assert all(abs(s.lat_deg - i.lat_deg) < 1e-7 and s.alt_m == pytest.approx(i.alt_m, abs=1e-4)
                       for s, i in zip(stored[offset:], items, strict=True))  # stored in order
            back = v.download_mission(item_timeout_s=0.1)
            assert len(back) == 200
            for a, b in zip(back, items, strict=True):
                assert a.command == b.command and a.param1 == b.param1
                assert abs(a.lat_deg - b.lat_deg) < 1e-7 and abs(a.lon_deg - b.lon_deg) < 1e-7
                assert a.alt_m == pytest.approx(b.alt_m, abs=1e-4)
            v.clear_mission()
            assert sim.vehicle(0).mission == []
        finally:
            v.close()
