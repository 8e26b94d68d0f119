"""Thermal flights over a mountain: orbits and lawn-mower passes, rendered on the true
terrain, with the pose log a drone would really write.

The world: a :class:`~skyfix.datasets.terrain.Terrain` with fires (:class:`FireSpec`
discs on the ground at known east/north, their height the terrain's). Pixels are ray
cast onto the terrain (occlusion by ridges included); the ground temperature is a
forest texture, sun-facing slopes a few degrees warmer, fires composited on top as in
:mod:`skyfix.datasets.thermal_scene`, then the sensor's noise and dead pixels.

The camera: frames are exposed at true log times and stamped ``time_offset_s`` early or
late; the real optical axes are the gimbal's rotated by the boresight misalignment.
What an estimator gets is :attr:`MountainFlight.log` (corrupted by
:class:`~skyfix.datasets.pose_errors.PoseErrorModel`), the frame stamps and the frames;
the truth (true log, fire positions, the error realisation) is kept apart for scoring.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera
from skyfix.datasets.pose_errors import PoseErrorModel
from skyfix.datasets.render import _pixel_rays, rendered_in_order
from skyfix.datasets.terrain import Terrain
from skyfix.datasets.thermal_scene import FireSpec, ThermalSensor, forest_texture
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.thermal.detect import Hotspot
from skyfix.thermal.poselog import PoseLog

GRAVITY_MPS2 = 9.81
SKY_C = -20.0


class MountainScene:
    """Fires on a terrain. ``ambient_c``/``texture_sigma_c``: ground temperature and its
    spread; ``sun_heating_c``: extra warmth of a slope facing the sun (from
    ``sun_azimuth_deg``) at 45 degrees."""

    def __init__(self, terrain: Terrain, fires: list[FireSpec] | tuple[FireSpec, ...], *, ambient_c: float = 15.0,
                 texture_sigma_c: float = 3.0, sun_heating_c: float = 6.0, sun_azimuth_deg: float = 200.0,
                 seed: int = 0) -> None:
        if not isinstance(terrain, Terrain):
            raise InputError(f"terrain must be a Terrain, got {type(terrain).__name__}")
        self.terrain = terrain
        self.fires = tuple(fires)
        if any(not isinstance(f, FireSpec) for f in self.fires):
            raise InputError("fires must be FireSpec objects")
        self.ambient_c = validate.finite_scalar("ambient_c", ambient_c)
        self.texture_sigma_c = validate.finite_scalar("texture_sigma_c", texture_sigma_c)
        self.sun_heating_c = validate.finite_scalar("sun_heating_c", sun_heating_c)
        az = math.radians(validate.finite_scalar("sun_azimuth_deg", sun_azimuth_deg))
        self._sun_en = np.array([math.sin(az), math.cos(az)])
        n = terrain.up_m.shape[0]
        self._texture = forest_texture(n, terrain.metres_per_px, int(seed) + 7)

    @property
    def frame(self):
        """The scene's :class:`~skyfix.geo.LocalFrame`."""
        return self.terrain.frame

    def fire_enu(self) -> np.ndarray:
        """True fire centres ``(F, 3)`` ENU metres in :attr:`frame` (on the terrain)."""
        e = np.array([f.east_m for f in self.fires])
        n = np.array([f.north_m for f in self.fires])
        return np.stack((e, n, self.terrain.up_at(e, n)), axis=1)

    def _windows(self, camera: Camera, cam: np.ndarray, r: np.ndarray, time_s: float) -> list[tuple[slice, slice]]:
        """Image windows around the burning fires (where rays are cast at full resolution)."""
        out = []
        for f, p in zip(self.fires, self.fire_enu(), strict=True):
            rad = f.radius_at(time_s)
            if rad <= 0:
                continue
            pc = r.T @ (p - cam)
            if pc[2] <= 1.0:
                continue
            u, v = camera.fx * pc[0] / pc[2] + camera.cx, camera.fy * pc[1] / pc[2] + camera.cy
            half = (rad + 3.0) * camera.fx / pc[2] * 2.0 + 6.0
            c0, c1 = int(max(u - half, 0)), int(min(u + half + 1, camera.width))
            r0, r1 = int(max(v - half, 0)), int(min(v + half + 1, camera.height))
            if c0 < c1 and r0 < r1:
                out.append((slice(r0, r1), slice(c0, c1)))
        return out

    def render(self, camera: Camera, cam_enu_m: np.ndarray, r_frame_from_cam: np.ndarray, time_s: float = 0.0, *,
               blur_sigma_px: float = 0.5, stride: int = 4) -> np.ndarray:
        """Noise-free apparent temperature (deg C) ``(H, W)`` float32 seen by a camera at
        ``cam_enu_m`` ``(3,)`` with rotation frame <- camera ``r_frame_from_cam`` ``(3, 3)``.

        Rays are cast every ``stride`` pixels (background) and at every pixel around the
        fires (whose shape and occlusion decide where a detector puts the centroid)."""
        cam = validate.finite_array("cam_enu_m", cam_enu_m).reshape(3)
        rays = _pixel_rays(camera, 1) @ np.asarray(r_frame_from_cam, float).T
        h, w = camera.height, camera.width
        coarse = self.terrain.cast_image(cam, rays[::stride, ::stride], stride=4)
        filled = np.where(np.isfinite(coarse), coarse, 0.0).astype(np.float32)
        t = cv2.resize(filled, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float64)
        hit = cv2.resize(np.isfinite(coarse).astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        t[~hit] = np.nan
        for win in self._windows(camera, cam, r_frame_from_cam, time_s):
            t[win] = self.terrain.cast_image(cam, rays[win], stride=4)
        ground = cam + t[..., None] * rays
        img = self._temperature(ground, t / camera.fx, time_s)
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
        return img

    def _temperature(self, ground: np.ndarray, footprint_m: np.ndarray, time_s: float) -> np.ndarray:
        terrain = self.terrain
        col, row = terrain._colrow(ground[..., 0], ground[..., 1])
        ok = np.isfinite(col)
        col, row = np.where(ok, col, -10.0), np.where(ok, row, -10.0)
        tex = terrain._sample(self._texture, col, row)
        slope_sun = (terrain._sample(terrain._grad[0], col, row) * self._sun_en[0]
                     + terrain._sample(terrain._grad[1], col, row) * self._sun_en[1])
        img = self.ambient_c + self.texture_sigma_c * tex + self.sun_heating_c * np.clip(slope_sun, -1.0, 1.0)
        edge_m = np.maximum(0.15, 2.0 * np.nan_to_num(footprint_m, nan=1.0))
        reach_m = float(np.max(edge_m)) / 2.0
        east, north = ground[..., 0], ground[..., 1]
        for f in self.fires:
            rad = f.radius_at(time_s)
            if rad <= 0:
                continue
            # a pixel is covered (cover > 0) only where dist < rad + edge/2: the fire's terms are
            # computed on the pixels inside that square alone (a frame is 0.3 Mpx, a fire ~100 px)
            near = (np.abs(east - f.east_m) < rad + reach_m) & (np.abs(north - f.north_m) < rad + reach_m)
            rows, cols = np.nonzero(near)
            if rows.size == 0:
                continue
            dist = np.hypot(east[rows, cols] - f.east_m, north[rows, cols] - f.north_m)
            cover = np.clip((rad - dist) / edge_m[rows, cols] + 0.5, 0.0, 1.0)
            core = 1.0 - 0.3 * np.clip(dist / rad, 0.0, 1.0) ** 2
            fire_c = np.where(cover > 0, self.ambient_c + (f.peak_c - self.ambient_c) * cover * core, -1e9)
            img[rows, cols] = np.maximum(img[rows, cols], fire_c)
        img = np.where(np.isfinite(img) & ok, img, SKY_C)
        return img.astype(np.float32)


def mountain_scene(seed: int, *, n_fires: int = 5, spread_m: float = 70.0, origin=(42.15, 9.05, 850.0),
                   size_m: float = 2100.0) -> MountainScene:
    """A seeded mountain (:meth:`Terrain.mountain`) around ``origin`` (lat, lon deg,
    ellipsoidal height m of the valley floor; default: central Corsica) with ``n_fires``
    fires of 0.8-2 m radius and 350-700 deg C within ``spread_m`` of the centre, at
    least 15 m apart."""
    rng = np.random.default_rng(seed)
    terrain = Terrain.mountain(LocalFrame(*origin), seed=seed, size_m=size_m)
    centres: list[np.ndarray] = []
    while len(centres) < n_fires:
        c = rng.uniform(-spread_m, spread_m, 2)
        if all(np.hypot(*(c - o)) >= 15.0 for o in centres):
            centres.append(c)
    fires = [FireSpec(float(c[0]), float(c[1]), float(rng.uniform(0.8, 2.0)), float(rng.uniform(350.0, 700.0)))
             for c in centres]
    return MountainScene(terrain, fires, seed=seed)


def _log_from_track(scene: MountainScene, t_s: np.ndarray, enu: np.ndarray, yaw_deg: np.ndarray, roll_deg: np.ndarray,
                    pitch_deg: np.ndarray, gimbal_pitch_deg: np.ndarray, clearance_m: float) -> PoseLog:
    ground = scene.terrain.up_at(enu[:, 0], enu[:, 1])
    if not np.all(np.isfinite(ground)) or np.min(enu[:, 2] - ground) < clearance_m:
        raise GeometryError(f"flight path leaves the terrain or passes within {clearance_m} m of it")
    lat, lon, alt = scene.frame.to_geodetic(enu[:, 0], enu[:, 1], enu[:, 2])
    zero = np.zeros_like(t_s)
    return PoseLog(t_s, lat, lon, alt, roll_deg, pitch_deg, yaw_deg, gimbal_pitch_deg, zero, zero, stabilized=True)


def orbit_log(scene: MountainScene, centre_en_m: tuple[float, float], *, radius_m: float, height_m: float,
              speed_mps: float = 8.0, laps: float = 1.0, rate_hz: float = 10.0, start_deg: float = 0.0,
              clearance_m: float = 30.0, both_ways: bool = False, reverse_s: float = 6.0) -> PoseLog:
    """True pose log of an orbit around ``centre_en_m`` at ``radius_m``, ``height_m`` above
    the highest ground under the circle, nose and stabilised gimbal aimed at the centre,
    ``laps`` clockwise. ``both_ways``: then slow down, stop and fly ``laps`` back
    counter-clockwise (the speed ramps linearly through zero over ``reverse_s``): the
    boresight calibration orbit of thermal/README.md."""
    r = validate.positive_scalar("radius_m", radius_m)
    v = validate.positive_scalar("speed_mps", speed_mps)
    lap_s = validate.positive_scalar("laps", laps) * 2 * math.pi * r / v
    dt = 1.0 / validate.positive_scalar("rate_hz", rate_hz)
    if both_ways:
        ramp = validate.positive_scalar("reverse_s", reverse_s) / 2.0
        t_stop = lap_s + ramp / 2.0  # full speed to t_stop - ramp, then half on average: `laps` exactly
        t = np.arange(0.0, 2.0 * t_stop + 1e-9, dt)
        u = v * np.clip((t_stop - t) / ramp, -1.0, 1.0)  # signed speed, clockwise positive (m/s)
        ang = math.radians(start_deg) + np.concatenate(([0.0], np.cumsum(0.5 * (u[1:] + u[:-1]) * dt))) / r
    else:
        t = np.arange(0.0, lap_s + 1e-9, dt)
        u = np.full(t.size, v)
        ang = math.radians(start_deg) + v * t / r  # position angle, clockwise from north
    ce, cn = (float(x) for x in centre_en_m)
    circle = np.linspace(0.0, 2 * math.pi, 720)
    under = scene.terrain.up_at(ce + r * np.sin(circle), cn + r * np.cos(circle))
    if not np.all(np.isfinite(under)):
        raise GeometryError(f"orbit of radius {r} m around {centre_en_m} leaves the terrain")
    up = float(under.max()) + validate.positive_scalar("height_m", height_m)
    enu = np.stack((ce + r * np.sin(ang), cn + r * np.cos(ang), np.full(t.size, up)), axis=1)
    yaw = (np.degrees(ang) + 180.0) % 360.0  # facing the centre
    # Facing the centre, the centripetal acceleration is along the nose (pitch down) and a
    # clockwise speed-up is to the left (roll left).
    pitch = -np.degrees(np.arctan(u * u / (r * GRAVITY_MPS2)))
    roll = -np.degrees(np.arctan(np.gradient(u, t) / GRAVITY_MPS2))
    g_pitch = np.full(t.size, -math.degrees(math.atan2(up - float(scene.terrain.up_at(ce, cn)), r)))
    return _log_from_track(scene, t, enu, yaw, roll, pitch, g_pitch, clearance_m)


def lines_log(scene: MountainScene, waypoints_en_m, *, up_m: float, speed_mps: float = 8.0,
              gimbal_pitch_deg: float = -70.0, rate_hz: float = 10.0, turn_s: float = 4.0,
              clearance_m: float = 30.0) -> PoseLog:
    """True pose log along straight legs between ``waypoints_en_m`` ``(K, 2)`` at constant
    frame height ``up_m``, nose along the leg, hovering ``turn_s`` at each inner waypoint
    while yawing to the next leg (a single pass: two waypoints; a lawn-mower: more)."""
    wp = validate.points("waypoints_en_m", waypoints_en_m, 2)
    if wp.shape[0] < 2:
        raise InputError("lines_log needs at least two waypoints")
    v = validate.positive_scalar("speed_mps", speed_mps)
    dt = 1.0 / validate.positive_scalar("rate_hz", rate_hz)
    pts, yaws, pitch = [], [], []
    for k in range(wp.shape[0] - 1):
        a, b = wp[k], wp[k + 1]
        length = float(np.linalg.norm(b - a))
        heading = math.degrees(math.atan2(b[0] - a[0], b[1] - a[1])) % 360.0
        s = np.arange(0.0, length, v * dt)
        pts.append(a + (b - a) * (s / length)[:, None])
        yaws.append(np.full(s.size, heading))
        pitch.append(np.full(s.size, -4.0))  # nose down in forward flight
        if k + 1 < wp.shape[0] - 1:
            nxt = math.degrees(math.atan2(*(wp[k + 2] - b))) % 360.0
            turn = ((nxt - heading + 180.0) % 360.0) - 180.0
            n_turn = max(int(turn_s / dt), 1)
            pts.append(np.repeat(b[None], n_turn, 0))
            yaws.append(heading + turn * np.linspace(0.0, 1.0, n_turn))
            pitch.append(np.zeros(n_turn))
    en = np.concatenate(pts)
    t = np.arange(en.shape[0]) * dt
    enu = np.column_stack((en, np.full(t.size, validate.finite_scalar("up_m", up_m))))
    return _log_from_track(scene, t, enu, np.concatenate(yaws) % 360.0, np.zeros(t.size), np.concatenate(pitch),
                           np.full(t.size, validate.finite_scalar("gimbal_pitch_deg", gimbal_pitch_deg)),
                           clearance_m)


@dataclass(frozen=True, eq=False)
class MountainFlight:
    """A simulated flight. For the estimator: ``camera``, ``log`` (what the drone logged),
    ``stamps_s`` (camera time stamps of the frames) and :meth:`frames`. For scoring
    only: ``scene`` (terrain, fires), ``truth_log`` and ``errors`` (the realisation)."""

    scene: MountainScene
    camera: Camera
    truth_log: PoseLog
    log: PoseLog
    errors: PoseErrorModel
    stamps_s: np.ndarray
    sensor: ThermalSensor
    seed: int

    def true_camera(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(ENU position, rotation frame <- real camera) at frame ``k``'s exposure."""
        tau = self.stamps_s[k] + self.errors.time_offset_s
        cam, r = self.truth_log.camera_in_frame(self.scene.frame, [tau])
        return cam[0], r[0] @ self.errors.boresight().as_matrix()

    def render(self, k: int) -> np.ndarray:
        """Noise-free apparent temperature (deg C) ``(H, W)`` of frame ``k``."""
        cam, r = self.true_camera(k)
        return self.scene.render(self.camera, cam, r, float(self.stamps_s[k] + self.errors.time_offset_s))

    def frames(self, start: int = 0, stop: int | None = None, *, threads: int = 2
               ) -> Iterator[tuple[float, np.ndarray]]:
        """(camera stamp s, 16-bit radiometric counts ``(H, W)``) per frame, rendered on demand.

        ``threads`` frames are rendered ahead at once (the renderer's numpy and OpenCV work
        releases the GIL); the sensor noise is drawn in frame order, so the frames are the
        same for any ``threads``."""
        rng = np.random.default_rng(self.seed + 17)
        for k, celsius in rendered_in_order(self.render, range(len(self.stamps_s))[start:stop], threads=threads):
            yield float(self.stamps_s[k]), self.sensor.to_counts(self.sensor.observe(celsius, rng))


def projected_hotspots(flight: MountainFlight, rng: np.random.Generator, *, pixel_sigma_px: float = 0.3
                       ) -> list[tuple[float, list[Hotspot]]]:
    """Measurement-level sightings without rendering, for fast tests: each fire centre
    visible from the true camera (in the image, not hidden by the terrain) becomes a
    hotspot at its projection plus ``pixel_sigma_px`` Gaussian centroid noise."""
    cam_model = flight.camera
    pts = flight.scene.fire_enu()
    out = []
    for k, stamp in enumerate(flight.stamps_s):
        cam, r = flight.true_camera(k)
        uv = cam_model.project((pts - cam) @ r)
        spots = []
        for i in np.flatnonzero(np.isfinite(uv).all(axis=1)):
            if not cam_model.in_image(uv[i:i + 1])[0]:
                continue
            ray = pts[i] - cam
            rng_m = float(np.linalg.norm(ray))
            t = flight.scene.terrain.cast(cam, (ray / rng_m)[None])[0]
            if not np.isfinite(t) or t < rng_m - 1.0:
                continue  # behind a ridge
            u, v = uv[i] + rng.normal(0.0, pixel_sigma_px, 2)
            spots.append(Hotspot(float(u), float(v), 50, flight.scene.fires[i].peak_c, 100.0,
                                 (int(u) - 4, int(v) - 4, 9, 9), "celsius"))
        out.append((float(stamp), spots))
    return out


def fly(scene: MountainScene, camera: Camera, truth_log: PoseLog, errors: PoseErrorModel, *, frame_rate_hz: float = 1.0,
        seed: int = 0, sensor: ThermalSensor | None = None) -> MountainFlight:
    """Expose frames at ``frame_rate_hz`` over the log (kept clear of its ends by the time
    offset) and corrupt the log with ``errors``."""
    lo, hi = truth_log.span_s
    margin = abs(errors.time_offset_s) + 0.5
    tau = np.arange(lo + margin, hi - margin, 1.0 / validate.positive_scalar("frame_rate_hz", frame_rate_hz))
    log = errors.corrupt(truth_log, scene.frame, np.random.default_rng(seed))
    sensor = sensor or ThermalSensor(camera.width, camera.height, noise_sigma_c=0.05, dead_pixel_fraction=2e-4,
                                     seed=seed)
    return MountainFlight(scene, camera, truth_log, log, errors, tau - errors.time_offset_s, sensor, seed)


def write_mountain_flight(out_dir, flight: MountainFlight, *, dem_metres_per_px: float = 10.0,
                          dem_datum: str = "amsl", progress=iter) -> Path:
    """Write ``flight`` for ``skyfix thermal locate``: ``frames/NNNNN.png`` (16-bit counts),
    ``poses.csv`` (the drone's log read at each frame's camera stamp, as a user joins them),
    ``camera.json``, ``dem.tif`` (a DEM of the terrain, ``dem_datum``) and ``truth.json``
    (fires, boresight, time offset: for scoring only)."""
    import json

    from skyfix.camera_io import save_camera
    from skyfix.datasets.thermal_flight import write_poses_csv

    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    rows = []
    for k, (stamp, counts) in enumerate(progress(flight.frames())):
        name = f"frames/{k:05d}.png"
        cv2.imwrite(str(out / name), counts)
        rows.append((name, stamp, flight.log.pose_at(stamp)))
    write_poses_csv(out / "poses.csv", rows)
    save_camera(out / "camera.json", flight.camera)
    flight.scene.terrain.write_dem(out / "dem.tif", metres_per_px=dem_metres_per_px, datum=dem_datum)
    lat, lon, alt = flight.scene.frame.to_geodetic(*flight.scene.fire_enu().T)
    truth = {"dem": "dem.tif", "dem_datum": dem_datum, "kelvin_per_count": flight.sensor.kelvin_per_count,
             "boresight_deg": list(flight.errors.boresight_deg), "time_offset_s": flight.errors.time_offset_s,
             "fires": [{"index": i, "lat_deg": float(a), "lon_deg": float(b), "alt_m": float(c),
                        "radius_m": f.radius_m} for i, (a, b, c, f) in enumerate(zip(lat, lon, alt, flight.scene.fires,
                                                                                       strict=True))]}
    (out / "truth.json").write_text(json.dumps(truth, indent=2))
    return out
