"""GeoTIFF writers (cloud-optimised, rasterio) for the pipeline's orthophoto, DSM and masks;
the other output formats are in :mod:`skyfix.mapping.model_files`."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from skyfix.mapping.grid import Grid

__all__ = ["write_cog_blocks", "write_dsm_tif", "write_mask_tif", "write_orthophoto_tif"]

def _write_cog(path: str | os.PathLike, data: np.ndarray, profile: dict, band_tags: dict | None = None) -> None:
    """Write ``data`` (bands, H, W) as a Cloud-Optimized GeoTIFF (see :func:`write_cog_blocks`)."""
    write_cog_blocks(path, profile, [(None, data)], band_tags)


def write_cog_blocks(path: str | os.PathLike, profile: dict, blocks, band_tags: dict | None = None) -> None:
    """Write a Cloud-Optimized GeoTIFF from ``blocks``, an iterable of ``(window, data)`` with
    ``data`` (bands, h, w) for a ``rasterio.windows.Window`` (None: the whole raster), so a raster
    larger than memory is written a block at a time: 512 px tiles, deflate, overviews inside the file
    before the full-resolution image (GDAL's COG driver, through a temporary tiled GeoTIFF since the
    driver only copies)."""
    import rasterio
    from rasterio.shutil import copy as rio_copy

    tmp = Path(f"{path}.part.tif")
    try:
        with rasterio.open(tmp, "w", driver="GTiff", tiled=True, blockxsize=512, blockysize=512,
                           compress="deflate", BIGTIFF="IF_SAFER", **profile) as dst:
            for window, data in blocks:
                dst.write(data, window=window)
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
