"""Photo-to-model pipeline: geotagged photos -> orthophoto, DSM, point cloud, report.

Stages run in order over one project folder (``out_dir``); each writes its outputs and
a marker ``work/stages/<stage>.json`` (with its time). On a new run a stage whose marker
exists is skipped unless it is forced or an earlier stage ran again, so a run resumes
after a crash or Ctrl-C. Feature extraction and matching keep the pycolmap database
(``work/database.db``) and are never redone once their markers exist (force them with
``force=("features",)``); pycolmap also skips images already in the database.

Stages: ``photos`` (EXIF, rejections, GPS overlap), ``correct`` (optional barrel lens
correction), ``features``, ``matches``, ``mapping`` (pycolmap), ``georef`` (similarity to
GPS in a local ENU frame), ``dsm``, ``ortho``, ``export`` (PLY, GeoJSON, report).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import resource
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skyfix.camera import Camera
from skyfix.distortion import Barrel
from skyfix.errors import ConfigurationError, DataError, InputError, SkyfixError
from skyfix.mapping.photos import Photo, camera_groups, check_gps_overlap, load_photos
from skyfix.mapping.report import Report

__all__ = ["STAGES", "PipelineConfig", "run_pipeline", "stage_options"]

log = logging.getLogger(__name__)

STAGES = ("photos", "correct", "features", "matches", "mapping", "georef", "dsm", "ortho", "export")


@dataclass(frozen=True)
class PipelineConfig:
    """Everything a run needs; defaults suit 1-12 Mpx survey photos on a laptop."""

    photos_dir: str | os.PathLike
    out_dir: str | os.PathLike
    barrel: Barrel | None = None          # ImageMagick barrel model: photos are corrected first
    calibration: Camera | None = None     # pre-calibrated lens, passed to pycolmap (held fixed)
    resolution_cm: float | None = None    # orthophoto pixel; None: the photos' median GSD
    dsm_resolution_m: float | None = None  # DSM cell; None: dense_cell_px matched pixels (sparse: 2x point spacing)
    max_ortho_mpx: float | None = None    # only if asked: raise the pixel size if the orthophoto would be larger
    max_image_size_px: int = 1600         # photos are downscaled to this for features
    max_features: int = 4000              # SIFT features per photo
    exhaustive_max_photos: int = 40       # more photos than this: spatial (GPS neighbour) matching
    spatial_neighbours: int = 12          # GPS neighbours matched per photo in spatial matching
    max_agl_m: float = 120.0              # upper bound of height above ground for the overlap check
    georef_max_error_m: float = 10.0      # RANSAC inlier distance camera centre <-> GPS
    two_view_max_offset_m: float = 5.0    # a photo placed by a two-view model: this close to its GPS horizontally
    two_view_max_vertical_m: float = 12.0  # ... and vertically (GPS heights wander: 3x a 4 m sigma)
    ortho_seams: bool = True              # one photo per pixel, graph-cut seams, gains (False: feathered mean)
    seam_band_px: float = 6.0             # blending band across a seam, orthophoto pixels
    blend_power: float = 2.0              # feathered mean only: exponent of the edge-distance weight
    estimate_gps_lag: bool = True         # estimate the GPS time lag from the model and remove it (reported)
    refine_focal: bool = False            # let bundle adjustment move the focal length (see sfm.reconstruct)
    gps_sigma_m: tuple[float, float] = (2.0, 4.0)  # GPS pose prior std dev (horizontal, vertical); () = no priors
    seed: int = 0                         # pycolmap's random seed: the same photos give the same model
    dense: bool = True                    # DSM from dense stereo matching (False: from the sparse points)
    dense_scale: float = 0.5              # photos are matched at this fraction of their size
    dense_cell_px: float = 2.0            # DSM cell = this many matched pixels on the ground
    max_dense_points: int = 5_000_000     # points.ply holds at most this many dense points (stated in the report)
    threads: int = -1                     # -1: all cores
    force: tuple[str, ...] = ()           # stages to re-run even when their outputs exist

    def __post_init__(self) -> None:
        if self.barrel is not None and self.calibration is not None:
            raise ConfigurationError("give either barrel= (correct photos) or calibration= (pass the lens "
                                     "model to pycolmap), not both")
        unknown = set(self.force) - set(STAGES)
        if unknown:
            raise ConfigurationError(f"force names unknown stage(s) {sorted(unknown)}; stages are {list(STAGES)}")
        if not 0.05 <= self.dense_scale <= 1.0:
            raise InputError(f"dense_scale must be in [0.05, 1], got {self.dense_scale!r}")
        for name in ("resolution_cm", "dsm_resolution_m", "max_ortho_mpx"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise InputError(f"{name} must be a positive number, got {v!r}")


#: The options each stage's result depends on (its own and, for the stages that are
#: never redone by a change upstream, those of the stages it reads). A stage whose
#: recorded options differ runs again, and every later stage with it.
_STAGE_OPTIONS = {
    "photos": (), "correct": ("barrel",),
    "features": ("barrel", "calibration", "max_image_size_px", "max_features"),
    "matches": ("barrel", "calibration", "max_image_size_px", "max_features", "exhaustive_max_photos",
                "spatial_neighbours", "seed"),
    "mapping": ("calibration", "refine_focal", "gps_sigma_m", "seed"),
    "georef": ("georef_max_error_m", "two_view_max_offset_m", "two_view_max_vertical_m", "estimate_gps_lag"),
    "dsm": ("dense", "dense_scale", "dense_cell_px", "dsm_resolution_m", "max_dense_points", "seed"),
    "ortho": ("resolution_cm", "max_ortho_mpx", "ortho_seams", "seam_band_px", "blend_power"),
    "export": (),
}


def stage_options(config: PipelineConfig, stage: str) -> dict:
    """The options ``stage`` depends on, as JSON values (objects by their repr)."""
    def plain(value):
        if value is None or isinstance(value, (bool, int, float, str)):
            return value
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        return repr(value)

    return {name: plain(getattr(config, name)) for name in _STAGE_OPTIONS[stage]}


class _Project:
    """Paths of a project folder and the stage markers."""

    def __init__(self, out_dir: Path) -> None:
        self.root = out_dir
        self.work = out_dir / "work"
        self.stages = self.work / "stages"
        self.database = self.work / "database.db"
        self.sparse = self.work / "sparse"
        self.georef = self.work / "georef"
        self.corrected = self.work / "corrected"
        self.stages.mkdir(parents=True, exist_ok=True)

    def marker(self, stage: str) -> dict | None:
        path = self.stages / f"{stage}.json"
        return json.loads(path.read_text()) if path.exists() else None

    def mark(self, stage: str, data: dict) -> None:
        tmp = self.stages / f"{stage}.json.part"
        tmp.write_text(json.dumps(data, indent=1))
        os.replace(tmp, self.stages / f"{stage}.json")

    def reset_database(self, stage: str) -> None:
        """Before re-running ``features`` (the database goes) or ``matches`` (its matches go):
        pycolmap skips images and pairs the database already holds."""
        if stage == "features":
            for suffix in ("", "-wal", "-shm"):
                Path(f"{self.database}{suffix}").unlink(missing_ok=True)
        elif self.database.exists():
            import pycolmap

            db = pycolmap.Database.open(str(self.database))
            try:
                db.clear_matches()
                db.clear_two_view_geometries()
            finally:
                db.close()

    def clear_from(self, stage: str) -> None:
        for later in STAGES[STAGES.index(stage):]:
            (self.stages / f"{later}.json").unlink(missing_ok=True)


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_pipeline(config: PipelineConfig) -> Report:
    """Run (or resume) the pipeline; returns the :class:`Report` also saved as ``report.json``.

    Raises :class:`InputError` for a missing/empty photo folder and :class:`DataError` when
    no photo is usable or nothing reconstructs; the report written so far says why.
    """
    import cv2

    start = time.perf_counter()
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    project = _Project(out)
    report = Report(str(config.photos_dir), str(out))
    if config.threads > 0:
        cv2.setNumThreads(config.threads)
    state: dict = {}
    dirty = False
    try:
        for stage in STAGES:
            marker = project.marker(stage)
            options = stage_options(config, stage)
            changed = marker is not None and marker.get("options") != options
            if changed:
                log.info("stage %s runs again: its options changed since the last run (%s)", stage,
                         ", ".join(k for k in options if (marker.get("options") or {}).get(k) != options[k]))
            rerun = stage in config.force or marker is None or changed or \
                (dirty and stage not in ("features", "matches"))
            if stage == "photos":
                rerun = True  # cheap, and later stages need the photo list
            if not rerun:
                report.stage_seconds[stage] = marker.get("seconds", 0.0)
                report.resumed_stages.append(stage)
                _STAGE_LOAD[stage](config, project, state, report, marker)
                continue
            t0 = time.perf_counter()
            log.info("stage %s", stage)
            if marker is not None and stage in ("features", "matches"):
                project.reset_database(stage)
            data = _STAGE_RUN[stage](config, project, state, report) or {}
            data["seconds"] = time.perf_counter() - t0
            data["options"] = options
            if stage != "photos":
                dirty = True
            elif marker is not None and marker.get("names") != data.get("names"):
                log.info("the photo set changed since the last run: every stage runs again")
                project.clear_from("correct")
                config = dataclasses.replace(config, force=STAGES)
            project.mark(stage, data)
            report.stage_seconds[stage] = data["seconds"]
    except SkyfixError as exc:
        report.error = str(exc)
        raise
    finally:
        report.total_seconds = time.perf_counter() - start
        report.peak_memory_mib = _peak_mib()
        report.save_json(out / "report.json")
    return report


# --------------------------------------------------------------------------- stages


def _photos_run(config, project, state, report) -> dict:
    photos, rejected = load_photos(config.photos_dir)
    report.photos_found = len(photos) + len(rejected)
    report.rejected = [{"photo": r.name, "reason": r.reason} for r in rejected]
    report.warnings += [f"rejected {r.name}: {r.reason}" for r in rejected]
    if not photos:
        raise DataError(f"none of the {len(rejected)} photo(s) in {config.photos_dir} is usable: "
                        + "; ".join(f"{r.name}: {r.reason}" for r in rejected[:5]))
    groups = camera_groups(photos)
    report.camera_groups = [{"make": k[0], "model": k[1], "width": k[2], "height": k[3], "focal_px": k[4],
                             "focal_source": v[0].focal_source, "focal_refined": config.refine_focal,
                             "photos": len(v)} for k, v in groups.items()]
    for k, v in groups.items():
        if v[0].focal_source == "35mm-equivalent" and max(k[2], k[3]) / min(k[2], k[3]) > 1.6:
            report.warnings.append(f"{k[0]} {k[1]}: focal length from the 35 mm equivalent of a {k[2]}x{k[3]} "
                                   "frame; if it is cropped from the sensor this is 4-5 % short and every height "
                                   "above ground with it (give a lens calibration)")
    if len(groups) > 1:
        report.warnings.append(f"mixed cameras: {len(groups)} camera models, each with its own calibration")
    report.without_gps = [p.name for p in photos if not p.has_gps]
    if report.without_gps:
        report.warnings.append(f"{len(report.without_gps)} photo(s) without GPS in EXIF reconstruct but are not "
                               "used for georeferencing")
    overlap = check_gps_overlap(photos, config.max_agl_m)
    report.isolated_by_gps = overlap.isolated
    if overlap.isolated:
        report.warnings.append(f"{len(overlap.isolated)} photo(s) cannot overlap any other photo by GPS "
                               f"(even {config.max_agl_m:.0f} m above ground): {', '.join(overlap.isolated[:10])}")
    report.photos_used = [p.name for p in photos]
    state["photos"] = photos
    state["image_dir"] = Path(config.photos_dir)
    return {"names": report.photos_used, "photos": [dataclasses.asdict(p) for p in photos]}


def _correct_run(config, project, state, report) -> dict:
    if config.barrel is None:
        state["image_dir"] = Path(config.photos_dir)
        return {"corrected": False}
    from skyfix.mapping.batch import CorrectionSpec, correct_photos

    result = correct_photos([p.path for p in state["photos"]], project.corrected,
                            CorrectionSpec(barrel=config.barrel), workers=None if config.threads < 1 else
                            config.threads, progress=False)
    focal = {Path(r.source).name: r.output_camera for r in result.written}
    kept = []
    for p in state["photos"]:
        cam = focal.get(p.name)
        if cam is None:
            reason = next(r.error for r in result.skipped if Path(r.source).name == p.name)
            report.rejected.append({"photo": p.name, "reason": f"lens correction failed: {reason}"})
            continue
        kept.append(dataclasses.replace(p, path=str(project.corrected / p.name), width=cam["width"],
                                        height=cam["height"], focal_px=cam["fx_px"] or p.focal_px))
    state["photos"], state["image_dir"] = kept, project.corrected
    report.photos_used = [p.name for p in kept]
    return {"corrected": True, "photos": [dataclasses.asdict(p) for p in kept]}


def _correct_load(config, project, state, report, marker) -> None:
    if marker.get("corrected"):
        state["photos"] = [Photo(**d) for d in marker["photos"]]
        state["image_dir"] = project.corrected
        report.photos_used = [p.name for p in state["photos"]]
    else:
        state["image_dir"] = Path(config.photos_dir)


def _features_run(config, project, state, report) -> dict:
    from skyfix.mapping import sfm

    sfm.extract(project.database, state["image_dir"], state["photos"], calibration=config.calibration,
                max_image_size_px=config.max_image_size_px, max_features=config.max_features,
                threads=config.threads)
    return {"database": str(project.database)}


def _matches_run(config, project, state, report) -> dict:
    from skyfix.mapping import sfm

    report.matching = sfm.match(project.database, state["photos"], exhaustive_max_photos=config.exhaustive_max_photos,
                                neighbours=config.spatial_neighbours, seed=config.seed, threads=config.threads)
    return {"method": report.matching}


def _matches_load(config, project, state, report, marker) -> None:
    report.matching = marker.get("method", "")


def _mapping_run(config, project, state, report) -> dict:
    from skyfix.mapping import sfm

    if project.sparse.exists():
        shutil.rmtree(project.sparse)
    from skyfix.mapping.georef import survey_frame

    frame = survey_frame(state["photos"])
    priors = 0
    if frame is not None and config.gps_sigma_m:
        priors = sfm.set_pose_priors(project.database, state["photos"], frame, config.gps_sigma_m)
    models = sfm.reconstruct(project.database, state["image_dir"], project.sparse,
                             calibrated=config.calibration is not None, refine_focal=config.refine_focal,
                             pose_priors=priors >= 3, seed=config.seed, threads=config.threads)
    if not models:
        raise DataError("structure from motion reconstructed nothing: the photos share too few features "
                        "(do they overlap? are they sharp?)")
    registered = {im.name for rec in models for im in rec.images.values() if im.has_pose}
    unregistered = {p.name for p in state["photos"] if p.has_gps} - registered
    state["models"] = models
    state["pairs"] = sfm.pair_models(project.database, state["image_dir"], project.sparse / "pairs", unregistered,
                                     models, threads=config.threads) if unregistered else []
    return {"models": len(models), "pairs": [dataclasses.asdict(pair) for _, pair in state["pairs"]]}


def _mapping_load(config, project, state, report, marker) -> None:
    from skyfix.mapping import sfm

    state["models"] = sfm.load_models(project.sparse)
    pair_recs = sfm.load_models(project.sparse / "pairs")
    state["pairs"] = [(rec, sfm.PairModel(**d)) for rec, d in zip(pair_recs, marker.get("pairs", []), strict=True)]


def _summarise_models(state, report) -> None:
    models = state["models"]
    registered = sorted({im.name for rec in models for im in rec.images.values() if im.has_pose})
    report.registered = registered
    report.unregistered = sorted(set(report.photos_used) - set(registered))
    errors = [rec.compute_mean_reprojection_error() for rec in models]
    weights = [rec.compute_num_observations() for rec in models]
    report.mean_reprojection_error_px = float(np.average(errors, weights=weights)) if sum(weights) else math.nan
    report.points = int(sum(rec.num_points3D() for rec in models))


def _georef_run(config, project, state, report) -> dict:
    from skyfix.mapping.georef import georeference, survey_frame

    if project.georef.exists():
        shutil.rmtree(project.georef)
    from skyfix.mapping.gps_lag import gps_velocities

    models = state["models"]
    frame = survey_frame(state["photos"])
    velocities = gps_velocities(state["photos"], frame) if frame is not None and config.estimate_gps_lag else {}
    state["velocities"] = velocities
    results = []
    for i, rec in enumerate(models):
        if frame is None:
            from skyfix.mapping.georef import ModelGeoref

            results.append(ModelGeoref(i, rec.num_reg_images(), False, "no photo has GPS; model left unreferenced"))
        else:
            results.append(georeference(rec, state["photos"], frame, i, max_error_m=config.georef_max_error_m,
                                        velocities=velocities))
        path = project.georef / str(i)
        path.mkdir(parents=True, exist_ok=True)
        rec.write(str(path))
    state["frame"] = frame
    rejected = _attach_pairs(config, project, state, results)
    data = {"frame": None if frame is None else [frame.lat0_deg, frame.lon0_deg, frame.alt0_m],
            "models": [r.to_dict() for r in results], "two_view_rejected": rejected}
    _georef_load(config, project, state, report, data)
    return data


def _attach_pairs(config, project, state, results: list) -> list[str]:
    """Two-view models anchored on georeferenced main models; accepted ones are appended to
    ``results`` and written as further models, rejected ones only return their reason."""
    from skyfix.mapping.georef import attach_pair

    models, frame, rejected = state["models"], state.get("frame"), []
    for pair_rec, pair in state.get("pairs", []):
        host = next((i for i, rec in enumerate(models[:len(results)]) if results[i].georeferenced
                     and any(im.name == pair.partner and im.has_pose for im in rec.images.values())), None)
        if frame is None or host is None:
            rejected.append(f"{pair.photo}: partner {pair.partner} is in no georeferenced model; not placed")
            continue
        lag = results[host].gps_lag
        shift = {n: lag["lag_s"] * v for n, v in state.get("velocities", {}).items()} if lag.get("applied") else None
        found = attach_pair(pair_rec, models[host], results[host], pair, state["photos"], frame, len(results),
                            max_offset_m=config.two_view_max_offset_m,
                            max_vertical_m=config.two_view_max_vertical_m, gps_shift_enu=shift)
        if not found.georeferenced:
            rejected.append(found.reason)
            continue
        results.append(found)
        path = project.georef / str(found.model_index)
        path.mkdir(parents=True, exist_ok=True)
        pair_rec.write(str(path))
    return rejected


def _georef_load(config, project, state, report, marker) -> None:
    from skyfix.geo import LocalFrame
    from skyfix.mapping import sfm

    state["models"] = sfm.load_models(project.georef)
    state["frame"] = None if marker["frame"] is None else LocalFrame(*marker["frame"])
    _summarise_models(state, report)
    report.models = marker["models"]
    report.registered_two_view = [m["two_view"] for m in marker["models"] if m.get("two_view")]
    report.warnings.extend(marker.get("two_view_rejected", []))
    referenced = [m for m in marker["models"] if m["georeferenced"]]
    report.georeferenced = bool(referenced)
    report.gps_lag = next((m["gps_lag"] for m in referenced if m.get("gps_lag")), {})
    for m in marker["models"]:
        if not m["georeferenced"]:
            report.warnings.append(f"model {m['model']} ({m['registered']} photos) not georeferenced: {m['reason']}")
    mapped = [m for m in marker["models"] if not m.get("two_view")]
    if len(mapped) > 1:
        report.warnings.append(f"mapping produced {len(mapped)} models; georeferenced ones are merged in the outputs")
    if referenced:
        res = np.array([r for m in referenced for r in m["residuals_enu_m"].values()])
        report.georef_rms_m = float(np.sqrt((res ** 2).sum(axis=1).mean()))
        report.georef_rms_horizontal_m = float(np.sqrt((res[:, :2] ** 2).sum(axis=1).mean()))
    state["referenced"] = [state["models"][m["model"]] for m in referenced]
    state["unreferenced"] = [state["models"][m["model"]] for m in marker["models"] if not m["georeferenced"]]


def _points(models: list, max_error_px: float = 2.0, min_track: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) xyz and (N, 3) uint8 colours of well-measured points of ``models``."""
    xyz, rgb = [], []
    for rec in models:
        for p in rec.points3D.values():
            if p.error <= max_error_px and p.track.length() >= min_track:
                xyz.append(p.xyz)
                rgb.append(p.color)
    if not xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return np.array(xyz, dtype=np.float64), np.array(rgb, dtype=np.uint8)


