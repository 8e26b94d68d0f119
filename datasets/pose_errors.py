"""The pose errors a consumer drone really logs, applied to a true pose log.

What a DJI/ArduPilot-class aircraft with a gimbal logs differs from where its camera was
and where it looked by:

- GNSS position error: a first-order Gauss-Markov process per axis (multipath and
  atmosphere change over about a minute: ~1.5 m horizontal, ~2.5 m vertical) plus
  ~0.2 m white noise;
- attitude error of the logged heading and gimbal angles: white noise per log sample
  plus a slow Gauss-Markov drift (AHRS heading, gimbal encoder);
- a constant boresight misalignment between the gimbal's reported axes and the
  thermal sensor's optical axis (mounting, 0.5-1.2 degrees);
- a time offset between the camera's frame stamps and the pose log's clock.

:func:`~skyfix.datasets.gauss_markov.gauss_markov` is the exact discretisation of the
process, at arbitrary times.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from skyfix.datasets.gauss_markov import gauss_markov
from skyfix.geo import LocalFrame
from skyfix.thermal.poselog import PoseLog


@dataclass(frozen=True)
class PoseErrorModel:
    """One realisation's parameters (1-sigma unless stated; units in the names).

    ``boresight_deg``: rotation vector (camera optical axes x right, y down, z forward)
    from the camera the gimbal reports to the one that took the picture, degrees.
    ``time_offset_s``: pose-log time minus camera stamp of the same instant.
    """

    gnss_h_sigma_m: float = 1.5
    gnss_v_sigma_m: float = 2.5
    gnss_tau_s: float = 60.0
    gnss_white_m: float = 0.2
    attitude_white_deg: float = 0.3
    attitude_drift_deg: float = 0.25
    attitude_tau_s: float = 30.0
    boresight_deg: tuple[float, float, float] = (0.6, -0.7, 0.4)
    time_offset_s: float = 0.12

    @classmethod
    def draw(cls, rng: np.random.Generator) -> PoseErrorModel:
        """A random consumer drone: sigmas within +-30 % of the defaults, correlation times
        40-100 s (GNSS) and 15-60 s (attitude), boresight 0.5-1.2 deg in a random
        direction, time offset uniform in +-0.2 s."""
        base = cls()
        axis = rng.normal(size=3)
        bore = axis / np.linalg.norm(axis) * rng.uniform(0.5, 1.2)
        scale = rng.uniform(0.7, 1.3, 5)
        return replace(base, gnss_h_sigma_m=base.gnss_h_sigma_m * scale[0],
                       gnss_v_sigma_m=base.gnss_v_sigma_m * scale[1], gnss_tau_s=rng.uniform(40, 100),
                       gnss_white_m=base.gnss_white_m * scale[2],
                       attitude_white_deg=base.attitude_white_deg * scale[3],
                       attitude_drift_deg=base.attitude_drift_deg * scale[4],
                       attitude_tau_s=rng.uniform(15, 60), boresight_deg=tuple(float(b) for b in bore),
                       time_offset_s=float(rng.uniform(-0.2, 0.2)))

    def boresight(self) -> Rotation:
        """The boresight misalignment as a rotation (reported camera -> real camera)."""
        return Rotation.from_rotvec(np.radians(self.boresight_deg))

    def corrupt(self, truth: PoseLog, frame: LocalFrame, rng: np.random.Generator) -> PoseLog:
        """The log a drone would write for the true ``truth`` log (same sample times):
        GNSS and attitude errors added; boresight and time offset are applied by the
        camera side (:meth:`boresight`, :attr:`time_offset_s`)."""
        t = truth.time_s
        enu, rot = truth._samples_in(frame)
        sig = np.array([self.gnss_h_sigma_m, self.gnss_h_sigma_m, self.gnss_v_sigma_m])
        err_local = gauss_markov(rng, t, sig, self.gnss_tau_s) + rng.normal(0.0, self.gnss_white_m, enu.shape)
        # Errors are drawn in the ENU axes at the vehicle; rotate into the frame's axes.
        err = np.einsum("nij,nj->ni", rot.reshape(-1, 3, 3), err_local)
        lat, lon, alt = frame.to_geodetic(*(enu + err).T)
        att = (gauss_markov(rng, t, np.full(3, self.attitude_drift_deg), self.attitude_tau_s)
               + rng.normal(0.0, self.attitude_white_deg, (t.size, 3)))
        # A gimbal's logged angles carry its own errors; a hard mount's are the vehicle's.
        names = (("yaw_deg", "gimbal_pitch_deg", "gimbal_roll_deg") if truth.stabilized
                 else ("yaw_deg", "pitch_deg", "roll_deg"))
        cols = {n: getattr(truth, n) for n in ("roll_deg", "pitch_deg", "yaw_deg", "gimbal_pitch_deg",
                                                 "gimbal_yaw_deg", "gimbal_roll_deg")}
        for k, name in enumerate(names):
            cols[name] = cols[name] + att[:, k]
        return PoseLog(t, lat, lon, alt, **cols, stabilized=truth.stabilized)
