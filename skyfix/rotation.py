"""Rotation matrices and the fixed axis changes between skyfix's frames.

Frames: NED (north, east, down) and ENU (east, north, up) world axes; body FRD
(forward, right, down); camera optical frame (OpenCV: x right, y down, z forward).
Euler angles are aerospace Z-Y-X (yaw, then pitch, then roll) in degrees:
yaw 0 = north, clockwise positive; pitch nose-up positive; roll right-wing-down positive.
A matrix named ``r_a_from_b`` maps vectors expressed in frame b into frame a.
"""

from __future__ import annotations

import math

import numpy as np

#: ENU <- NED (its own inverse).
R_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: FRD (x forward, y right, z down) <- OpenCV camera (x right, y down, z forward).
R_FRD_FROM_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def rot_x(angle_deg: float) -> np.ndarray:
    """Active rotation about x by ``angle_deg`` (right-handed).

    Example:
        >>> (rot_x(90.0) @ [0.0, 1.0, 0.0]).round(12) + 0.0  # y turns into z
        array([0., 0., 1.])
    """
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_deg: float) -> np.ndarray:
    """Active rotation about y by ``angle_deg`` (right-handed).

    Example:
        >>> (rot_y(90.0) @ [0.0, 0.0, 1.0]).round(12) + 0.0  # z turns into x
        array([1., 0., 0.])
    """
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_deg: float) -> np.ndarray:
    """Active rotation about z by ``angle_deg`` (right-handed).

    Example:
        >>> (rot_z(90.0) @ [1.0, 0.0, 0.0]).round(12) + 0.0  # x turns into y
        array([0., 1., 0.])
    """
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def r_ned_from_frd(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Body FRD -> NED for aerospace Z-Y-X Euler angles in degrees.

    Example:
        >>> (r_ned_from_frd(90.0, 0.0, 0.0) @ [1.0, 0.0, 0.0]).round(12) + 0.0  # nose east
        array([0., 1., 0.])
    """
    return rot_z(yaw_deg) @ rot_y(pitch_deg) @ rot_x(roll_deg)


def euler_zyx_from_r_ned_from_frd(r: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`r_ned_from_frd`: (yaw_deg in [-180, 180), pitch_deg, roll_deg).

    Example:
        >>> [round(a, 9) for a in euler_zyx_from_r_ned_from_frd(r_ned_from_frd(200.0, -5.0, 10.0))]
        [-160.0, -5.0, 10.0]
    """
    (r10, r00), (r20, r21, r22) = (float(r[1][0]), float(r[0][0])), (float(v) for v in r[2])
    # math on five scalars: numpy's per-call overhead is 5x the work here (a hot path of tags)
    pitch = math.degrees(math.asin(min(max(-r20, -1.0), 1.0)))
    yaw = math.degrees(math.atan2(r10, r00))
    roll = math.degrees(math.atan2(r21, r22))
    return (yaw + 180.0) % 360.0 - 180.0, pitch, roll
