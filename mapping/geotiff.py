"""GeoTIFF, PNG preview, PLY and GeoJSON writers for the pipeline's outputs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from skyfix.mapping.grid import Grid

__all__ = ["write_cameras_geojson", "write_dsm_tif", "write_orthophoto_tif", "write_ply", "write_preview_png"]

_OVERVIEWS = (2, 4, 8, 16, 32)


def _overview_levels(grid: Grid) -> list[int]:
    return [f for f in _OVERVIEWS if min(grid.width, grid.height) // f >= 64] or [2]


def write_orthophoto_tif(path: str | os.PathLike, rgba: np.ndarray, grid: Grid) -> None:
    """RGBA uint8 ``(H, W, 4)`` as a tiled, deflate-compressed GeoTIFF with overviews
    (alpha band marks nodata)."""
    import rasterio
    from rasterio.enums import Resampling

    profile = {"driver": "GTiff", "width": grid.width, "height": grid.height, "count": 4, "dtype": "uint8",
               "crs": f"EPSG:{grid.epsg}", "transform": grid.affine(), "tiled": True, "blockxsize": 256,
               "blockysize": 256, "compress": "deflate", "photometric": "RGB",
               # GTiff creation option: band 4 is alpha. Setting colorinterp after the pixels are
               # written makes GDAL fail to modify the TIFF ExtraSamples tag.
               "alpha": "YES"}
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(np.moveaxis(rgba, 2, 0))
        dst.build_overviews(_overview_levels(grid), Resampling.average)
        dst.update_tags(ns="rio_overview", resampling="average")


def write_dsm_tif(path: str | os.PathLike, surface_m: np.ndarray, grid: Grid, nodata: float = -9999.0) -> None:
    """Float32 heights (metres, AMSL for the photo pipeline) with NaN written as ``nodata``."""
    import rasterio
    from rasterio.enums import Resampling

    data = np.where(np.isfinite(surface_m), surface_m, nodata).astype(np.float32)
    profile = {"driver": "GTiff", "width": grid.width, "height": grid.height, "count": 1, "dtype": "float32",
               "crs": f"EPSG:{grid.epsg}", "transform": grid.affine(), "nodata": nodata, "compress": "deflate",
               "tiled": grid.width >= 256 and grid.height >= 256}
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
        dst.update_tags(1, units="metre", vertical_datum="as recorded by the photos' GPS (usually AMSL)")
        dst.build_overviews(_overview_levels(grid), Resampling.average)


def write_preview_png(path: str | os.PathLike, rgba: np.ndarray, max_side_px: int = 2000) -> None:
    """Downscaled RGBA PNG (transparent where there is no data)."""
    import cv2

    h, w = rgba.shape[:2]
    scale = min(1.0, max_side_px / max(h, w))
    small = cv2.resize(rgba, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA) \
        if scale < 1.0 else rgba
    cv2.imwrite(str(path), cv2.cvtColor(small, cv2.COLOR_RGBA2BGRA))


def write_ply(path: str | os.PathLike, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY of ``(N, 3)`` float64 coordinates and ``(N, 3)`` uint8 colours."""
    n = len(xyz)
    header = ("ply\nformat binary_little_endian 1.0\n"
              "comment coordinates: UTM easting/northing metres, height metres (AMSL)\n"
              f"element vertex {n}\nproperty double x\nproperty double y\nproperty double z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    rec = np.empty(n, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["r"], rec["g"], rec["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())


def write_cameras_geojson(path: str | os.PathLike, features: list[dict]) -> None:
    """FeatureCollection of camera points; each item: lat_deg, lon_deg, alt_m and properties."""
    fc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [f["lon_deg"], f["lat_deg"], f["alt_m"]]},
         "properties": f.get("properties", {})} for f in features]}
    Path(path).write_text(json.dumps(fc, indent=1) + "\n")
