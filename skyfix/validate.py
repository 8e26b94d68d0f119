"""Small input checks shared by every module; each raises :class:`skyfix.errors.InputError`.

They return clean float64 arrays and never modify the caller's data.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from skyfix.errors import InputError


def finite_scalar(name: str, value: Any) -> float:
    """Return ``value`` as a float, or raise if it is not a finite real number.

    Example:
        >>> finite_scalar("alt_m", "12.5")
        12.5
        >>> finite_scalar("alt_m", float("nan"))
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: alt_m must be finite, got nan
    """
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(out):
        raise InputError(f"{name} must be finite, got {out}")
    return out


def finite_or_nan_scalar(name: str, value: Any) -> float:
    """Return ``value`` as a float that is finite or NaN (MAVLink's "default / unchanged"
    parameter); raise for an infinity or a non-number.

    Example:
        >>> finite_or_nan_scalar("param4", float("nan"))
        nan
        >>> finite_or_nan_scalar("param1", float("inf"))
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: param1 must be finite or NaN, got inf
    """
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a real number, got {value!r}") from None
    if math.isinf(out):
        raise InputError(f"{name} must be finite or NaN, got {out}")
    return out


def positive_scalar(name: str, value: Any) -> float:
    """Return ``value`` as a float, or raise if it is not finite and > 0.

    Example:
        >>> positive_scalar("tau_s", 0)
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: tau_s must be > 0, got 0.0
    """
    out = finite_scalar(name, value)
    if out <= 0.0:
        raise InputError(f"{name} must be > 0, got {out}")
    return out


def nonnegative_scalar(name: str, value: Any) -> float:
    """Return ``value`` as a float, or raise if it is not finite and >= 0.

    Example:
        >>> nonnegative_scalar("sigma_m", 0)
        0.0
        >>> nonnegative_scalar("sigma_m", -0.5)
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: sigma_m must be >= 0, got -0.5
    """
    out = finite_scalar(name, value)
    if out < 0.0:
        raise InputError(f"{name} must be >= 0, got {out}")
    return out


def finite_array(name: str, value: Any) -> np.ndarray:
    """Return ``value`` as a float64 array (a copy when conversion is needed); raise on NaN/inf.

    Example:
        >>> finite_array("enu_m", [[1, 2, 3]])
        array([[1., 2., 3.]])
        >>> finite_array("enu_m", [1.0, float("inf"), float("nan")])
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: enu_m contains 2 NaN or infinite value(s)
    """
    if isinstance(value, float) and math.isfinite(value):  # a scalar on a hot path: skip numpy's per-call cost
        return np.array(value)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be numeric, got {type(value).__name__}") from None
    if not np.isfinite(arr).all():  # method form: this check runs on every hot path
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise InputError(f"{name} contains {bad} NaN or infinite value(s)")
    return arr


def positive_array(name: str, value: Any) -> np.ndarray:
    """Return ``value`` as a finite float64 array whose every element is > 0.

    Example:
        >>> positive_array("focal_px", [800.0, 1200.0])
        array([ 800., 1200.])
        >>> positive_array("focal_px", [800.0, 0.0, -1.0])
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: focal_px must be > 0, got [ 0. -1.]
    """
    arr = finite_array(name, value)
    return _refuse(name, arr, arr <= 0.0, "> 0")


def nonnegative_array(name: str, value: Any) -> np.ndarray:
    """Return ``value`` as a finite float64 array whose every element is >= 0.

    Example:
        >>> nonnegative_array("sigma_px", 0.0)
        array(0.)
    """
    arr = finite_array(name, value)
    return _refuse(name, arr, arr < 0.0, ">= 0")


def _refuse(name: str, arr: np.ndarray, bad: np.ndarray, expected: str) -> np.ndarray:
    """``arr``, or InputError quoting up to three of its ``bad`` elements."""
    if bad.any():
        raise InputError(f"{name} must be {expected}, got {arr[bad].ravel()[:3]}")
    return arr


def points(name: str, value: Any, ncols: int) -> np.ndarray:
    """Return ``value`` as a finite float64 ``(N, ncols)`` array.

    A single point of shape ``(ncols,)`` is accepted and returned as ``(1, ncols)``.

    Example:
        >>> points("uv", [320.0, 240.0], 2)
        array([[320., 240.]])
    """
    arr = finite_array(name, value)
    if arr.ndim == 1 and arr.shape[0] == ncols:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != ncols:
        raise InputError(f"{name} must have shape (N, {ncols}) or ({ncols},), got {arr.shape}")
    return arr


def latitude(name: str, value: Any) -> np.ndarray:
    """Return latitudes in degrees as a finite array, raising outside [-90, 90].

    Example:
        >>> latitude("lat_deg", [47.0, -90.0])
        array([ 47., -90.])
    """
    if isinstance(value, float) and -90.0 <= value <= 90.0:  # plain float fast path (NaN fails the test)
        return np.array(value)
    arr = finite_array(name, value)
    if (np.abs(arr) > 90.0).any():
        raise InputError(f"{name} must be within [-90, 90] degrees, got {arr[np.abs(arr) > 90.0].ravel()[:3]}")
    return arr


def longitude(name: str, value: Any) -> np.ndarray:
    """Return longitudes in degrees as a finite array, raising outside [-180, 360].

    Example:
        >>> longitude("lon_deg", 359.5)
        array(359.5)
    """
    if isinstance(value, float) and -180.0 <= value <= 360.0:  # plain float fast path (NaN fails the test)
        return np.array(value)
    arr = finite_array(name, value)
    if ((arr < -180.0) | (arr > 360.0)).any():
        raise InputError(f"{name} must be within [-180, 360] degrees, got {arr.ravel()[:3]}")
    return arr


def covariance(name: str, value: Any, dim: int) -> np.ndarray:
    """Return a finite, symmetric, positive semi-definite ``(dim, dim)`` matrix.

    Example:
        >>> covariance("cov_m2", [[1.0, 2.0], [2.0, 1.0]], 2)  # eigenvalues 3 and -1
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: cov_m2 must be positive semi-definite
    """
    arr = finite_array(name, value)
    if arr.shape != (dim, dim):
        raise InputError(f"{name} must have shape ({dim}, {dim}), got {arr.shape}")
    if dim == 3 and _clearly_positive_definite_3x3(arr.tolist()):
        return arr
    scale = max(1.0, float(np.abs(arr).max()))
    # Same test as np.allclose(arr, arr.T, rtol=1e-9, atol=1e-12 * scale), without its overhead.
    if (np.abs(arr - arr.T) > 1e-12 * scale + 1e-9 * np.abs(arr.T)).any():
        raise InputError(f"{name} must be symmetric")
    if np.linalg.eigvalsh(arr).min() < -1e-9 * scale:
        raise InputError(f"{name} must be positive semi-definite")
    return arr


def covariances(name: str, value: Any, dim: int) -> np.ndarray:
    """Return a stack ``(N, dim, dim)`` of matrices that :func:`covariance` accepts one by
    one (finite, symmetric, positive semi-definite), the same checks; clearly positive
    definite 3x3 ones in plain floats, without numpy's per-call cost.

    Example:
        >>> covariances("cov_m2", [np.eye(2), [[1.0, 2.0], [2.0, 1.0]]], 2)
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: cov_m2[1] must be positive semi-definite
    """
    arr = finite_array(name, value)
    if arr.ndim != 3 or arr.shape[1:] != (dim, dim):
        raise InputError(f"{name} must have shape (N, {dim}, {dim}), got {arr.shape}")
    rows = arr.tolist()
    for k in range(arr.shape[0]):
        if not (dim == 3 and _clearly_positive_definite_3x3(rows[k])):
            covariance(f"{name}[{k}]", arr[k], dim)
    return arr


def _clearly_positive_definite_3x3(m: list[list[float]]) -> bool:
    """True only for a 3x3 matrix that :func:`covariance` accepts: symmetric by its own test and
    positive definite by Sylvester's leading minors of the lower triangle (what ``eigvalsh``
    reads). Anything else, boundary cases included, goes to the general test; plain floats
    because a GeoFix per detected fire validates one (numpy's per-call cost was half of it)."""
    (a, b, c), (d, e, f), (g, h, i) = m
    scale = max(1.0, abs(a), abs(b), abs(c), abs(d), abs(e), abs(f), abs(g), abs(h), abs(i))
    tol = 1e-12 * scale
    for x, y in ((b, d), (c, g), (f, h)):
        if abs(x - y) > tol + 1e-9 * abs(y) or abs(y - x) > tol + 1e-9 * abs(x):
            return False
    minor2 = a * e - d * d
    det = a * (e * i - h * h) - d * (d * i - h * g) + g * (d * h - e * g)
    return a > 0.0 and minor2 > 0.0 and det > 0.0


def integer_in(name: str, value: Any, lo: int, hi: int | None = None) -> int:
    """Return ``value`` as an int, or raise if it is not a whole number in ``[lo, hi]``
    (``hi`` None: no upper bound). A bool is not a number here.

    Example:
        >>> integer_in("fix_type", 3.0, 0, 8)
        3
        >>> integer_in("fix_type", 2.5, 0, 8)
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: fix_type must be an integer in [0, 8], got 2.5
        >>> integer_in("supersample", 0, 1)
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: supersample must be an integer >= 1, got 0
    """
    what = f"an integer >= {lo}" if hi is None else f"an integer in [{lo}, {hi}]"
    if isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name} must be {what}, got {value!r}")
    try:
        out = int(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name} must be {what}, got {value!r}") from None
    if out != value or out < lo or (hi is not None and out > hi):
        raise InputError(f"{name} must be {what}, got {value!r}")
    return out


def positive_definite(name: str, value: Any) -> np.ndarray:
    """Return a finite square matrix whose symmetric part is positive definite.

    For covariances that become noise models (gtsam, a Kalman gain): a singular or
    indefinite one would poison the solve; "definite" means the smallest eigenvalue is
    above 1e-12 of the largest (or of 1).

    Example:
        >>> positive_definite("cov_m2", [[4.0, 0.0], [0.0, 1.0]]).shape
        (2, 2)
        >>> positive_definite("cov_m2", [[1.0, 0.0], [0.0, 0.0]])
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: cov_m2 must be positive definite (a measurement with zero uncertainty cannot be fused), got eigenvalues [0. 1.]
    """
    arr = finite_array(name, value)
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1]:
        raise InputError(f"{name} must be a square matrix, got shape {arr.shape}")
    eig = np.linalg.eigvalsh(0.5 * (arr + arr.T))
    if not eig[0] > 1e-12 * max(1.0, eig[-1]):
        raise InputError(f"{name} must be positive definite (a measurement with zero uncertainty cannot be "
                         f"fused), got eigenvalues {eig}")
    return arr
