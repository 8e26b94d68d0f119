"""The pipeline's non-raster outputs: a binary PLY point cloud, a PNG preview and a GeoJSON
of camera positions (the GeoTIFFs are in :mod:`skyfix.mapping.geotiff`)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

__all__ = ["PLY_DTYPE", "ply_header", "write_cameras_geojson", "write_ply", "write_preview_png"]


def write_preview_png(path: str | os.PathLike, rgba: np.ndarray, max_side_px: int = 2000) -> None:
    """Downscaled RGBA PNG (transparent where there is no data)."""
    import cv2

    h, w = rgba.shape[:2]
    scale = min(1.0, max_side_px / max(h, w))
    small = cv2.resize(rgba, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA) \
        if scale < 1.0 else rgba
    cv2.imwrite(str(path), cv2.cvtColor(small, cv2.COLOR_RGBA2BGRA))


#: one vertex of the pipeline's PLY clouds (binary little endian)
PLY_DTYPE = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")])


def ply_header(n: int) -> bytes:
    """The header of a cloud of ``n`` :data:`PLY_DTYPE` vertices (UTM metres, heights AMSL)."""
    return ("ply\nformat binary_little_endian 1.0\n"
            "comment coordinates: UTM easting/northing metres, height metres (AMSL)\n"
            f"element vertex {n}\nproperty double x\nproperty double y\nproperty double z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode("ascii")


def write_ply(path: str | os.PathLike, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY of ``(N, 3)`` float64 coordinates and ``(N, 3)`` uint8 colours."""
    n = len(xyz)
    rec = np.empty(n, dtype=PLY_DTYPE)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["r"], rec["g"], rec["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    with open(path, "wb") as fh:
        fh.write(ply_header(n))
        fh.write(rec.tobytes())


def write_cameras_geojson(path: str | os.PathLike, features: list[dict]) -> None:
    """FeatureCollection of camera points; each item: lat_deg, lon_deg, alt_m and properties."""
    fc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [f["lon_deg"], f["lat_deg"], f["alt_m"]]},
         "properties": f.get("properties", {})} for f in features]}
    Path(path).write_text(json.dumps(fc, indent=1) + "\n")
