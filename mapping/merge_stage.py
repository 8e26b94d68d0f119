"""The last step of a split run (:mod:`skyfix.mapping.scale_out`): read the submodels' outputs, align them
(:mod:`skyfix.mapping.align`), merge them (:mod:`skyfix.mapping.merge`) into the project folder, and
gather one report over the whole survey with each submodel's figures."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from skyfix.errors import DataError
from skyfix.mapping.align import align_submodels
from skyfix.mapping.merge import Part, merge_cameras, merge_points, merge_rasters
from skyfix.mapping.report import peak_memory_mib

__all__ = ["merge_submodels"]

log = logging.getLogger(__name__)


def _raster_facts(path: Path) -> tuple[tuple[float, float, float, float], float, float]:
    """(bounds W, S, E, N), pixel size and a typical value (median of a small overview) of a GeoTIFF."""
    import rasterio

    with rasterio.open(path) as ds:
        b = ds.bounds
        scale = max(1, max(ds.width, ds.height) // 256)
        small = ds.read(1, out_shape=(max(1, ds.height // scale), max(1, ds.width // scale)), masked=True)
        typical = float(np.ma.median(small)) if small.count() else float("nan")
        return (b.left, b.bottom, b.right, b.top), float(ds.transform.a), typical


class _LocalUtm:
    """UTM metres of ``epsg`` minus an origin near the photos (heights unchanged), and back to WGS84."""

    def __init__(self, epsg: int, by_name: dict) -> None:
        from skyfix.mapping.grid import utm_transformer

        self.fwd, self.back = utm_transformer(epsg), utm_transformer(epsg, inverse=True)
        self.utm = {n: np.array(self.fwd.transform(p.gps_lon_deg, p.gps_lat_deg)) for n, p in by_name.items()}
        self.origin = np.round(np.mean(list(self.utm.values()), axis=0), -1)

    def to_local(self, lon, lat, alt) -> np.ndarray:
        e, n = self.fwd.transform(lon, lat)
        return np.stack((np.asarray(e) - self.origin[0], np.asarray(n) - self.origin[1], np.asarray(alt, float)),
                        axis=1)

    def to_geodetic(self, xyz: np.ndarray):
        lon, lat = self.back.transform(xyz[:, 0] + self.origin[0], xyz[:, 1] + self.origin[1])
        return lon, lat, xyz[:, 2]


def _preview(tif: Path, png: Path) -> None:
    """A PNG of at most 2000 px from the COG's overviews (never the full raster in memory)."""
    import rasterio

    from skyfix.mapping.model_files import write_preview_png

    with rasterio.open(tif) as ds:
        k = max(1, max(ds.width, ds.height) // 2000)
        preview = ds.read(out_shape=(4, max(1, ds.height // k), max(1, ds.width // k)))
    write_preview_png(png, np.ascontiguousarray(np.moveaxis(preview, 0, 2)))


def merge_submodels(out: Path, subs, results: list[dict], by_name: dict, scale,
                    gps_sigma_m: tuple[float, ...] = (2.0, 4.0)) -> dict:
    """Align and merge the finished submodels in ``out/submodels`` into ``out``; the survey report (dict).
    ``gps_sigma_m``: the photos' GPS sigmas (horizontal, vertical) the joint alignment weighs them by."""
    t0 = time.perf_counter()
    folders = {s.index: out / "submodels" / s.name for s in subs}
    ok = [s for s, r in zip(subs, results, strict=True) if not r.get("error") and (folders[s.index] / "dsm.tif").exists()]
    if not ok:
        raise DataError("no submodel reconstructed: " + "; ".join(f"{s.name}: {r.get('error')}" for s, r in
                                                                   zip(subs, results, strict=True)))
    epsgs = {r.get("crs_epsg") for s, r in zip(subs, results, strict=True) if s in ok}
    if len(epsgs) != 1:
        raise DataError(f"submodels fell in different UTM zones {sorted(epsgs)}: merging across zones is not "
                        "supported; split the survey by zone and run each")
    epsg = epsgs.pop()
    local = _LocalUtm(epsg, by_name)
    utm, origin, to_local, to_geodetic = local.utm, local.origin, local.to_local, local.to_geodetic
    centres = {}
    for s in ok:
        feats = json.loads((folders[s.index] / "cameras.geojson").read_text())["features"]
        centres[s.index] = {f["properties"]["photo"]: to_local(*([v] for v in f["geometry"]["coordinates"]))[0]
                            for f in feats}
    alignments = align_submodels(centres, tuple(gps_sigma_m) if len(gps_sigma_m) == 2 else (2.0, 4.0))
    parts = [Part(s.index, folders[s.index], np.array([utm[n] - origin for n in s.core]), alignments[s.index].matrix)
             for s in ok]
    facts = {s.index: _raster_facts(folders[s.index] / "dsm.tif") for s in ok}
    ortho_facts = {s.index: _raster_facts(folders[s.index] / "orthophoto.tif") for s in ok
                   if (folders[s.index] / "orthophoto.tif").exists()}
    shift = max(float(np.abs(a.matrix[:2, 3]).max()) for a in alignments.values()) + 1.0
    bounds = (min(f[0][0] for f in facts.values()) - shift, min(f[0][1] for f in facts.values()) - shift,
              max(f[0][2] for f in facts.values()) + shift, max(f[0][3] for f in facts.values()) + shift)
    z_ref = float(np.nanmedian([f[2] for f in facts.values()]))
    dsm_res = min(f[1] for f in facts.values())
    ortho_res = min(f[1] for f in ortho_facts.values()) if ortho_facts else None
    from skyfix.progress import bar

    with bar(desc="merging", unit="block") as progress:
        dsm_grid, ortho_grid, seams = merge_rasters(
            parts, origin, epsg, out / "dsm.tif", out / "orthophoto.tif" if ortho_res else None, dsm_res_m=dsm_res,
            ortho_res_m=ortho_res, bounds_m=bounds, z_ref_m=z_ref, dsm_band_m=scale.dsm_band_m,
            ortho_band_m=scale.ortho_band_m, on_block=lambda: progress.update(1))
    points = merge_points(parts, origin, out / "points.ply")
    cameras = merge_cameras(parts, {s.index: set(s.core) for s in ok}, to_local, to_geodetic,
                            out / "cameras.geojson")
    outputs = {"dsm": str(out / "dsm.tif"), "points": str(out / "points.ply"),
               "cameras": str(out / "cameras.geojson"), "report": str(out / "report.json")}
    if ortho_grid is not None:
        _preview(out / "orthophoto.tif", out / "orthophoto.png")
        outputs.update(orthophoto=str(out / "orthophoto.tif"), orthophoto_png=str(out / "orthophoto.png"))
    per_sub = [{"index": s.index, "folder": str(folders[s.index]), "core_photos": len(s.core),
                "shared_photos": len(s.shared), **{k: v for k, v in r.items() if k != "group"},
                "alignment": alignments[s.index].to_dict() if s.index in alignments else None}
               for s, r in zip(subs, results, strict=True)]
    registered = set()
    for s in ok:
        registered |= set(centres[s.index]) & set(s.core)
    report = {"submodels": per_sub, "registered": len(registered),
              "registered_photos": sorted(registered), "epsg": epsg, "origin_utm_m": [float(v) for v in origin],
              "dsm_resolution_m": dsm_res, "ortho_resolution_m": ortho_res, "dense_points": points,
              "cameras": cameras, "seams": seams.to_dict(), "dsm_grid": dsm_grid.to_dict(),
              "ortho_grid": ortho_grid.to_dict() if ortho_grid else None,
              "worker_peak_memory_mib": max((r.get("worker_peak_memory_mib") or 0.0) for r in results),
              "merge_seconds": time.perf_counter() - t0, "merge_peak_memory_mib": peak_memory_mib(),
              "outputs": outputs}
    _report_png(out / "report.png", report, parts, origin, out / "orthophoto.png" if ortho_grid else None,
                ortho_grid)
    report["outputs"]["report_png"] = str(out / "report.png")
    return report


def _report_png(path: Path, report: dict, parts: list[Part], origin: np.ndarray, preview: Path | None, grid) -> None:
    """The orthophoto with each submodel's core photos in its own colour, and per-submodel figures."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax_t) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [2, 1]})
    if preview is not None and grid is not None:
        import cv2

        img = cv2.cvtColor(cv2.imread(str(preview), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
        w, s, e, n = grid.bounds_m
        ax.imshow(img, extent=(w, e, s, n))
    for part in parts:
        en = part.core_en_m + origin
        ax.scatter(en[:, 0], en[:, 1], s=10, label=f"submodel {part.index}")
    ax.legend(fontsize=8, loc="upper right")
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_title(f"{report['registered']} photos registered in {len(parts)} submodels, EPSG:{report['epsg']}",
                 fontsize=10)
    lines = []
    for sub in report["submodels"]:
        a = sub.get("alignment") or {}
        lines.append(f"{sub['index']}: {sub.get('registered', 0)}/{sub.get('photos', 0)} reg, georef "
                     f"{sub.get('georef_rms_m', float('nan')):.2f} m, overlap "
                     f"{a.get('rms_after_m', float('nan')):.3f} m, {sub.get('worker_peak_memory_mib', 0):.0f} MiB"
                     + (f"\n   {sub['error']}" if sub.get("error") else ""))
    for key, seam in report["seams"].items():
        dz, sh = seam["dsm_median_difference_m"], seam["ortho_shift_px"]
        lines.append(f"seam {key}: dz {dz if dz is None else round(dz, 3)} m, shift "
                     f"{sh if sh is None else round(sh, 2)} px")
    ax_t.axis("off")
    ax_t.text(0, 1, "\n".join(lines), va="top", family="monospace", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