def _dsm_run(config, project, state, report) -> dict:
    from skyfix.mapping.dsm import auto_dsm_resolution_m, build_dsm
    from skyfix.mapping.geotiff import write_dsm_tif
    from skyfix.mapping.grid import Grid, enu_to_utm, utm_epsg

    if not state["referenced"]:
        report.warnings.append("no georeferenced model: DSM and orthophoto skipped")
        state["dsm"] = None
        return {"skipped": True}
    frame = state["frame"]
    xyz, _ = _points(state["referenced"])
    if len(xyz) < 3:
        raise DataError(f"only {len(xyz)} well-measured 3-D points; a DSM needs more")
    epsg = utm_epsg(frame.lat0_deg, frame.lon0_deg)
    utm = enu_to_utm(frame, xyz, epsg)
    lo, hi = utm[:, :2].min(axis=0), utm[:, :2].max(axis=0)
    extra = {}
    if config.dense:
        dsm, extra = _dense(config, project, state, xyz, epsg)
        grid = dsm.grid
    else:
        res_m = config.dsm_resolution_m or auto_dsm_resolution_m(utm)
        grid = Grid.covering(epsg, lo[0], lo[1], hi[0], hi[1], res_m)
        dsm = build_dsm(utm, grid)
    write_dsm_tif(project.root / "dsm.tif", dsm.surface_m, grid)
    np.save(project.work / "dsm_filled.npy", dsm.filled_m)
    np.save(project.work / "dsm_surface.npy", dsm.surface_m)
    from skyfix.mapping.height_check import flying_height

    check = flying_height(state["referenced"], state["photos"], frame, dsm)
    area = extra.pop("stereo_area", None)
    data = {"grid": grid.to_dict(), "points": len(xyz), "flying_height": check.to_dict(),
            "flying_height_suspicious": check.suspicious(), "valid_share": _valid_share(dsm.observed, area), **extra}
    _dsm_load(config, project, state, report, data)
    return data


