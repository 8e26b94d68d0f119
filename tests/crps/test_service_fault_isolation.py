"""A fault in the help logic (an exception no input check foresaw) does not stop the onboard service: it logs it
with its traceback, counts it, and goes on estimating and publishing (a lost drone's injection is in the same tick).
Before, the exception ended the service's thread."""

from __future__ import annotations

import logging
import os
import threading

from test_swarm_transport import wait_for

from skyfix.crps.help_loop import HelpLoop, HelpSetup
from skyfix.crps.service import Service, ServiceConfig
from skyfix.crps.transport import Endpoints, InProcessBus


def test_an_exception_in_the_help_step_is_survived(monkeypatch, caplog):
    from skyfix.datasets.sim import Simulator, SimulatorConfig

    def broken_step(self, now_s, state):
        raise ZeroDivisionError("a bug in the help logic")

    monkeypatch.setattr(HelpLoop, "step", broken_step)
    sim = Simulator(SimulatorConfig(vehicles=1, seed=5)).start()
    cfg = ServiceConfig("d1", sim.url(0), Endpoints((), ()), os.urandom(32), help=HelpSetup())
    service = Service(cfg, transport=InProcessBus().attach("skyfix", "d1"))
    runner = threading.Thread(target=service.run, daemon=True)
    caplog.set_level(logging.ERROR, logger="skyfix")
    runner.start()
    try:
        assert wait_for(lambda: service.counters["estimates"] >= 10, 30.0), service.counters
        assert runner.is_alive()
        assert service.counters.get("help_faults", 0) >= 3, service.counters  # the help step ran, and failed
        assert service.counters.get("loop_faults", 0) == 0
        assert any("help step" in r.getMessage() and r.exc_info for r in caplog.records)
    finally:
        service.stop.set()
        runner.join(10.0)
        sim.stop()
