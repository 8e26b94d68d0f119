"""Per-drone bookkeeping of the fusion engine and the one rule for drone ids."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from skyfix.errors import InputError
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.drift import GnssDriftTest
from skyfix.fusion.health import HealthState, SourceMonitor
from skyfix.fusion.velocity import IntervalVelocity


@dataclass
class DroneState:
    """What the engine keeps about one drone besides its states in the graph window.

    ``index`` names its current state chain in the window (a re-anchored drone gets a new
    one); steps ``first_k``..``last_k`` hold states (None: not anchored). ``velocity`` is
    (time s, velocity m/s in frame axes, per-axis variance m2/s2 including the model's).
    """

    index: int
    first_k: int | None = None
    last_k: int | None = None
    last_time_s: float = -math.inf       # newest measurement time of this drone
    velocity: tuple[float, np.ndarray, float] | None = None
    monitors: dict[str, SourceMonitor] = field(default_factory=dict)
    r_frame_from_local: np.ndarray = field(default_factory=lambda: np.eye(3))
    axes_at_enu_m: np.ndarray | None = None  # where r_frame_from_local and up_minus_alt_m were taken
    up_minus_alt_m: float | None = None      # near there: up_m = alt_m + this
    cov_cache: tuple[int, np.ndarray] | None = None
    intervals: IntervalVelocity | None = None
    drift: GnssDriftTest | None = None
    drift_rejected: bool = False             # GNSS refused by the drift test; re-admitted against the velocity
    drift_strikes: int = 0                   # consecutive fixes failing the drift test
    reporting: bool = False                  # has reported its own sensors (may observe others on an open roster)
    bias_walk_mps_per_sqrt_s: float | None = None  # its velocity bias's walk when not the configured one

    @property
    def anchored(self) -> bool:
        return self.last_k is not None

    def monitor(self, source: str, timeout_s: float, t: float, config: FusionConfig) -> SourceMonitor:
        """The health monitor of ``source`` (time-out s), created at time ``t`` with ``config``'s
        rejection and re-admission rules on its first message.

        A ``relative:*`` source that was only silent is not put on probation: each of its observations is
        gated against the fused estimate, and a drone positioned by camera observers alone has, while they are
        silent, nothing else that could confirm them. Probation then only delayed the one position source for
        readmit_after_s (MAVLink drop under load: observers silent 5 s, their next 5 s refused, the fix 5-8 m
        off on dead reckoning)."""
        monitor = self.monitors.get(source)
        if monitor is None:
            monitor = self.monitors[source] = SourceMonitor(
                timeout_s, config.reject_after, config.readmit_after_s, t, config.readmit_fraction,
                probation_after_silence=not source.startswith("relative:"))
        return monitor

    def set_relative_timeout(self, timeout_s: float) -> None:
        """A new time-out (s) for every ``relative:*`` source of this drone (the fusion lag changed)."""
        for name, monitor in self.monitors.items():
            if name.startswith("relative:"):
                monitor.timeout_s = timeout_s

    def contributing(self, now_s: float, window_s: float) -> tuple[str, ...]:
        """Sources fused within ``window_s`` of ``now_s`` (s) and not lost, sorted."""
        return tuple(sorted(name for name, m in self.monitors.items()
                            if now_s - m.last_fused_s <= window_s and m.state is not HealthState.LOST))


def drone_id(value) -> str:
    """A drone id as the engine keys it: a non-empty string (integers are accepted as text).

    Example:
        >>> drone_id(7), drone_id("A")
        ('7', 'A')
    """
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"drone id must be a non-empty string, got {value!r}")
    return value