def _valid_share(observed: np.ndarray, area: np.ndarray | None = None) -> float:
    """Share of the cells inside the surveyed ``area`` (default: the convex hull of the
    measured cells) that hold a measured height (not interpolated)."""
    import cv2

    if area is not None:
        return float(observed[area].mean()) if area.any() else 0.0
    rows, cols = np.nonzero(observed)
    if len(rows) < 3:
        return 0.0
    hull = cv2.convexHull(np.stack((cols, rows), axis=1).astype(np.int32))
    area = np.zeros(observed.shape, np.uint8)
    cv2.fillConvexPoly(area, hull, 1)
    return float(observed[area > 0].mean())


def _dense(config, project, state, sparse_enu: np.ndarray, epsg: int) -> tuple:
    """Dense DSM (mapping.dense) on a grid of ``dense_cell_px`` matched pixels; saves the cloud."""
    from skyfix.mapping.dense import dense_dsm, stereo_area
    from skyfix.mapping.grid import EnuToUtm, Grid
    from skyfix.mapping.ortho import load_views

    views = load_views(state["referenced"], state["image_dir"])
    up = (float(np.percentile(sparse_enu[:, 2], 1)) - 20.0, float(np.percentile(sparse_enu[:, 2], 99)) + 20.0)
    lo, hi = sparse_enu[:, :2].min(axis=0), sparse_enu[:, :2].max(axis=0)
    to_utm = EnuToUtm(state["frame"], epsg, (lo[0], lo[1], hi[0], hi[1]), up)
    gsd_m = _median_gsd_m(state["referenced"], state["frame"], None, float(np.median(sparse_enu[:, 2])))
    res_m = config.dsm_resolution_m or gsd_m / config.dense_scale * config.dense_cell_px
    utm = to_utm(sparse_enu)
    grid = Grid.covering(epsg, *utm[:, :2].min(axis=0), *utm[:, :2].max(axis=0), res_m)
    dsm, cloud = dense_dsm(views, {v.name: v.path for v in views}, sparse_enu, to_utm, grid,
                           scale=config.dense_scale, max_points=config.max_dense_points, seed=config.seed)
    np.savez(project.work / "dense_points.npz", xyz=cloud.xyz_utm_m, rgb=cloud.rgb)
    area = stereo_area(views, grid, to_utm, float(np.median(sparse_enu[:, 2])))
    return dsm, {"stereo_area": area, "valid_area": "cells inside the footprints of two or more photos","dense_points": len(cloud.xyz_utm_m), "dense_pairs": cloud.pairs, "dense_scale": cloud.scale,
                 "enu_to_utm_max_residual_m": to_utm.max_residual_m}


