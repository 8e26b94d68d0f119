"""GeoTIFF, PNG preview, PLY and GeoJSON writers for the pipeline's outputs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from skyfix.mapping.grid import Grid

__all__ = ["write_cameras_geojson", "write_dsm_tif", "write_orthophoto_tif", "write_ply", "write_preview_png"]

def _write_cog(path: str | os.PathLike, data: np.ndarray, profile: dict, band_tags: dict | None = None) -> None:
    """Write ``data`` (bands, H, W) as a Cloud-Optimized GeoTIFF: 512 px tiles, deflate,
    overviews inside the file before the full-resolution image (GDAL's COG driver, through
    a temporary tiled GeoTIFF since the driver only copies)."""
    import rasterio
    from rasterio.shutil import copy as rio_copy

    tmp = Path(f"{path}.part.tif")
    try:
        with rasterio.open(tmp, "w", driver="GTiff", tiled=True, blockxsize=512, blockysize=512,
                           compress="deflate", BIGTIFF="IF_SAFER", **profile) as dst:
            dst.write(data)
            if band_tags:
                dst.update_tags(1, **band_tags)
        rio_copy(tmp, path, driver="COG", compress="DEFLATE", blocksize=512, overview_resampling="average",
                 BIGTIFF="IF_SAFER")
    finally:
        tmp.unlink(missing_ok=True)


def write_orthophoto_tif(path: str | os.PathLike, rgba: np.ndarray, grid: Grid) -> None:
    """RGBA uint8 ``(H, W, 4)`` at full resolution as a tiled Cloud-Optimized GeoTIFF with
    overviews (alpha band marks nodata)."""
    _write_cog(path, np.moveaxis(rgba, 2, 0), {
        "width": grid.width, "height": grid.height, "count": 4, "dtype": "uint8", "crs": f"EPSG:{grid.epsg}",
        "transform": grid.affine(), "photometric": "RGB",
        # GTiff creation option: band 4 is alpha (colorinterp set afterwards fails on ExtraSamples).
        "alpha": "YES"})


def write_dsm_tif(path: str | os.PathLike, surface_m: np.ndarray, grid: Grid, nodata: float = -9999.0) -> None:
    """Float32 heights (metres, AMSL for the photo pipeline) with NaN written as ``nodata``,
    as a tiled Cloud-Optimized GeoTIFF."""
    data = np.where(np.isfinite(surface_m), surface_m, nodata).astype(np.float32)
    _write_cog(path, data[None], {"width": grid.width, "height": grid.height, "count": 1, "dtype": "float32",
                                  "crs": f"EPSG:{grid.epsg}", "transform": grid.affine(), "nodata": nodata},
               {"units": "metre", "vertical_datum": "as recorded by the photos' GPS (usually AMSL)"})


def write_mask_tif(path: str | os.PathLike, mask: np.ndarray, grid: Grid, description: str) -> None:
    """A uint8 0/1 band on ``grid`` (e.g. the DSM cells that are interpolated) as a COG."""
    _write_cog(path, np.asarray(mask, np.uint8)[None], {"width": grid.width, "height": grid.height, "count": 1,
                                                        "dtype": "uint8", "crs": f"EPSG:{grid.epsg}",
                                                        "transform": grid.affine()}, {"meaning": description})


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
