"""Who may observe whom: the roster rule for relative observations.

Relative observations come only from observers on ``FusionConfig.roster`` (drone ids);
with an empty roster, from a drone that has reported its own sensors to the engine
(GNSS, velocity, altitude or a fix). A refused observation raises
:class:`~skyfix.errors.InputError` and is counted in the target's health as the
source ``relative:unknown`` (rejected), so an operator sees that someone is talking.
"""

from __future__ import annotations

import math

from skyfix.errors import InputError
from skyfix.fusion.drone import DroneState
from skyfix.fusion.health import SourceMonitor


class ObserverTrust:
    """The roster check of one engine and its count of refused observations.

    Example (an open roster: only drones that report their own sensors may observe):
        >>> trust = ObserverTrust(roster=())
        >>> drones = {"B": DroneState(index=0, reporting=True)}
        >>> trust.check(drones, "B", "A", 0.0)
        >>> trust.check(drones, "X", "B", 0.0)
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: relative observation from unknown observer 'X' (not in the drones reporting their own sensors ['B']); its observation and any position it carries are ignored
        >>> trust.refused, drones["B"].monitors["relative:unknown"].state.value
        (1, 'rejected')
    """

    def __init__(self, roster: tuple[str, ...]) -> None:
        self.roster = roster
        self.refused = 0                                  # observations refused so far
        self.last_refused: tuple[str, float] | None = None  # (observer id, time s) of the newest

    def check(self, drones: dict[str, DroneState], observer_id: str, target_id: str, t_s: float) -> None:
        """Refuse (InputError) an observation by a drone off the roster, or of a target off it."""
        roster = self.roster
        observer = drones.get(observer_id)
        trusted = observer_id in roster if roster else observer is not None and observer.reporting
        if trusted and roster and target_id not in roster:
            raise InputError(f"relative observation of {target_id!r}, which is not on the roster {list(roster)}")
        if trusted:
            return
        self.refused += 1
        self.last_refused = (observer_id, t_s)
        target = drones.get(target_id)
        if target is not None:
            target.monitors.setdefault("relative:unknown", SourceMonitor(math.inf, 1, math.inf, t_s)).reject(
                t_s, f"{self.refused} observation(s) from observers not on the roster (last {observer_id!r})")
        reporting = sorted(d for d, drone in drones.items() if drone.reporting)
        who = f"the roster {list(roster)}" if roster else f"the drones reporting their own sensors {reporting}"
        raise InputError(f"relative observation from unknown observer {observer_id!r} (not in {who}); "
                         "its observation and any position it carries are ignored")
