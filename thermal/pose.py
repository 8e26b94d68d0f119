"""Building a :class:`~skyfix.camera.CameraPose` from what autopilots and gimbals report,
and the uncertainty of a pose.

The two field mistakes this guards against: a gimbal yaw reported relative to north
(most gimbals' "absolute" mode, DJI's ``gimbal yaw``) passed where skyfix expects yaw
relative to the vehicle heading, and an AMSL altitude passed as ellipsoidal height.
:func:`camera_pose` makes the caller name both references.
"""

from __future__ import annotations

from dataclasses import dataclass

from skyfix import validate
from skyfix.camera import CameraPose
from skyfix.errors import InputError

GIMBAL_YAW_REFERENCES = ("vehicle", "north")
ALTITUDE_DATUMS = ("ellipsoid", "amsl")


def camera_pose(lat_deg: float, lon_deg: float, alt_m: float, *, altitude_datum: str,
                roll_deg: float, pitch_deg: float, yaw_deg: float, gimbal_pitch_deg: float,
                gimbal_yaw_deg: float = 0.0, gimbal_yaw_reference: str, gimbal_roll_deg: float = 0.0,
                stabilized: bool, geoid_undulation_m: float | None = None) -> CameraPose:
    """A camera pose with the altitude datum and gimbal-yaw reference stated explicitly.

    ``altitude_datum``: "ellipsoid" (GNSS ellipsoidal height, MAVLink
    ``GPS_RAW_INT.alt_ellipsoid``) or "amsl" (then ``geoid_undulation_m`` N is required;
    h = H + N). ``gimbal_yaw_reference``: "vehicle" (relative to the nose) or "north"
    (absolute heading of the camera; converted with ``yaw_deg``). ``stabilized``: True
    for a gimbal that holds the horizon, False for a hard-mounted camera.

    Example:
        450 m AMSL where the geoid is 50 m above the ellipsoid is 500 m ellipsoidal; a
        gimbal pointing east (north-referenced) on a drone heading east is straight ahead:

        >>> pose = camera_pose(47.0, 8.0, 450.0, altitude_datum="amsl", geoid_undulation_m=50.0,
        ...                    roll_deg=0.0, pitch_deg=0.0, yaw_deg=90.0, gimbal_pitch_deg=-90.0,
        ...                    gimbal_yaw_deg=90.0, gimbal_yaw_reference="north", stabilized=True)
        >>> pose.alt_m, pose.gimbal_yaw_deg
        (500.0, 0.0)
    """
    if altitude_datum not in ALTITUDE_DATUMS:
        raise InputError(f"altitude_datum must be one of {ALTITUDE_DATUMS}, got {altitude_datum!r} "
                         "(AGL is not a datum: convert with the ground height first)")
    if gimbal_yaw_reference not in GIMBAL_YAW_REFERENCES:
        raise InputError(f"gimbal_yaw_reference must be one of {GIMBAL_YAW_REFERENCES}, "
                         f"got {gimbal_yaw_reference!r}")
    alt = validate.finite_scalar("alt_m", alt_m)
    if altitude_datum == "amsl":
        if geoid_undulation_m is None:
            raise InputError("altitude_datum='amsl' needs geoid_undulation_m (geoid height above "
                             "the WGS84 ellipsoid at the site, metres)")
        alt += validate.finite_scalar("geoid_undulation_m", geoid_undulation_m)
    yaw = validate.finite_scalar("yaw_deg", yaw_deg)
    g_yaw = validate.finite_scalar("gimbal_yaw_deg", gimbal_yaw_deg)
    if gimbal_yaw_reference == "north":
        g_yaw = (g_yaw - yaw + 180.0) % 360.0 - 180.0
    return CameraPose(lat_deg, lon_deg, alt, roll_deg, pitch_deg, yaw, gimbal_pitch_deg, g_yaw,
                      gimbal_roll_deg, bool(stabilized))


@dataclass(frozen=True)
class PoseUncertainty:
    """1-sigma errors of one frame's pose and hotspot centroid, assumed independent
    between frames (GNSS noise, not a constant bias).

    ``position_sigma_m``: east and north each, metres. ``altitude_sigma_m``: vertical,
    metres (default: same as horizontal). ``tilt_sigma_deg``: roll and pitch of the
    camera, degrees. ``yaw_sigma_deg``: heading, degrees (default: same as tilt).
    ``pixel_sigma_px``: centroid error in u and v, pixels.
    """

    position_sigma_m: float = 1.5
    altitude_sigma_m: float | None = None
    tilt_sigma_deg: float = 0.5
    yaw_sigma_deg: float | None = None
    pixel_sigma_px: float = 0.5

    def __post_init__(self) -> None:
        for name in ("position_sigma_m", "altitude_sigma_m", "tilt_sigma_deg", "yaw_sigma_deg",
                     "pixel_sigma_px"):
            value = getattr(self, name)
            if value is None:
                continue
            object.__setattr__(self, name, validate.nonnegative_scalar(f"PoseUncertainty.{name}", value))

    @property
    def vertical_m(self) -> float:
        """Vertical position 1-sigma, metres."""
        return self.position_sigma_m if self.altitude_sigma_m is None else self.altitude_sigma_m

    @property
    def heading_deg(self) -> float:
        """Heading 1-sigma, degrees."""
        return self.tilt_sigma_deg if self.yaw_sigma_deg is None else self.yaw_sigma_deg