def _dsm_load(config, project, state, report, marker) -> None:
    from skyfix.mapping.dsm import Dsm
    from skyfix.mapping.grid import Grid

    if marker.get("skipped"):
        state["dsm"] = None
        return
    grid = Grid(**marker["grid"])
    surface = np.load(project.work / "dsm_surface.npy")
    state["dsm"] = Dsm(grid, surface, np.load(project.work / "dsm_filled.npy"), np.isfinite(surface))
    report.crs_epsg = grid.epsg
    report.dsm_resolution_m = grid.resolution_m
    report.flying_height = marker.get("flying_height", {})
    report.dsm_valid_share = marker.get("valid_share", math.nan)
    report.dense_points = marker.get("dense_points", 0)
    report.dense_pairs = marker.get("dense_pairs", 0)
    if marker.get("flying_height_suspicious"):
        report.warnings.append(report.flying_height["line"] + ": the model's heights are probably wrong (focal "
                               "length?) unless the take-off point was that far above or below the ground surveyed")
    report.outputs["dsm"] = str(project.root / "dsm.tif")


def _median_gsd_m(models: list, frame, dsm, ground_up: float | None = None) -> float:
    """Median ground sample distance: height above the median DSM height (or ``ground_up``,
    ENU metres) / focal length."""
    if ground_up is None:  # measured cells only: filled ones are interpolations
        ground_up = float(np.nanmedian(dsm.surface_m)) - frame.alt0_m
    gsd = []
    for rec in models:
        for image in rec.images.values():
            if image.has_pose:
                cam = rec.cameras[image.camera_id]
                gsd.append((image.projection_center()[2] - ground_up) / cam.mean_focal_length())
    return float(np.median(gsd))


