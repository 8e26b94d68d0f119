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
import logging
import math
import os
import resource
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skyfix import validate
from skyfix.camera import Camera
from skyfix.distortion import Barrel
from skyfix.errors import ConfigurationError, DataError, InputError, SkyfixError
from skyfix.mapping.photos import Photo, camera_groups, check_gps_overlap, load_photos
from skyfix.mapping.project import STAGES, Project, stage_options
from skyfix.mapping.report import Report
from skyfix.mapping.surface_stages import dsm_load, dsm_run, ortho_load, ortho_run, points

__all__ = ["STAGES", "PipelineConfig", "run_pipeline", "stage_options"]

log = logging.getLogger(__name__)



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
    two_view_max_vertical_m: float = 12.0  # ... and vertically within 3x the host model's vertical GPS RMS, at most this
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
    dsm_fill_max_m2: float = 4.0          # dense DSM: enclosed holes up to this area interpolated, in dsm_interpolated.tif
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
            if v is not None:
                validate.positive_scalar(name, v)


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
    project = Project(out)
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
        xyz, rgb = points(state["referenced"], max_error_px=4.0, min_track=2)
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
        xyz, rgb = points(state["unreferenced"], max_error_px=4.0, min_track=2)
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
              "matches": _matches_run, "mapping": _mapping_run, "georef": _georef_run, "dsm": dsm_run,
              "ortho": ortho_run, "export": _export_run}
_STAGE_LOAD = {"photos": _noop_load, "correct": _correct_load, "features": _noop_load,
               "matches": _matches_load, "mapping": _mapping_load, "georef": _georef_load, "dsm": dsm_load,
               "ortho": ortho_load, "export": _noop_load}
