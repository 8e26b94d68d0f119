"""Typed, timestamped vehicle state as reported by the autopilot.

Every record carries ``time_s``: UNIX time at which skyfix received the message.
Altitudes: ``alt_amsl_m`` above mean sea level as the autopilot reports it,
``alt_ellipsoid_m`` above the WGS84 ellipsoid (what skyfix's geodesy and fusion use),
``alt_rel_m`` above home. Velocities in local NED, m/s. Angles in degrees. The
conversions from MAVLink's wire units are all in :mod:`skyfix.drivers.units`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from skyfix.errors import NotAvailableError
from skyfix.geo import Height, VerticalDatum


class _Heights:
    """``height(datum)`` for a record holding ``alt_amsl_m`` (EGM96) and ``alt_ellipsoid_m``."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_ellipsoid_m: float

    def height(self, datum: VerticalDatum | str = VerticalDatum.WGS84) -> Height:
        """This record's height above ``datum`` (default the WGS84 ellipsoid, skyfix's frames):
        the autopilot's AMSL value for EGM96, the ellipsoidal height for WGS84 (the autopilot's
        own when it sent one), others converted at the record's position. NotAvailableError
        when the record has no height (no fix).

        Example:
            >>> Home(47.0, 8.0, 500.0, 0.0, alt_ellipsoid_m=548.39).height("egm96")
            Height(value_m=500.0, datum=<VerticalDatum.EGM96: 'egm96'>)
        """
        target = Height(0.0, datum).datum
        if not math.isfinite(self.alt_ellipsoid_m):  # units.py fills it whenever there is a fix
            raise NotAvailableError(f"{type(self).__name__} has no height above {target.value} (no fix)")
        if target is VerticalDatum.EGM96:
            return Height(self.alt_amsl_m, target)
        source = Height(self.alt_ellipsoid_m, VerticalDatum.WGS84)
        return source.to(target, self.lat_deg, self.lon_deg)


@dataclass(frozen=True)
class Position(_Heights):
    """Fused position (GLOBAL_POSITION_INT); ``alt_ellipsoid_m`` = AMSL + EGM96 geoid."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_rel_m: float
    time_s: float
    autopilot_time_s: float = math.nan  # the message's own time stamp (time_boot_ms), autopilot clock
    alt_ellipsoid_m: float = math.nan


@dataclass(frozen=True)
class Velocity:
    """Ground velocity in local NED (GLOBAL_POSITION_INT), m/s."""

    north_mps: float
    east_mps: float
    down_mps: float
    time_s: float
    autopilot_time_s: float = math.nan  # the message's own time stamp (time_boot_ms), autopilot clock

    @property
    def speed_mps(self) -> float:
        return math.sqrt(self.north_mps ** 2 + self.east_mps ** 2 + self.down_mps ** 2)

    @property
    def ground_speed_mps(self) -> float:
        return math.hypot(self.north_mps, self.east_mps)


@dataclass(frozen=True)
class Attitude:
    """Aerospace Z-Y-X attitude of the body FRD frame in local NED (ATTITUDE), degrees."""

    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    time_s: float


@dataclass(frozen=True)
class GnssFix(_Heights):
    """Raw GNSS receiver report (GPS_RAW_INT): GPS_FIX_TYPE, satellites, accuracies.

    ``h_acc_m``/``v_acc_m``: the receiver's 1-sigma accuracies in metres (NaN when the
    autopilot does not report them). ``hdop``/``vdop``: dilutions of precision, unitless
    (NaN when unknown); never a metre sigma. ``alt_ellipsoid_m``: height above WGS84, from
    the message's ``alt_ellipsoid`` (``alt_ellipsoid_source == "autopilot"``) or AMSL plus
    the EGM96 geoid when the autopilot leaves it 0 (``"egm96"``); ``"none"`` without a fix.
    """

    fix_type: int
    satellites: int
    h_acc_m: float
    v_acc_m: float
    hdop: float
    vdop: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_ellipsoid_m: float
    alt_ellipsoid_source: str
    time_s: float
    autopilot_time_s: float = math.nan  # the message's own time stamp (time_usec), autopilot clock


@dataclass(frozen=True)
class EkfStatus:
    """The autopilot estimator's own verdict (ArduPilot EKF_STATUS_REPORT): ``flags`` are
    EKF_STATUS_FLAGS; ``pos_horiz_abs`` true while it trusts its absolute horizontal position
    (GPS or an injected fix); ``const_pos_mode`` when it has fallen back to a constant position.
    Variances are the EKF's normalised innovation test ratios (0..1 good, > 1 rejected)."""

    flags: int
    pos_horiz_abs: bool
    const_pos_mode: bool
    velocity_variance: float
    pos_horiz_variance: float
    time_s: float


@dataclass(frozen=True)
class Battery:
    """Battery (SYS_STATUS / BATTERY_STATUS); NaN when the autopilot does not know."""

    voltage_v: float
    current_a: float
    remaining_pct: float
    time_s: float


@dataclass(frozen=True)
class Home(_Heights):
    """Home position (HOME_POSITION)."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    time_s: float
    autopilot_time_s: float = math.nan  # the message's own time stamp (time_usec), autopilot clock
    alt_ellipsoid_m: float = math.nan  # AMSL + EGM96 geoid


@dataclass(frozen=True)
class VehicleEvent:
    """Something that happened: ``kind`` is e.g. ``"statustext"``, ``"mode"``, ``"armed"``,
    ``"link_lost"``, ``"mission_item_reached"``, ``"camera_trigger"``, ``"safety_violation"``."""

    kind: str
    time_s: float
    text: str = ""
    data: dict = field(default_factory=dict)


@dataclass(frozen=True)
class VehicleState:
    """A consistent snapshot of everything known about one vehicle."""

    system_id: int
    autopilot: str = ""
    mode: str = ""
    armed: bool = False
    landed_state: str = "UNDEFINED"
    link_ok: bool = False
    heartbeat_time_s: float = math.nan
    position: Position | None = None
    velocity: Velocity | None = None
    attitude: Attitude | None = None
    gps: GnssFix | None = None
    ekf: EkfStatus | None = None
    battery: Battery | None = None
    home: Home | None = None
    mission_seq: int = -1
    mission_count: int = 0

    def summary(self) -> str:
        """One line for logs and error messages."""
        parts = [f"sys {self.system_id} {self.autopilot} {self.mode}",
                 "armed" if self.armed else "disarmed", self.landed_state.lower()]
        if self.position:
            p = self.position
            parts.append(f"at {p.lat_deg:.7f},{p.lon_deg:.7f} rel {p.alt_rel_m:.1f} m")
        if self.gps:
            parts.append(f"gps fix {self.gps.fix_type} sats {self.gps.satellites}")
        if not self.link_ok:
            parts.append("LINK LOST")
        return ", ".join(parts)
