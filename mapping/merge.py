"""Merge aligned submodels into one DSM, orthophoto, point cloud and camera list, a block at a time.

Every output is written in blocks (``block_px`` square) from windows read out of the submodels' own
GeoTIFFs and PLYs, so no step holds a whole survey's raster or cloud in memory. The ground belongs to the
submodel with the nearest *core* photo (:mod:`skyfix.mapping.submodels`): where two meet, both are
averaged across a band (``dsm_band_m`` for heights, ``ortho_band_m`` for the orthophoto: narrow, so no
ghosting) with weights falling linearly from the boundary, and a hole in one is filled from the other. Where
two submodels overlap, their height difference and the orthophotos' shift (phase correlation) are
measured: the seams a user would see. Coordinates: UTM metres of the reference submodel's zone minus
``origin`` (E, N; heights unchanged), in which the alignment matrices (:mod:`skyfix.mapping.align`) act.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skyfix.errors import DataError
from skyfix.mapping.align import apply
from skyfix.mapping.grid import Grid
from skyfix.mapping.model_files import PLY_DTYPE, ply_header

__all__ = ["Part", "MergeStats", "merge_rasters", "merge_points", "merge_cameras", "read_ply_header"]

log = logging.getLogger(__name__)

DSM_NODATA = -9999.0


@dataclass
class Part:
    """One submodel's outputs as the merge reads them; ``core_en_m``: its core photos' GPS (K, 2) local
    metres; ``matrix``: its alignment onto the reference (3x4, local metres)."""

    index: int
    folder: Path
    core_en_m: np.ndarray
    matrix: np.ndarray

    @property
    def dsm(self) -> Path:
        return self.folder / "dsm.tif"

    @property
    def ortho(self) -> Path:
        return self.folder / "orthophoto.tif"

    @property
    def ply(self) -> Path:
        return self.folder / "points.ply"

    @property
    def cameras(self) -> Path:
        return self.folder / "cameras.geojson"


@dataclass
class MergeStats:
    """Seams where submodels overlap, per pair ``"i-j"``: median height difference (m), its median
    absolute value, the orthophoto shift (px of the output, phase correlation over the largest common
    block) and the cells compared."""

    heights: dict = field(default_factory=dict)
    ortho_shift_px: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        out = {}
        for key in sorted(set(self.heights) | set(self.ortho_shift_px)):
            h = self.heights.get(key)
            arr = np.concatenate(h) if h else np.array([])
            shift = self.ortho_shift_px.get(key)
            out[key] = {"dsm_cells_compared": int(arr.size),
                        "dsm_median_difference_m": float(np.median(arr)) if arr.size else None,
                        "dsm_median_abs_difference_m": float(np.median(np.abs(arr))) if arr.size else None,
                        "ortho_shift_px": float(math.hypot(*shift[1])) if shift else None,
                        "ortho_px_compared": int(shift[0]) if shift else 0}
        return out


class _Raster:
    """A submodel raster, opened once, sampled through its alignment into output blocks."""

    def __init__(self, path: Path, part: Part, origin: np.ndarray) -> None:
        import rasterio

        self.ds = rasterio.open(path)
        self.part = part
        t = self.ds.transform
        self.west, self.north, self.res = t.c - origin[0], t.f - origin[1], t.a
        self.inv = np.linalg.inv(np.vstack((part.matrix, [0, 0, 0, 1])))[:3]
        self.nodata = self.ds.nodata

    def close(self) -> None:
        self.ds.close()

    def sample(self, east: np.ndarray, north: np.ndarray, z_ref: float):
        """Source pixels (bands, h, w) remapped onto the output cells ``east``/``north`` (local m), and the
        source positions (E, N local m) of those cells; None when the block misses this raster."""
        import cv2
        from rasterio.windows import Window

        pts = np.stack((east.ravel(), north.ravel(), np.full(east.size, z_ref)), axis=1)
        src = apply(self.inv, pts)
        col = ((src[:, 0] - self.west) / self.res - 0.5).reshape(east.shape)
        row = ((self.north - src[:, 1]) / self.res - 0.5).reshape(east.shape)
        c0, r0 = max(0, int(math.floor(col.min())) - 1), max(0, int(math.floor(row.min())) - 1)
        c1, r1 = min(self.ds.width, int(math.ceil(col.max())) + 2), min(self.ds.height, int(math.ceil(row.max())) + 2)
        if c1 <= c0 or r1 <= r0:
            return None
        data = self.ds.read(window=Window(c0, r0, c1 - c0, r1 - r0))
        mx, my = (col - c0).astype(np.float32), (row - r0).astype(np.float32)
        if data.dtype == np.uint8:
            img = cv2.remap(np.ascontiguousarray(np.moveaxis(data, 0, 2)), mx, my, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            out = np.moveaxis(img.reshape(east.shape + (-1,)), 2, 0)
        else:
            band = data[0].astype(np.float32)
            if self.nodata is not None:
                band[band == self.nodata] = np.nan
            out = cv2.remap(band, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                            borderValue=float("nan"))[None]
        return out, src[:, 0].reshape(east.shape), src[:, 1].reshape(east.shape)


def _ownership(trees: list, east: np.ndarray, north: np.ndarray, step_m: float) -> np.ndarray:
    """Distance (m) of every cell to each part's nearest core photo (``trees``: a ``cKDTree`` of each part's
    core photos), (parts, h, w): computed on cells of ``step_m`` and interpolated (a distance changes by at
    most one metre per metre)."""
    import cv2

    h, w = east.shape
    res = abs(float(east[0, 1] - east[0, 0])) if w > 1 else step_m
    k = max(1, int(step_m / max(res, 1e-9)))
    ce, cn = east[::k, ::k], north[::k, ::k]
    q = np.stack((ce.ravel(), cn.ravel()), axis=1)
    out = np.empty((len(trees), h, w), np.float32)
    for i, tree in enumerate(trees):
        d, _ = tree.query(q)
        coarse = d.reshape(ce.shape).astype(np.float32)
        if coarse.shape == (h, w):
            out[i] = coarse
        else:  # coarse cell (r, c) sits at fine cell (r k, c k): scale so those line up
            mx = np.clip(np.arange(w, dtype=np.float32) / k, 0, coarse.shape[1] - 1)
            my = np.clip(np.arange(h, dtype=np.float32) / k, 0, coarse.shape[0] - 1)
            out[i] = cv2.remap(coarse, *np.meshgrid(mx, my), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out


def _weights(dist: np.ndarray, valid: np.ndarray, band_m: float) -> np.ndarray:
    """Blend weights (parts, h, w): 1 for the nearest valid part, falling to 0 ``band_m`` further."""
    d = np.where(valid, dist, np.inf)
    nearest = d.min(axis=0)
    with np.errstate(invalid="ignore"):  # inf - inf where no part is valid: weight 0 there anyway
        return np.where(valid, np.clip(1.0 - (d - nearest) / max(band_m, 1e-6), 0.0, 1.0), 0.0)


def _blocks(grid: Grid, block_px: int):
    for r0 in range(0, grid.height, block_px):
        for c0 in range(0, grid.width, block_px):
            yield r0, c0, min(block_px, grid.height - r0), min(block_px, grid.width - c0)


def _cells(grid: Grid, origin: np.ndarray, r0: int, c0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.mgrid[r0:r0 + h, c0:c0 + w]
    east, north = grid.centres_m(rows, cols)
    return east - origin[0], north - origin[1]


def merge_rasters(parts: list[Part], origin: np.ndarray, epsg: int, dsm_path: Path, ortho_path: Path | None, *,
                  dsm_res_m: float, ortho_res_m: float | None, bounds_m: tuple[float, float, float, float],
                  z_ref_m: float, dsm_band_m: float = 3.0, ortho_band_m: float = 0.5, block_px: int = 1024,
                  on_block=None) -> tuple[Grid, Grid | None, MergeStats]:
    """Write the merged ``dsm_path`` (float32, AMSL m) and ``ortho_path`` (RGBA) as COGs on grids of
    ``dsm_res_m`` / ``ortho_res_m`` covering ``bounds_m`` (west, south, east, north; UTM m of ``epsg``).
    ``z_ref_m``: a typical ground height, where the alignments are evaluated horizontally (their tilts are
    small: the error is tilt x height range). ``on_block()`` is called after each block (progress)."""
    stats = MergeStats()
    west, south, east_b, north_b = bounds_m
    dsm_grid = Grid.covering(epsg, west, south, east_b, north_b, dsm_res_m)
    if not any(p.dsm.exists() for p in parts):
        raise DataError("no submodel produced a DSM: nothing to merge")
    _merge_raster(parts, "dsm", dsm_grid, origin, dsm_path, z_ref_m, dsm_band_m, block_px, stats, on_block)
    ortho_grid = None
    if ortho_path is not None and ortho_res_m:
        ortho_grid = Grid.covering(epsg, west, south, east_b, north_b, ortho_res_m)
        _merge_raster(parts, "ortho", ortho_grid, origin, ortho_path, z_ref_m, ortho_band_m, block_px, stats,
                      on_block)
    return dsm_grid, ortho_grid, stats


def _merge_raster(parts: list[Part], kind: str, grid: Grid, origin: np.ndarray, path: Path, z_ref_m: float,
                  band_m: float, block_px: int, stats: MergeStats, on_block) -> None:
    """One merged raster (``kind`` "dsm" or "ortho") written block by block."""
    from rasterio.windows import Window
    from scipy.spatial import cKDTree

    from skyfix.mapping.geotiff import write_cog_blocks

    def source_of(p: Part) -> Path:
        return p.dsm if kind == "dsm" else p.ortho

    sources = [(p, _Raster(source_of(p), p, origin)) for p in parts if source_of(p).exists()]
    ids = [p.index for p, _ in sources]
    trees = [cKDTree(p.core_en_m) for p, _ in sources]  # once, not per block

    def blocks():
        for r0, c0, h, w in _blocks(grid, block_px):
            e, n = _cells(grid, origin, r0, c0, h, w)
            dist = _ownership(trees, e, n, max(grid.resolution_m, 1.0))
            out = _dsm_block(sources, e, n, z_ref_m, dist, band_m, ids, stats) if kind == "dsm" else \
                _ortho_block(sources, e, n, z_ref_m, dist, band_m, ids, stats)
            if on_block:
                on_block()
            yield Window(c0, r0, w, h), out

    if kind == "dsm":
        profile = {"count": 1, "dtype": "float32", "nodata": DSM_NODATA}
        tags = {"units": "metre", "vertical_datum": "as recorded by the photos' GPS"}
    else:
        profile, tags = {"count": 4, "dtype": "uint8", "photometric": "RGB", "alpha": "YES"}, None
    try:
        write_cog_blocks(path, {"width": grid.width, "height": grid.height, "crs": f"EPSG:{grid.epsg}",
                                "transform": grid.affine(), **profile}, blocks(), tags)
    finally:
        for _, src in sources:
            src.close()


def _dsm_block(sources, e, n, z_ref_m, dist, band_m, ids, stats) -> np.ndarray:
    """Merged heights (1, h, w) of one block: each source's aligned heights, blended by ownership."""
    vals = np.full((len(sources),) + e.shape, np.nan, np.float32)
    for i, (part, src) in enumerate(sources):
        got = src.sample(e, n, z_ref_m)
        if got is not None:
            z_s, es, ns = got
            m = part.matrix
            vals[i] = m[2, 0] * es + m[2, 1] * ns + m[2, 2] * z_s[0] + m[2, 3]
    valid = np.isfinite(vals)
    wts = _weights(dist, valid, band_m)
    total = wts.sum(axis=0)
    merged = np.where(total > 0, (np.where(valid, vals, 0.0) * wts).sum(axis=0) / np.maximum(total, 1e-9),
                      np.nan)
    _pair_heights(stats, ids, vals, valid)
    return np.where(np.isfinite(merged), merged, DSM_NODATA).astype(np.float32)[None]


