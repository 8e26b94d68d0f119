"""Geometry of a multirotor target and its apparent-size calibration.

A :class:`DroneModel` is a set of convex 3-D parts (body, arms, motors, rotor disks) in
the body FRD frame, metres, origin at the centre of the airframe. ``span_m`` is the
diameter of the circle through the rotor tips, the size users quote for a drone.

The silhouette of a drone with n-fold symmetry (n >= 3) seen from elevation angle
``elevation_deg`` has a second moment along its major (horizontal) axis that barely
depends on the drone's yaw: for a flat airframe it is exactly the in-plane second
moment. :func:`shape_table` measures that moment on orthographic renders over yaw and
small tilts, so the ranging code can turn a measured angular moment into a range and
carry the residual yaw/tilt dependence as model uncertainty.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from skyfix import validate
from skyfix.errors import InputError
from skyfix.rotation import rot_x, rot_y, rot_z

__all__ = ["DroneModel", "ShapeTable", "rasterize_convex_parts", "shape_table", "silhouette_moments"]

_CIRCLE_SEGMENTS = 20


def _box(center: tuple[float, float, float], half: tuple[float, float, float], yaw_deg: float = 0.0) -> np.ndarray:
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    return (corners * np.asarray(half)) @ rot_z(yaw_deg).T + np.asarray(center)


def _cylinder(center_xy: tuple[float, float], radius: float, z0: float, z1: float) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * math.pi, _CIRCLE_SEGMENTS, endpoint=False)
    ring = np.stack((center_xy[0] + radius * np.cos(a), center_xy[1] + radius * np.sin(a)), axis=1)
    return np.concatenate((np.column_stack((ring, np.full(len(a), z0))),
                           np.column_stack((ring, np.full(len(a), z1)))))


@dataclass(frozen=True)
class DroneModel:
    """A multirotor airframe with ``arms`` arms (4 = quad, 6 = hex), ``span_m`` tip to tip.

    Proportions are fractions of the half-span: ``rotor_fraction`` rotor radius,
    ``arm_width_fraction`` arm width, ``body_fraction`` half-length of the central body.
    The first arm points forward-right (45 deg) on a quad, forward on a hex.

    Example:
        >>> quad = DroneModel.quad(0.5)
        >>> quad.arms, quad.scaled_to(1.0).span_m
        (4, 1.0)
        >>> parts = quad.parts()  # convex parts, body FRD metres
        >>> sum(name == "rotor" for name, _ in parts)
        4
        >>> corners = np.concatenate([v for _, v in parts])  # rotor tips reach the half-span
        >>> round(float(np.hypot(corners[:, 0], corners[:, 1]).max()), 2)
        0.25
    """

    arms: int = 4
    span_m: float = 0.5
    rotor_fraction: float = 0.26
    arm_width_fraction: float = 0.08
    body_fraction: float = 0.36
    thickness_fraction: float = 0.06

    def __post_init__(self) -> None:
        if self.arms not in (3, 4, 6, 8):
            raise InputError(f"DroneModel.arms must be 3, 4, 6 or 8, got {self.arms!r}")
        object.__setattr__(self, "span_m", validate.positive_scalar("DroneModel.span_m", self.span_m))
        for name in ("rotor_fraction", "arm_width_fraction", "body_fraction", "thickness_fraction"):
            value = validate.positive_scalar(f"DroneModel.{name}", getattr(self, name))
            if value >= 0.8:
                raise InputError(f"DroneModel.{name} must be a fraction of the half-span below 0.8, got {value}")
            object.__setattr__(self, name, value)
        # Neighbouring rotors must not overlap: chord between hubs > 2 rotor radii.
        hub = 1.0 - self.rotor_fraction
        if 2.0 * hub * math.sin(math.pi / self.arms) <= 2.0 * self.rotor_fraction:
            raise InputError(f"DroneModel: rotors of radius {self.rotor_fraction} (of the half-span) overlap "
                             f"on a {self.arms}-arm frame; use a smaller rotor_fraction")

    @classmethod
    def quad(cls, span_m: float = 0.5) -> DroneModel:
        """A typical X quadcopter (5-inch props on a 0.5 m span)."""
        return cls(arms=4, span_m=span_m)

    @classmethod
    def hex(cls, span_m: float = 0.5) -> DroneModel:
        """A typical hexacopter with smaller rotors."""
        return cls(arms=6, span_m=span_m, rotor_fraction=0.22)

    def scaled_to(self, span_m: float) -> DroneModel:
        """The same proportions at another span."""
        return DroneModel(self.arms, span_m, self.rotor_fraction, self.arm_width_fraction,
                          self.body_fraction, self.thickness_fraction)

    def parts(self) -> list[tuple[str, np.ndarray]]:
        """Convex parts as ``(name, (N, 3) vertices)`` in body FRD metres (z down)."""
        half = self.span_m / 2.0
        r_rotor = self.rotor_fraction * half
        hub = half - r_rotor
        t = self.thickness_fraction * half
        first = 45.0 if self.arms == 4 else 0.0
        out: list[tuple[str, np.ndarray]] = []
        body = self.body_fraction * half
        out.append(("body", _box((0.0, 0.0, 0.0), (body, 0.6 * body, 1.1 * t))))
        for k in range(self.arms):
            ang = first + 360.0 * k / self.arms
            c, s = math.cos(math.radians(ang)), math.sin(math.radians(ang))
            out.append(("arm", _box((0.5 * hub * c, 0.5 * hub * s, 0.0),
                                    (0.5 * hub, 0.5 * self.arm_width_fraction * half, 0.35 * t), ang)))
            out.append(("motor", _cylinder((hub * c, hub * s), 0.35 * r_rotor, -0.9 * t, 0.9 * t)))
            out.append(("rotor", _cylinder((hub * c, hub * s), r_rotor, -1.1 * t, -0.9 * t)))
        return out


def rasterize_convex_parts(parts_uv: list[np.ndarray], values: list[float], shape: tuple[int, int],
                           depth: list[float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fill the convex hulls of projected parts on a canvas of ``shape`` (rows, cols).

    ``parts_uv`` are ``(N, 2)`` canvas pixel coordinates (pixel centres at integers);
    ``values`` the intensity of each part. A pixel is filled when its centre lies inside
    the hull (exact point sampling, so supersampled coverage is unbiased; OpenCV's
    ``fillPoly`` also fills the pixels an edge touches). Parts are painted far to near
    when ``depth`` is given. Returns (coverage ``(H, W)`` float32 in {0, 1}, intensity
    ``(H, W)`` float32).
    """
    cover = np.zeros(shape, np.float32)
    value = np.zeros(shape, np.float32)
    order = np.argsort(depth)[::-1] if depth is not None else np.arange(len(parts_uv))
    for i in order:
        pts = np.asarray(parts_uv[i], np.float64)
        if pts.shape[0] < 3 or not np.isfinite(pts).all():
            continue
        hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(np.float64)
        if hull.shape[0] < 3:
            continue
        u0, v0 = max(int(math.ceil(hull[:, 0].min())), 0), max(int(math.ceil(hull[:, 1].min())), 0)
        u1 = min(int(math.floor(hull[:, 0].max())), shape[1] - 1)
        v1 = min(int(math.floor(hull[:, 1].max())), shape[0] - 1)
        if u1 < u0 or v1 < v0:
            continue
        nxt = np.concatenate((hull[1:], hull[:1]))
        edges = nxt - hull
        area2 = float(np.sum(hull[:, 0] * nxt[:, 1] - nxt[:, 0] * hull[:, 1]))
        orient = 1.0 if area2 > 0 else -1.0
        # Inside every edge: orient * (ex (v - py) - ey (u - px)) > 0, all edges at once (E, H, W).
        a = (-orient * edges[:, 1])[:, None, None]
        b = (orient * edges[:, 0])[:, None, None]
        c = (orient * (edges[:, 1] * hull[:, 0] - edges[:, 0] * hull[:, 1]))[:, None, None]
        us = np.arange(u0, u1 + 1, dtype=np.float64)[None, None, :]
        vs = np.arange(v0, v1 + 1, dtype=np.float64)[None, :, None]
        inside = ((a * us + b * vs + c) > 0.0).all(axis=0)
        cover[v0:v1 + 1, u0:u1 + 1][inside] = 1.0
        value[v0:v1 + 1, u0:u1 + 1][inside] = float(values[i])
    return cover, value