def _ortho_run(config, project, state, report) -> dict:
    from skyfix.mapping.geotiff import write_orthophoto_tif, write_preview_png
    from skyfix.mapping.grid import Grid, UtmToEnu, enu_to_utm
    from skyfix.mapping.ortho import load_views, orthomosaic

    dsm = state["dsm"]
    if dsm is None:
        return {"skipped": True}
    frame, models = state["frame"], state["referenced"]
    gsd_m = _median_gsd_m(models, frame, dsm)
    res_m = config.resolution_cm / 100.0 if config.resolution_cm else gsd_m
    # Ortho extent: the camera footprints bounded by the DSM box grown by a footprint's half-size.
    centres = np.array([im.projection_center() for rec in models for im in rec.images.values() if im.has_pose])
    centres_utm = enu_to_utm(frame, centres, dsm.grid.epsg)
    west, south, east, north = dsm.grid.bounds_m
    margin = 0.5 * gsd_m * max(max(c.width, c.height) for rec in models for c in rec.cameras.values())
    west, south = min(west, centres_utm[:, 0].min() - margin), min(south, centres_utm[:, 1].min() - margin)
    east, north = max(east, centres_utm[:, 0].max() + margin), max(north, centres_utm[:, 1].max() + margin)
    area = (east - west) * (north - south)
    if config.max_ortho_mpx is not None and area / res_m ** 2 > config.max_ortho_mpx * 1e6:
        res_m = math.sqrt(area / (config.max_ortho_mpx * 1e6))
        report.warnings.append(f"orthophoto pixel raised to {res_m * 100:.1f} cm (GSD {gsd_m * 100:.1f} cm) "
                               f"because max_ortho_mpx={config.max_ortho_mpx:g} was asked for")
    grid = Grid.covering(dsm.grid.epsg, west, south, east, north, res_m)
    to_enu = UtmToEnu(frame, grid.epsg, grid.bounds_m)
    views = load_views(models, state["image_dir"])
    if config.ortho_seams:
        from skyfix.mapping.mosaic import seamed_mosaic

        mosaic = seamed_mosaic(views, grid, dsm, to_enu, band_px=config.seam_band_px)
    else:
        mosaic = orthomosaic(views, grid, dsm, to_enu, blend_power=config.blend_power)
    # Crop to the covered part.
    alpha = mosaic.rgba[..., 3] > 0
    rows, cols = np.flatnonzero(alpha.any(axis=1)), np.flatnonzero(alpha.any(axis=0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    west_c, north_c = grid.centres_m(r0, c0)
    crop = Grid(grid.epsg, float(west_c) - res_m / 2, float(north_c) + res_m / 2, res_m, int(c1 - c0), int(r1 - r0))
    rgba = mosaic.rgba[r0:r1, c0:c1]
    write_orthophoto_tif(project.root / "orthophoto.tif", rgba, crop)
    write_preview_png(project.root / "orthophoto.png", rgba)
    data = {"grid": crop.to_dict(), "gsd_m": gsd_m, "covered_m2": float(alpha.sum() * res_m ** 2),
            "photos": mosaic.photos_used, "utm_to_enu_max_residual_m": to_enu.max_residual_m}
    _ortho_load(config, project, state, report, data)
    return data


def _ortho_load(config, project, state, report, marker) -> None:
    if marker.get("skipped"):
        return
    report.gsd_cm = marker["gsd_m"] * 100.0
    report.resolution_cm = marker["grid"]["resolution_m"] * 100.0
    report.covered_area_m2 = marker["covered_m2"]
    report.outputs["orthophoto"] = str(project.root / "orthophoto.tif")
    report.outputs["preview"] = str(project.root / "orthophoto.png")
    state["ortho_grid"] = marker["grid"]


def _export_run(config, project, state, report) -> dict:
    from skyfix.mapping.geotiff import write_cameras_geojson, write_ply
    from skyfix.mapping.grid import enu_to_utm

    frame = state["frame"]
    by_name = {p.name: p for p in state["photos"]}
    features, cams_utm, gps_utm = [], [], []
    residuals = {n: r for m in report.models for n, r in m["residuals_enu_m"].items()}
    dense = project.work / "dense_points.npz"
    if state["referenced"] and config.dense and dense.exists():
        with np.load(dense) as cloud:
            write_ply(project.root / "points.ply", cloud["xyz"], cloud["rgb"])
    elif state["referenced"]:
        xyz, rgb = _points(state["referenced"], max_error_px=4.0, min_track=2)
        write_ply(project.root / "points.ply", enu_to_utm(frame, xyz, report.crs_epsg) if len(xyz) else xyz, rgb)
    if state["referenced"]:
        emitted: set[str] = set()  # a photo shared by two models is listed once, from the first model
        for rec in state["referenced"]:
            for image in rec.images.values():
                if not image.has_pose or image.name in emitted:
                    continue
                emitted.add(image.name)
                lat, lon, alt = frame.to_geodetic_points(image.projection_center()[None, :])[0]
                p = by_name.get(image.name)
                features.append({"lat_deg": lat, "lon_deg": lon, "alt_m": alt, "properties": {
                    "photo": image.name, "alt_amsl_m": alt, "gps_lat_deg": p.gps_lat_deg if p else None,
                    "gps_lon_deg": p.gps_lon_deg if p else None, "gps_alt_amsl_m": p.gps_alt_amsl_m if p else None,
                    "residual_enu_m": residuals.get(image.name)}})
                if p is not None and p.has_gps:
                    cams_utm.append(image.projection_center())
                    gps_utm.append(frame.to_enu_points(np.array([[p.gps_lat_deg, p.gps_lon_deg,
                                                                  p.gps_alt_amsl_m]]))[0])
        write_cameras_geojson(project.root / "cameras.geojson", features)
        report.outputs["cameras"] = str(project.root / "cameras.geojson")
    elif state["unreferenced"]:
        xyz, rgb = _points(state["unreferenced"], max_error_px=4.0, min_track=2)
        write_ply(project.root / "points.ply", xyz, rgb)
        report.warnings.append("points.ply is in the arbitrary model frame (no georeference)")
    report.outputs["points"] = str(project.root / "points.ply")
    report.outputs["report"] = str(project.root / "report.json")
    report.outputs["report_png"] = str(project.root / "report.png")
    report.total_seconds = sum(report.stage_seconds.values())
    report.peak_memory_mib = _peak_mib()
    preview = extent = None
    if "ortho_grid" in state:
        import cv2

        g = state["ortho_grid"]
        img = cv2.imread(str(project.root / "orthophoto.png"), cv2.IMREAD_UNCHANGED)
        preview = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
        extent = (g["west_m"], g["west_m"] + g["width"] * g["resolution_m"],
                  g["north_m"] - g["height"] * g["resolution_m"], g["north_m"])
    cams = enu_to_utm(frame, np.array(cams_utm), report.crs_epsg) if cams_utm else None
    gps = enu_to_utm(frame, np.array(gps_utm), report.crs_epsg) if gps_utm else None
    report.save_png(project.root / "report.png", preview, extent, cams, gps)
    return {}


def _noop_load(config, project, state, report, marker) -> None:
    return None


_STAGE_RUN = {"photos": _photos_run, "correct": _correct_run, "features": _features_run,
              "matches": _matches_run, "mapping": _mapping_run, "georef": _georef_run, "dsm": _dsm_run,
              "ortho": _ortho_run, "export": _export_run}
_STAGE_LOAD = {"photos": _noop_load, "correct": _correct_load, "features": _noop_load,
               "matches": _matches_load, "mapping": _mapping_load, "georef": _georef_load, "dsm": _dsm_load,
               "ortho": _ortho_load, "export": _noop_load}
