"""A vehicle's pose log as time series, interpolated at camera frame times (vectorised).

Camera frames and the autopilot's pose log run on different clocks and rates: a frame
stamped ``t`` is taken at log time ``t + time_offset_s``. :class:`PoseLog` holds the log
(positions WGS84 with ellipsoidal heights, vehicle attitude and gimbal angles in the
conventions of :class:`skyfix.camera.CameraPose`) and returns camera positions and
orientations in a local ENU frame at any times, linearly interpolated (yaw unwrapped).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from skyfix import validate
from skyfix.camera import CameraPose
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.rotation import R_ENU_FROM_NED, R_FRD_FROM_CAM

_ANGLES = ("roll_deg", "pitch_deg", "yaw_deg", "gimbal_pitch_deg", "gimbal_yaw_deg", "gimbal_roll_deg")
_SERIES = ("lat_deg", "lon_deg", "alt_m", *_ANGLES)


@dataclass(frozen=True, eq=False)
class PoseLog:
    """Pose samples ``(N,)`` at strictly increasing ``time_s`` (log clock, s).

    ``alt_m`` metres above the WGS84 ellipsoid; angles in degrees as in
    :class:`~skyfix.camera.CameraPose` (``gimbal_yaw_deg`` relative to the nose);
    ``stabilized`` True for a gimbal holding the horizon.
    """

    time_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    roll_deg: np.ndarray
    pitch_deg: np.ndarray
    yaw_deg: np.ndarray
    gimbal_pitch_deg: np.ndarray
    gimbal_yaw_deg: np.ndarray
    gimbal_roll_deg: np.ndarray
    stabilized: bool = True
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        t = validate.finite_array("PoseLog.time_s", self.time_s).reshape(-1)
        if t.size < 2 or np.any(np.diff(t) <= 0):
            raise InputError("PoseLog.time_s needs >= 2 strictly increasing samples")
        object.__setattr__(self, "time_s", t)
        for name in _SERIES:
            a = validate.finite_array(f"PoseLog.{name}", getattr(self, name)).reshape(-1)
            if a.shape != t.shape:
                raise InputError(f"PoseLog.{name} has {a.size} samples, time_s has {t.size}")
            if name in ("yaw_deg", "gimbal_yaw_deg"):
                a = np.degrees(np.unwrap(np.radians(a)))  # interpolate through +-180
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        validate.latitude("PoseLog.lat_deg", self.lat_deg)
        validate.longitude("PoseLog.lon_deg", self.lon_deg)
        object.__setattr__(self, "stabilized", bool(self.stabilized))

    @classmethod
    def from_poses(cls, time_s, poses: list[CameraPose]) -> PoseLog:
        """A log from one :class:`CameraPose` per time (all stabilised or all hard-mounted)."""
        if not poses or any(not isinstance(p, CameraPose) for p in poses):
            raise InputError("PoseLog.from_poses needs a non-empty list of CameraPose")
        if len({p.stabilized for p in poses}) != 1:
            raise InputError("PoseLog.from_poses: poses mix stabilised and hard-mounted cameras")
        cols = {name: np.array([getattr(p, name) for p in poses]) for name in _SERIES}
        return cls(np.asarray(time_s, float), **cols, stabilized=poses[0].stabilized)

    @property
    def span_s(self) -> tuple[float, float]:
        """(first, last) log time, seconds."""
        return float(self.time_s[0]), float(self.time_s[-1])

    def interpolate(self, time_s) -> dict[str, np.ndarray]:
        """Every series linearly interpolated at ``time_s`` ``(M,)``; raises
        :class:`InputError` for times outside the log."""
        t = validate.finite_array("time_s", time_s).reshape(-1)
        lo, hi = self.span_s
        if t.size and (t.min() < lo - 1e-9 or t.max() > hi + 1e-9):
            raise InputError(f"times {t.min():.3f}..{t.max():.3f} s are outside the pose log "
                             f"({lo:.3f}..{hi:.3f} s)")
        return {name: np.interp(t, self.time_s, getattr(self, name)) for name in _SERIES}

    def smoothed(self, window_s: float = 2.0) -> PoseLog:
        """The log low-passed by a Savitzky-Golay filter (quadratic over ``window_s``): its
        motion without the per-sample noise, for time derivatives (a 10 Hz log with 0.3 deg
        noise has an apparent angular rate noise of several deg/s)."""
        from scipy.signal import savgol_filter

        rate_hz = 1.0 / float(np.median(np.diff(self.time_s)))
        n = int(round(validate.positive_scalar("window_s", window_s) * rate_hz)) | 1
        if n < 5 or n > self.time_s.size:
            return self
        cols = {name: savgol_filter(getattr(self, name), n, 2, mode="interp") for name in _SERIES}
        return PoseLog(self.time_s, **cols, stabilized=self.stabilized)

    def pose_at(self, time_s: float) -> CameraPose:
        """The interpolated :class:`CameraPose` at one log time."""
        v = {k: float(a[0]) for k, a in self.interpolate([validate.finite_scalar("time_s", time_s)]).items()}
        return CameraPose(v["lat_deg"], v["lon_deg"], v["alt_m"], v["roll_deg"], v["pitch_deg"],
                          v["yaw_deg"], v["gimbal_pitch_deg"], v["gimbal_yaw_deg"], v["gimbal_roll_deg"],
                          self.stabilized)

    def _samples_in(self, frame: LocalFrame) -> tuple[np.ndarray, np.ndarray]:
        """(ENU ``(N, 3)`` of the samples in ``frame``, frame <- local-ENU rotations ``(N, 9)``)."""
        hit = self._cache.get(frame)
        if hit is None:
            enu = np.stack(frame.to_enu(self.lat_deg, self.lon_deg, self.alt_m), axis=1)
            # The axes at the vehicle differ from the frame's by ~0.01 deg per km; they vary
            # so slowly that interpolating the matrix elements is exact to 1e-9.
            rot = np.array([frame.enu_rotation_at(la, lo).ravel() for la, lo in
                            zip(self.lat_deg, self.lon_deg, strict=True)])
            hit = self._cache[frame] = (enu, rot)
        return hit

    def camera_in_frame(self, frame: LocalFrame, time_s) -> tuple[np.ndarray, np.ndarray]:
        """Camera positions ``(M, 3)`` ENU metres in ``frame`` and rotations ``(M, 3, 3)``
        frame-ENU <- camera optical frame, at log times ``time_s`` ``(M,)``."""
        v = self.interpolate(time_s)
        t = validate.finite_array("time_s", time_s).reshape(-1)
        enu, rot = self._samples_in(frame)
        cam = np.stack([np.interp(t, self.time_s, enu[:, k]) for k in range(3)], axis=1)
        r_frame_from_enu = np.stack([np.interp(t, self.time_s, rot[:, k]) for k in range(9)],
                                    axis=1).reshape(-1, 3, 3)
        mount = Rotation.from_euler("ZYX", np.stack((v["gimbal_yaw_deg"], v["gimbal_pitch_deg"],
                                                     v["gimbal_roll_deg"]), axis=1), degrees=True)
        if self.stabilized:
            ref = Rotation.from_euler("Z", v["yaw_deg"][:, None], degrees=True)
        else:
            ref = Rotation.from_euler("ZYX", np.stack((v["yaw_deg"], v["pitch_deg"], v["roll_deg"]), axis=1),
                                      degrees=True)
        r_ned_from_cam = (ref * mount).as_matrix() @ R_FRD_FROM_CAM
        return cam, r_frame_from_enu @ (R_ENU_FROM_NED @ r_ned_from_cam)