def silhouette_moments(weight: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Zeroth moment, centroid ``(2,)`` (u, v) and second-moment matrix ``(2, 2)`` of a weight image."""
    w = np.asarray(weight, np.float64)
    m0 = float(w.sum())
    if m0 <= 0.0:
        raise InputError("silhouette_moments: the weight image has no positive mass")
    v, u = np.mgrid[0:w.shape[0], 0:w.shape[1]]
    cu, cv_ = float((w * u).sum() / m0), float((w * v).sum() / m0)
    du, dv = u - cu, v - cv_
    cov = np.array([[(w * du * du).sum(), (w * du * dv).sum()],
                    [(w * du * dv).sum(), (w * dv * dv).sum()]]) / m0
    return m0, np.array([cu, cv_]), cov


@dataclass(frozen=True)
class ShapeTable:
    """Major-axis RMS of the silhouette as a fraction of the span, versus view elevation.

    ``elevation_deg`` ascending grid in [-90, 90] (positive: seen from above);
    ``ratio_mean``/``ratio_std`` the mean and standard deviation over yaw and tilt of
    ``sqrt(largest eigenvalue of the silhouette second moments) / span``;
    ``aspect_mean``/``aspect_std`` the same for ``sqrt(smallest / largest eigenvalue)``.
    """

    elevation_deg: np.ndarray
    ratio_mean: np.ndarray
    ratio_std: np.ndarray
    aspect_mean: np.ndarray
    aspect_std: np.ndarray

    def ratio(self, elevation_deg) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated (mean, std) ratio at ``elevation_deg`` (array-like, degrees)."""
        e = np.clip(validate.finite_array("elevation_deg", elevation_deg), -90.0, 90.0)
        return (np.interp(e, self.elevation_deg, self.ratio_mean),
                np.interp(e, self.elevation_deg, self.ratio_std))

    def aspect(self, elevation_deg) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated (mean, std) minor/major RMS ratio at ``elevation_deg`` (degrees)."""
        e = np.clip(validate.finite_array("elevation_deg", elevation_deg), -90.0, 90.0)
        return (np.interp(e, self.elevation_deg, self.aspect_mean),
                np.interp(e, self.elevation_deg, self.aspect_std))


def _view_rotation(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Rows: image-right, image-down, view direction, in body FRD of a level drone.

    The viewer looks at the drone from azimuth ``azimuth_deg`` (relative to the drone's
    nose, clockwise) and ``elevation_deg`` above its horizontal plane.
    """
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    # Direction from the viewer to the drone (FRD: z down; viewer above -> +z component).
    look = np.array([-math.cos(el) * math.cos(az), -math.cos(el) * math.sin(az), math.sin(el)])
    right = np.cross(np.array([0.0, 0.0, 1.0]), look)
    n = np.linalg.norm(right)
    right = np.array([-math.sin(az), math.cos(az), 0.0]) if n < 1e-9 else right / n
    down = np.cross(look, right)
    return np.stack((right, down, look))


@functools.lru_cache(maxsize=16)
def shape_table(model: DroneModel, tilt_sigma_deg: float = 5.0, canvas_px: int = 160) -> ShapeTable:
    """Measure the silhouette major-axis RMS over yaw (uniform) and tilt (Gaussian) per elevation.

    Orthographic renders of ``model`` on a ``canvas_px`` canvas; 24 yaws x 3 tilts per
    elevation on a grid from edge-on (dense) to overhead. Deterministic (fixed tilt samples).
    """
    unit = model.scaled_to(1.0)
    parts = [p for _, p in unit.parts()]
    scale = (canvas_px - 8) / 1.2  # canvas pixels per metre of a unit-span model
    centre = (canvas_px - 1) / 2.0
    tilts = np.array([[0.0, 0.0], [1.0, -0.7], [-0.6, 1.1]]) * tilt_sigma_deg
    # Orthographic silhouettes from +e and -e are mirror images: measure e >= 0 only,
    # densely near edge-on where the yaw dependence changes fastest.
    upper = np.concatenate((np.arange(0.0, 10.0, 2.0), np.arange(10.0, 20.0, 2.5), np.arange(20.0, 90.1, 10.0)))
    stats_up = np.empty((upper.size, 4))
    for i, el in enumerate(upper):
        ratios, aspects = [], []
        for az in np.arange(0.0, 360.0, 15.0):
            view = _view_rotation(float(el), float(az))
            for pitch, roll in tilts:
                att = rot_y(pitch) @ rot_x(roll)
                uv = [((p @ att.T) @ view[:2].T) * scale + centre for p in parts]
                cover, _ = rasterize_convex_parts(uv, [1.0] * len(uv), (canvas_px, canvas_px))
                m = cv2.moments(cover, binaryImage=True)
                cov = np.array([[m["mu20"], m["mu11"]], [m["mu11"], m["mu02"]]]) / m["m00"]
                ev = np.maximum(np.linalg.eigvalsh(cov), 0.0)
                ratios.append(math.sqrt(ev[-1]) / scale)
                aspects.append(math.sqrt(ev[0] / ev[-1]))
        stats_up[i] = (np.mean(ratios), np.std(ratios), np.mean(aspects), np.std(aspects))
    elevations = np.concatenate((-upper[:0:-1], upper))
    stats = np.concatenate((stats_up[:0:-1], stats_up))
    cols = [np.ascontiguousarray(stats[:, j]) for j in range(4)]
    for arr in (elevations, *cols):
        arr.setflags(write=False)
    return ShapeTable(elevations, *cols)
