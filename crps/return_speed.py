"""A drone that lost GNSS flies its return no faster than its helpers fly.

Stock ArduPilot Copter flies RTL at ``RTL_SPEED`` (cm/s), or at ``WPNAV_SPEED`` when that is 0, its default:
1000 cm/s on the Copter 4.7 firmware in ``../shared/sitl`` (read back from it). Helpers plan their vantage points
at :attr:`skyfix.crps.vantage.VantageConfig.helper_speed_mps` (5 m/s): a lost drone returning at 10 m/s leaves
them behind, out of their cameras' range. So when the recovery starts (the hold, before RTL is commanded: RTL
reads ``RTL_SPEED`` as it starts its return leg), ``RTL_SPEED`` is lowered to the helpers' speed when the return
would be faster.

A parameter write is stored by the autopilot: the old value is written back when the recovery ends (GNSS
healthy again), when the drone has landed, and when the service stops. A companion that dies mid-recovery leaves
the slower return in place (the safe side). PX4 has no return speed of its own (``MPC_XY_CRUISE`` is shared with
missions): left alone, and said so.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

from skyfix.errors import InputError, SkyfixError

log = logging.getLogger(__name__)


class ReturnSpeed:
    """Lowers and restores ArduPilot's ``RTL_SPEED`` around a recovery; ``speed_mps`` None: never touched.

    :meth:`limit` and :meth:`restore` are queued with ``submit(kind, what, fn)`` (the help loop's one worker
    thread for blocking autopilot commands), so ``_saved`` is only ever touched on that thread; :attr:`note` is
    what the last of them did, for the caller's timeline (taken by :meth:`take_note`)."""

    def __init__(self, speed_mps: float | None, submit: Callable[[str, str, Callable[[], None]], None]) -> None:
        if speed_mps is not None and not (math.isfinite(speed_mps) and speed_mps > 0):
            raise InputError(f"return speed must be a positive number of m/s or None, got {speed_mps!r}")
        self.speed_mps = speed_mps
        self._submit = submit
        self._saved: int | None = None  # RTL_SPEED before the recovery (cm/s), None: not changed
        self.note: str | None = None

    def limit(self, vehicle, flavour: str) -> None:
        """Queue the limit for a recovery that starts now."""
        if self.speed_mps is None or vehicle is None:
            return
        if flavour != "ardupilot":
            self.note = f"return speed left to the autopilot ({flavour} has no RTL speed of its own)"
            return
        self._submit("return_speed", "RTL_SPEED limit", lambda: self._limit(vehicle))

    def restore(self, vehicle, now: bool = False) -> None:
        """Queue (``now``: run here) the write-back of the value the recovery found, if it changed one."""
        if vehicle is None:
            return
        if now:
            self._restore(vehicle)
        else:
            self._submit("return_speed", "RTL_SPEED restore", lambda: self._restore(vehicle))

    def take_note(self) -> str | None:
        note, self.note = self.note, None
        return note

    def _limit(self, vehicle) -> None:
        want_cms = int(round(self.speed_mps * 100.0))
        try:
            old = int(vehicle.get_param("RTL_SPEED"))
            return_cms = old if old > 0 else float(vehicle.get_param("WPNAV_SPEED"))
            if return_cms <= want_cms:
                return
            vehicle.set_param("RTL_SPEED", want_cms)
        except SkyfixError as exc:  # the link down as the hold starts: the return flies at the autopilot's speed
            self.note = f"return speed not limited: {exc}"
            raise
        if self._saved is None:
            self._saved = old
        self.note = (f"return speed limited to the helpers' {self.speed_mps:g} m/s (RTL_SPEED {want_cms} cm/s, "
                     f"was {return_cms:g} cm/s)")
        log.info("RTL_SPEED %d -> %d cm/s for the recovery", old, want_cms)

    def _restore(self, vehicle) -> None:
        if self._saved is None:
            return
        vehicle.set_param("RTL_SPEED", self._saved)
        self.note = f"return speed restored (RTL_SPEED {self._saved} cm/s)"
        log.info("RTL_SPEED restored to %d cm/s", self._saved)
        self._saved = None
