"""skyfix.fusion: the factor-graph core that turns measurements into estimates.

:class:`FusionEngine` keeps every drone's position (and its autopilot's velocity bias)
in a gtsam fixed-lag window over one local ENU frame, from GNSS, velocity, altitude,
absolute fixes (tags) and relative observations by helpers (crps); it judges each
positioning source's health (ok / degraded / lost / rejected), records every input to
a replayable measurement log (:mod:`skyfix.fusion.log`), and :func:`replay` runs a log
again. Names load on first use so ``skyfix --help`` does not import gtsam.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "FusionConfig": "config",
    "FusionEngine": "engine",
    "Estimate": "estimate",
    "HealthState": "health", "SourceHealth": "health", "SourceMonitor": "health",
    "MeasurementLog": "log", "read_log": "log",
    "ReplayResult": "replay", "replay": "replay",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"skyfix.fusion.{_EXPORTS[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'skyfix.fusion' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
