"""Foundation accuracy and speed: skyfix.geo and skyfix.camera against pyproj and hand cases.

Goals (issue 2): ENU round trip <= 1 mm within 20 km; ENU vs pyproj's ECEF pipeline
<= 1 mm; destination/inverse vs pyproj.Geod <= 1 mm; ray round trip <= 1e-6 px
(pinhole) and <= 1e-3 px per distortion model; a rendered ground point projects back
within 0.5 px. Prints every figure and, last, the worst ratio figure/goal; exits 1 if
any goal is missed.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import pyproj

from skyfix.camera import Camera, CameraPose, ground_intersection, world_to_pixel
from skyfix.datasets import GroundTexture, render_ground
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.geo import LocalFrame, destination, ecef_to_enu_rotation, inverse


def geodesy(rng: np.random.Generator) -> dict[str, float]:
    worst = {"enu_round_trip_m": 0.0, "enu_vs_pyproj_ecef_m": 0.0, "geodesic_vs_geod_m": 0.0}
    to_ecef = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    geod = pyproj.Geod(ellps="WGS84")
    n = 20_000
    for _ in range(10):
        lat0, lon0, h0 = rng.uniform(-85, 85), rng.uniform(-180, 180), rng.uniform(-50, 3000)
        frame = LocalFrame(lat0, lon0, h0)
        lat, lon = destination(np.full(n, lat0), np.full(n, lon0), rng.uniform(0, 360, n),
                               rng.uniform(0, 20_000, n))
        alt = rng.uniform(-100, 5000, n)
        e, nn, u = frame.to_enu(lat, lon, alt)
        enu2 = np.stack(frame.to_enu(*frame.to_geodetic(e, nn, u)), axis=1)
        worst["enu_round_trip_m"] = max(worst["enu_round_trip_m"],
                                        float(np.max(np.linalg.norm(enu2 - np.stack((e, nn, u), 1), axis=1))))
        xyz = np.stack(to_ecef.transform(lon, lat, alt), axis=1)
        ref = (xyz - np.array(to_ecef.transform(lon0, lat0, h0))) @ ecef_to_enu_rotation(lat0, lon0).T
        worst["enu_vs_pyproj_ecef_m"] = max(worst["enu_vs_pyproj_ecef_m"],
                                            float(np.max(np.linalg.norm(ref - np.stack((e, nn, u), 1), axis=1))))
        az, dist = rng.uniform(0, 360, n), rng.uniform(0, 50_000, n)
        lat2, lon2 = destination(np.full(n, lat0), np.full(n, lon0), az, dist)
        lon_r, lat_r, _ = geod.fwd(np.full(n, lon0), np.full(n, lat0), az, dist)
        _, err = inverse(lat2, lon2, lat_r, lon_r)
        _, d_back = inverse(np.full(n, lat0), np.full(n, lon0), lat2, lon2)
        worst["geodesic_vs_geod_m"] = max(worst["geodesic_vs_geod_m"], float(np.max(err)),
                                          float(np.max(np.abs(d_back - dist))))
    return worst


def camera_round_trips() -> dict[str, float]:
    out = {}
    models = {"pinhole": None, "brown_conrady": BrownConrady(-0.18, 0.035, 0.0012, -0.0008, -0.002),
              "fisheye": Fisheye(0.08, -0.03, 0.01, -0.002), "barrel": Barrel(0.1, -0.32, 0.0)}
    for name, model in models.items():
        cam = Camera.from_fov(1920, 1080, 90.0, distortion=model)
        u, v = np.meshgrid(np.arange(-0.5, 1920, 3.0), np.arange(-0.5, 1080, 3.0))
        uv = np.stack((u.ravel(), v.ravel()), axis=1)
        out[f"ray_round_trip_px[{name}]"] = float(np.max(np.abs(cam.project(cam.pixel_to_ray(uv)) - uv)))
    return out


def render_check(rng: np.random.Generator) -> tuple[float, float]:
    frame = LocalFrame(47.37, 8.54, 410.0)
    cam = Camera.from_fov(640, 512, 50.0, distortion=BrownConrady(-0.1, 0.01))
    worst = 0.0
    for _ in range(10):
        pose = CameraPose(47.37, 8.54, 410.0 + rng.uniform(40, 150), roll_deg=rng.uniform(-15, 15),
                          pitch_deg=rng.uniform(-15, 15), yaw_deg=rng.uniform(-180, 180),
                          gimbal_pitch_deg=rng.uniform(-90, -60), stabilized=False)
        uv = np.array([[rng.uniform(60, 580), rng.uniform(60, 450)]])
        ground = ground_intersection(cam, pose, uv, frame.alt0_m, frame)
        tex = np.zeros((4001, 4001), np.float32)
        probe = GroundTexture(tex, 0.1, frame)
        c, r = np.round(probe.en_to_px(ground[:, :2])[0]).astype(int)
        tex[r - 1:r + 2, c - 1:c + 2] = 1000.0
        texture = GroundTexture(tex, 0.1, frame)
        img = render_ground(texture, cam, pose, supersample=3).image
        vv, uu = np.nonzero(img > 1.0)
        w = img[vv, uu]
        found = np.array([(uu * w).sum() / w.sum(), (vv * w).sum() / w.sum()])
        expected = world_to_pixel(cam, pose, frame, texture.px_to_enu(np.array([[c, r]], float)))[0]
        worst = max(worst, float(np.linalg.norm(found - expected)))
    texture = GroundTexture(rng.random((4000, 4000), np.float32), 0.1, frame)
    pose = CameraPose(47.37, 8.54, 510.0, gimbal_pitch_deg=-70.0)
    render_ground(texture, cam, pose)
    t0 = time.perf_counter()
    for _ in range(20):
        render_ground(texture, cam, pose)
    return worst, (time.perf_counter() - t0) / 20


def main() -> int:
    rng = np.random.default_rng(7)
    goals = {"enu_round_trip_m": 1e-3, "enu_vs_pyproj_ecef_m": 1e-3, "geodesic_vs_geod_m": 1e-3,
             "ray_round_trip_px[pinhole]": 1e-6, "ray_round_trip_px[brown_conrady]": 1e-3,
             "ray_round_trip_px[fisheye]": 1e-3, "ray_round_trip_px[barrel]": 1e-3,
             "render_reprojection_px": 0.5}
    figures = geodesy(rng) | camera_round_trips()
    figures["render_reprojection_px"], render_s = render_check(rng)
    worst_ratio = 0.0
    for name, goal in goals.items():
        ratio = figures[name] / goal
        worst_ratio = max(worst_ratio, ratio)
        print(f"{name:36s} {figures[name]:.3e}  goal <= {goal:.0e}  ({'met' if ratio <= 1 else 'MISSED'})")
    print(f"render_ground 640x512: {render_s * 1e3:.1f} ms/frame")
    print(f"worst figure/goal ratio: {worst_ratio:.3g} (<= 1 means every foundation goal is met)")
    return 0 if worst_ratio <= 1.0 else 1


if __name__ == "__main__":
    sys.exit(main())