def _ortho_block(sources, e, n, z_ref_m, dist, band_m, ids, stats) -> np.ndarray:
    """Merged RGBA (4, h, w) of one block: each source's aligned pixels, blended by ownership."""
    imgs = np.zeros((len(sources), 4) + e.shape, np.uint8)
    for i, (_, src) in enumerate(sources):
        got = src.sample(e, n, z_ref_m)
        if got is not None:
            imgs[i] = got[0]
    valid = imgs[:, 3] >= 128
    wts = _weights(dist, valid, band_m)
    total = wts.sum(axis=0)
    rgb = (imgs[:, :3].astype(np.float32) * wts[:, None]).sum(axis=0) / np.maximum(total, 1e-9)
    out = np.zeros((4,) + e.shape, np.uint8)
    out[:3] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    out[3] = np.where(total > 0, 255, 0)
    out[:3, total <= 0] = 0
    _pair_shift(stats, ids, imgs, valid)
    return out


def _pair_heights(stats: MergeStats, ids: list[int], vals: np.ndarray, valid: np.ndarray,
                  max_samples: int = 20_000) -> None:
    for a in range(len(ids)):
        for b in range(a + 1, len(ids)):
            both = valid[a] & valid[b]
            if both.any():
                diff = (vals[a] - vals[b])[both]
                step = max(1, diff.size // max_samples)
                stats.heights.setdefault(f"{ids[a]}-{ids[b]}", []).append(diff[::step])


def _pair_shift(stats: MergeStats, ids: list[int], imgs: np.ndarray, valid: np.ndarray, min_px: int = 64 * 64) -> None:
    import cv2

    for a in range(len(ids)):
        for b in range(a + 1, len(ids)):
            both = valid[a] & valid[b]
            count = int(both.sum())
            key = f"{ids[a]}-{ids[b]}"
            if count < min_px or count <= stats.ortho_shift_px.get(key, (0, None))[0]:
                continue
            rows, cols = np.nonzero(both)
            sl = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
            mask = both[sl]
            grey = []
            for img in (imgs[a], imgs[b]):
                g = cv2.cvtColor(np.ascontiguousarray(np.moveaxis(img[:3], 0, 2)[sl]), cv2.COLOR_RGB2GRAY)
                g = g.astype(np.float32)
                g[~mask] = g[mask].mean()
                grey.append(g)
            if min(grey[0].shape) < 16:
                continue
            stats.ortho_shift_px[key] = (count, _shift_px(grey[0], grey[1], mask))


def _shift_px(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Shift (dx, dy) px of image ``b`` against ``a`` (b(x) = a(x - d)) over ``mask``: phase correlation,
    then Lucas-Kanade steps on the masked pixels (phase correlation's sub-pixel centroid alone is biased by
    a few tenths of a pixel on smooth ground)."""
    import cv2

    win = cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(a, b, win)
    d = np.array([dx, dy])
    gy, gx = np.gradient(a.astype(np.float64))
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    for _ in range(5):
        moved = cv2.warpAffine(b, np.float32([[1, 0, -d[0]], [0, 1, -d[1]]]), b.shape[::-1], flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REFLECT)
        r = (moved.astype(np.float64) - a)[inner]
        jx, jy = gx[inner], gy[inner]
        g = np.array([[jx @ jx, jx @ jy], [jx @ jy, jy @ jy]])
        if np.linalg.cond(g) > 1e6:
            break
        step = np.linalg.solve(g, [jx @ r, jy @ r])  # moved - a = grad a . (d - d_true): step = d - d_true
        d = d - step
        if np.abs(step).max() < 1e-3:
            break
    return float(d[0]), float(d[1])


def read_ply_header(path: Path) -> tuple[int, int]:
    """(vertex count, header bytes) of a PLY written by :func:`skyfix.mapping.model_files.write_ply`."""
    with open(path, "rb") as fh:
        head = b""
        while not head.endswith(b"end_header\n"):
            line = fh.readline()
            if not line:
                raise DataError(f"{path}: not a PLY written by skyfix (no end_header)")
            head += line
    count = next(int(line.split()[2]) for line in head.decode("ascii").splitlines()
                 if line.startswith("element vertex"))
    return count, len(head)


def merge_points(parts: list[Part], origin: np.ndarray, out_path: Path, chunk: int = 1_000_000) -> int:
    """Concatenate the parts' clouds, aligned, each keeping only the points nearest its own core photos
    (no doubled overlap); streamed in chunks of ``chunk`` points. Returns the count written."""
    from scipy.spatial import cKDTree

    owners = np.concatenate([np.full(len(p.core_en_m), p.index) for p in parts])
    tree = cKDTree(np.concatenate([p.core_en_m for p in parts]))
    body = Path(f"{out_path}.body")
    total = 0
    with open(body, "wb") as out:
        for part in parts:
            if not part.ply.exists():
                continue
            count, offset = read_ply_header(part.ply)
            cloud = np.memmap(part.ply, PLY_DTYPE, "r", offset=offset, shape=(count,))
            for s in range(0, count, chunk):
                rec = np.array(cloud[s:s + chunk])
                xyz = np.stack((rec["x"] - origin[0], rec["y"] - origin[1], rec["z"]), axis=1)
                xyz = apply(part.matrix, xyz)
                _, nearest = tree.query(xyz[:, :2])
                keep = owners[nearest] == part.index
                rec = rec[keep]
                rec["x"], rec["y"], rec["z"] = xyz[keep, 0] + origin[0], xyz[keep, 1] + origin[1], xyz[keep, 2]
                out.write(rec.tobytes())
                total += len(rec)
            del cloud
    with open(out_path, "wb") as out, open(body, "rb") as src:
        out.write(ply_header(total))
        shutil.copyfileobj(src, out, 16 << 20)
    os.unlink(body)
    return total


def merge_cameras(parts: list[Part], core: dict[int, set[str]], to_local, to_geodetic, out_path: Path) -> int:
    """One ``cameras.geojson``: every core photo once, from its own submodel, aligned. ``to_local`` maps
    (lon, lat, alt) arrays to local (N, 3) m, ``to_geodetic`` back."""
    features = []
    for part in parts:
        if not part.cameras.exists():
            continue
        for f in json.loads(part.cameras.read_text())["features"]:
            props = f["properties"]
            if props.get("photo") not in core[part.index]:
                continue
            lon, lat, alt = f["geometry"]["coordinates"]
            xyz = apply(part.matrix, to_local(np.array([lon]), np.array([lat]), np.array([alt])))
            lon2, lat2, alt2 = (float(v[0]) for v in to_geodetic(xyz))
            props = dict(props, submodel=part.index, alt_amsl_m=alt2)
            features.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [lon2, lat2, alt2]},
                             "properties": props})
    out_path.write_text(json.dumps({"type": "FeatureCollection", "features": features}, indent=1) + "\n")
    return len(features)
