"""Give ArduPilot SITL's simulated GNSS receiver an error track: its glitch offsets, kept current.

SITL's receiver is perfect by default. Next to skyfix's simulated drones, whose receivers share
the area's common error (:class:`skyfix.datasets.gnss_error.CommonGnssError`: orbits, clocks,
atmosphere), a perfect receiver is a world no real drone flies in: its home and its fixes sit in
another frame than its neighbours'. :class:`SitlGnssError` moves the firmware's reported position
by an ENU error track through its own parameters (``SIM_GPS<n>_GLTCH``, ArduPilot's
``libraries/SITL/SIM_GPS.cpp``: X and Y are degrees added to latitude and longitude, Z metres to
the height), set over MAVLink (PARAM_SET) once before take-off, so the home the firmware records
carries it, and then every ``period_s`` of simulated time as the track evolves.

    err = SitlGnssError(vehicle, common.at, clock, (lat_deg, lon_deg, alt_m))
    err.apply_now()   # before arming: the home shares it
    err.start()       # a thread follows the track; err.close() stops it
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from skyfix import validate
from skyfix.errors import InputError, SkyfixError
from skyfix.geo import LocalFrame

log = logging.getLogger(__name__)


class SitlGnssError:
    """Drives ``SIM_GPS<receiver>_GLTCH_X/Y/Z`` of the SITL at ``vehicle`` (a skyfix ``Vehicle``) so its
    receiver reports truth + ``error_enu_m(clock())`` (ENU metres, (3,), e.g. ``CommonGnssError.at``).

    ``near``: (lat_deg, lon_deg, alt_m) of the flying area, where metres become degrees (the exact
    ellipsoidal conversion of :class:`skyfix.geo.LocalFrame`; over a few hundred metres it changes by
    < 1e-4 of the offset). ``period_s``: simulated seconds between updates (a 1800 s / 1.4 m track moves
    ~5 cm in 1 s); ``speedup``: simulated seconds per wall second. ``updates``/``failures`` count the
    parameter sets; ``applied_enu_m`` is the offset last confirmed by the firmware.
    """

    def __init__(self, vehicle, error_enu_m: Callable[[float], np.ndarray], clock: Callable[[], float],
                 near: tuple[float, float, float], *, receiver: int = 1, period_s: float = 1.0,
                 speedup: float = 1.0) -> None:
        self.vehicle, self.error_enu_m, self.clock = vehicle, error_enu_m, clock
        self.frame = LocalFrame(*(float(v) for v in near))
        if int(receiver) not in (1, 2):
            raise InputError(f"receiver must be 1 or 2, got {receiver}")
        self.prefix = f"SIM_GPS{int(receiver)}_GLTCH_"
        self.period_s = validate.positive_scalar("period_s", period_s)
        self.speedup = validate.positive_scalar("speedup", speedup)
        self.updates = self.failures = 0
        self.applied_enu_m: np.ndarray | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def glitch_for(self, error_enu_m: np.ndarray) -> tuple[float, float, float]:
        """The (X deg of latitude, Y deg of longitude, Z m up) that move a fix near the area by ``error_enu_m``."""
        e, n, u = (float(v) for v in validate.finite_array("error_enu_m", error_enu_m).reshape(3))
        lat, lon, _ = self.frame.to_geodetic(e, n, 0.0)
        return float(lat) - self.frame.lat0_deg, float(lon) - self.frame.lon0_deg, u

    def apply_now(self) -> np.ndarray:
        """Set the offsets for the track's value now and wait for the firmware's echo; returns it (ENU m)."""
        error = np.asarray(self.error_enu_m(self.clock()), dtype=float).reshape(3)
        for axis, value in zip("XYZ", self.glitch_for(error), strict=True):
            self.vehicle.set_param(self.prefix + axis, value, timeout_s=1.0, retries=3)
        self.updates += 1
        self.applied_enu_m = error
        return error

    def start(self) -> SitlGnssError:
        """Follow the track on a daemon thread until :meth:`close`."""
        self._thread = threading.Thread(target=self._run, daemon=True, name="skyfix-sitl-gnss-error")
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period_s / self.speedup):
            try:
                self.apply_now()
            except SkyfixError as exc:  # no echo, or a late echo of an earlier set: the next period sets again
                self.failures += 1
                log.debug("SITL receiver error not confirmed: %s", exc)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
