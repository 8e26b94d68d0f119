"""A map people open: fires with their 95 % ellipses over the DEM's hillshade (PNG)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from skyfix.thermal.ground import DemGround
from skyfix.thermal.io import ellipse_axes


def hillshade(up_m: np.ndarray, step_m: float, *, azimuth_deg: float = 315.0, altitude_deg: float = 45.0) -> np.ndarray:
    """Shaded relief ``(H, W)`` in 0-1 of a north-up height grid (row 0 north) with cells of
    ``step_m``, lit from ``azimuth_deg`` (clockwise from north) at ``altitude_deg``."""
    z = np.where(np.isfinite(up_m), up_m, np.nanmedian(up_m))
    d_north, d_east = np.gradient(z, step_m)
    d_north = -d_north  # rows run southwards
    az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
    light = np.array([math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)])
    normal = np.stack((-d_east, -d_north, np.ones_like(z)), axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.clip(normal @ light, 0.0, 1.0)


def fires_map_png(path: str | Path, fires, dem: DemGround, *, track_latlon: np.ndarray | None = None,
                  truth_latlon: np.ndarray | None = None, margin_m: float = 80.0, title: str = "") -> Path:
    """Write a PNG: hillshade of ``dem`` around the fires (and the camera track), each fire
    a cross with its 95 % ellipse (red burning, black out) and id; optional true positions
    ``(K, 2)`` lat, lon as green dots. Axes: east/north metres about the DEM's centre."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    local = dem.local()
    fr = local.frame
    pts = [np.array([fr.to_enu(f.lat_deg, f.lon_deg, f.alt_m)[k] for k in range(2)], float) for f in fires]
    xy = list(pts)
    track = None
    if track_latlon is not None and len(track_latlon):
        t = np.asarray(track_latlon, float)
        e, n, _ = fr.to_enu(t[:, 0], t[:, 1], np.full(len(t), fr.alt0_m))
        track = np.column_stack((e, n))
        xy += list(track)
    fig, ax = plt.subplots(figsize=(8, 8))
    half = local.half_m
    ax.imshow(hillshade(local.up_m, local.step_m), cmap="gray", extent=(-half, half, -half, half), vmin=0, vmax=1)
    levels = np.arange(np.floor(local.min_up_m / 20) * 20, local.max_up_m, 20.0)
    axis = np.linspace(-half, half, local.up_m.shape[0])
    ax.contour(axis, axis[::-1], local.up_m, levels=levels, colors="0.35", linewidths=0.4)
    if track is not None:
        ax.plot(track[:, 0], track[:, 1], "-", color="tab:blue", lw=1, label="camera track")
    if truth_latlon is not None and len(truth_latlon):
        tl = np.asarray(truth_latlon, float)
        e, n, _ = fr.to_enu(tl[:, 0], tl[:, 1], np.full(len(tl), fr.alt0_m))
        ax.plot(e, n, "o", color="tab:green", ms=4, label="true fires")
    for f, p in zip(fires, pts, strict=True):
        a, b, az = ellipse_axes(f.cov_en_m2)
        colour = "red" if f.burning else "black"
        ax.add_patch(Ellipse((p[0], p[1]), 2 * a, 2 * b, angle=90.0 - az, fill=False, color=colour, lw=1.2))
        ax.plot(p[0], p[1], "x", color=colour)
        ax.annotate(f"{f.fire_id}: 95 % {a:.1f} x {b:.1f} m", (p[0], p[1]), textcoords="offset points",
                    xytext=(6, 6), fontsize=8, color=colour)
    if xy:
        arr = np.array(xy)
        lo, hi = arr.min(axis=0) - margin_m, arr.max(axis=0) + margin_m
        ax.set_xlim(max(lo[0], -half), min(hi[0], half))
        ax.set_ylim(max(lo[1], -half), min(hi[1], half))
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title or "fires (x) with 95 % ellipses over the DEM hillshade (20 m contours)")
    ax.legend(loc="best", fontsize=8)
    path = Path(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
