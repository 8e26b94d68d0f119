"""skyfix.fusion: the factor-graph core that turns measurements into estimates.

:class:`FusionEngine` keeps every drone's position (and its autopilot's velocity bias)
in a gtsam fixed-lag window over one local ENU frame, from GNSS, velocity, altitude,
absolute fixes (tags) and relative observations by helpers (crps); it judges each
positioning source's health (ok / degraded / lost / rejected), records every input to
a replayable measurement log (:mod:`skyfix.fusion.log`), and :func:`replay` runs a log
again. Names load on first use so ``skyfix --help`` does not import gtsam.
"""

from __future__ import annotations

from skyfix.lazy import lazy_exports

_EXPORTS = {
    "FusionConfig": "config",
    "FusionEngine": "engine",
    "Estimate": "estimate",
    "HealthState": "health", "SourceHealth": "health", "SourceMonitor": "health",
    "MeasurementLog": "log", "read_log": "log",
    "ReplayResult": "replay", "replay": "replay",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
