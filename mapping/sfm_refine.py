"""What follows pycolmap's incremental mapping: joining the models it split a survey into,
and deciding whether the photos support a radial distortion term. Both adjust with the
photos' GPS pose priors when the database holds them (:func:`skyfix.mapping.sfm.set_pose_priors`),
so the model stays in the survey frame. pycolmap is imported inside the functions.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

__all__ = ["adjust", "join_models", "pipeline_options", "pose_priors", "prior_rms_m", "without_unsupported_distortion"]

log = logging.getLogger(__name__)

_RADIAL = {"SIMPLE_RADIAL": (3,), "RADIAL": (3, 4)}
_NEVER = 2**31 - 1


def pipeline_options(seed: int, sfm_threads: int = 1):
    """pycolmap incremental-pipeline options with every random seed set to ``seed`` (the
    triangulator's own is -1, i.e. unseeded, unless set) and ``sfm_threads`` threads for
    the mapper's registration, initial-pair search and bundle adjustments.

    One thread repeats exactly. With more, COLMAP 4 runs each photo's absolute-pose
    LO-RANSAC on parallel threads that share one trial counter and one best model, and
    the initial-pair search on a thread pool that shares the set of tried pairs: which
    model wins depends on thread timing (CI saw 5005 and 4963 sparse points on the same
    rendered survey). Ceres also sums a multi-threaded adjustment in thread order (COLMAP
    issue 727), so runs then differ in the last digits and keep or drop a different point."""
    from skyfix.mapping.sfm import _colmap_logging

    pycolmap = _colmap_logging()
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = int(seed)
    options.mapper.random_seed = int(seed)
    options.triangulation.random_seed = int(seed)
    options.num_threads = int(sfm_threads)
    if sfm_threads == 1:  # Ceres goes multi-threaded above this many residuals
        options.ba_min_num_residuals_for_cpu_multi_threading = _NEVER
    return options


def pose_priors(database: Path) -> list:
    """The database's pose priors (``pycolmap.PosePrior``), empty when it holds none."""
    from skyfix.mapping.sfm import _colmap_logging

    pycolmap = _colmap_logging()
    db = pycolmap.Database.open(str(database))
    try:
        return list(db.read_all_pose_priors())
    finally:
        db.close()


def prior_rms_m(rec, priors: list) -> float:
    """RMS distance (m) of ``rec``'s camera centres from their pose priors; NaN without any."""
    by_image = {p.corr_data_id.id: p.position for p in priors}
    d = [rec.images[i].projection_center() - by_image[i] for i in rec.reg_image_ids() if i in by_image]
    return float(np.sqrt(np.mean(np.sum(np.square(d), axis=1)))) if d else float("nan")


def adjust(rec, priors: list, *, refine_focal: bool, refine_extra: bool, sfm_threads: int = 1) -> None:
    """Global bundle adjustment of ``rec`` in place, on one thread unless ``sfm_threads`` is
    not 1 (one repeats exactly, see :func:`pipeline_options`); with ``priors`` (three or more of its photos)
    pycolmap's pose-prior adjuster, whose camera positions are held to them, else the plain
    one. The principal point is held."""
    from skyfix.mapping.sfm import _colmap_logging, _native_stderr_quiet

    pycolmap = _colmap_logging()
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False  # Ceres's report goes to stdout, past the logging levels
    options.refine_focal_length = bool(refine_focal)
    options.refine_extra_params = bool(refine_extra)
    options.refine_principal_point = False
    options.ceres.solver_options.num_threads = int(sfm_threads)
    reg = set(rec.reg_image_ids())
    used = [p for p in priors if p.corr_data_id.id in reg]
    with _native_stderr_quiet():
        if len(used) >= 3:
            config = pycolmap.BundleAdjustmentConfig()
            for image_id in reg:
                config.add_image(image_id)
            pycolmap.create_pose_prior_bundle_adjuster(options, pycolmap.PosePriorBundleAdjustmentOptions(),
                                                       config, used, rec).solve()
        else:
            pycolmap.bundle_adjustment(rec, options)
    _colmap_logging()  # bundle_adjustment leaves glog at INFO
    rec.update_point_3d_errors()


def without_unsupported_distortion(rec, priors: list, min_gain: float = 0.05, *, sfm_threads: int = 1):
    """``rec``, or a copy re-adjusted with the radial distortion at 0 when the refined
    term lowers neither the mean reprojection error nor the cameras' RMS distance from
    their GPS priors by ``min_gain`` (5 %).

    Over a nadir grid flown at constant height the radial term trades off against depth
    (the "doming" of parallel-axis surveys): on a rendered pinhole survey pycolmap settled
    at k = 0.0056 with no better fit than k = 0, and every height came out 1.2 % of the
    flying height too high. A real lens shows its distortion as a clear gain, in the
    reprojection error or, where GPS priors hold the cameras, in their fit to the priors:
    the Seneca photos' k = -0.022 lowers the reprojection error by 4.6 % only, but without
    it the strips dome and the cameras' vertical RMS from their GPS grows from 0.6 to 2.3 m.
    The trial is adjusted with the priors, as the mapper's own adjustments are (adjusted
    without them, the trial tilted the model up to 21 m away from the GPS heights).
    """
    from skyfix.mapping.sfm import _colmap_logging

    pycolmap = _colmap_logging()
    cams = [c for c in rec.cameras.values() if c.model.name in _RADIAL and any(
        c.params[i] != 0.0 for i in _RADIAL[c.model.name])]
    if not cams or rec.num_reg_images() < 3:
        return rec
    rec.update_point_3d_errors()
    with_k, with_k_prior = rec.compute_mean_reprojection_error(), prior_rms_m(rec, priors)
    trial = pycolmap.Reconstruction(rec)
    for cam in trial.cameras.values():
        if cam.model.name in _RADIAL:
            params = cam.params
            for i in _RADIAL[cam.model.name]:
                params[i] = 0.0
            cam.params = params
    adjust(trial, priors, refine_focal=False, refine_extra=False, sfm_threads=sfm_threads)
    without_k, without_k_prior = trial.compute_mean_reprojection_error(), prior_rms_m(trial, priors)
    keep = with_k < (1.0 - min_gain) * without_k or with_k_prior < (1.0 - min_gain) * without_k_prior
    log.info("radial distortion %s: reprojection %.4f px with it, %.4f px without; camera RMS from the GPS "
             "priors %.2f m with it, %.2f m without", "kept" if keep else "dropped (not supported by the photos)",
             with_k, without_k, with_k_prior, without_k_prior)
    return rec if keep else trial


def _alignment(rec, joined):
    """The similarity ``joined_from_rec`` from the photos both hold: by their observations of
    common points when pycolmap finds one, else (one shared photo, few common points) the
    rigid transform that puts the shared photo with the most points on its pose in
    ``joined`` (both models are metric where GPS priors held them); None without a shared photo."""
    from skyfix.mapping.sfm import _colmap_logging

    pycolmap = _colmap_logging()
    sim = pycolmap.align_reconstructions_via_reprojections(rec, joined)
    if sim is not None:
        return sim
    shared = [i for i in rec.reg_image_ids() if joined.exists_image(i) and joined.image(i).has_pose]
    if not shared:
        return None
    best = max(shared, key=lambda i: rec.image(i).num_points3D)
    pose = joined.image(best).cam_from_world().inverse() * rec.image(best).cam_from_world()
    return pycolmap.Sim3d(1.0, pose.rotation, pose.translation)


def join_models(models: list, database: Path, image_dir: Path, work_dir: Path, priors: list, *,
                refine_focal: bool, refine_extra: bool, max_reproj_error_px: float = 4.0, seed: int = 0,
                sfm_threads: int = 1) -> list:
    """``models`` (largest first) with every model that shares registered photos with the
    first joined into it; the others are returned as they were.

    pycolmap's mapper starts a new model when it cannot register a photo onto the current
    one, and keeps a few photos in both (on the Seneca photos IMG_0485 opens model 1 and
    is also in model 0). Each such model is aligned onto the first by the shared photos'
    observations of common points (pycolmap ``align_reconstructions_via_reprojections``),
    its other photos are added with their aligned poses, every point is triangulated again
    from the database's verified matches over all photos (tie points across the former
    models included), and one bundle adjustment with the GPS pose priors refines the whole;
    points then reprojecting more than ``max_reproj_error_px`` off are dropped.
    """
    from skyfix.mapping.sfm import _colmap_logging, _native_stderr_quiet

    pycolmap = _colmap_logging()
    if len(models) < 2:
        return models
    joined = pycolmap.Reconstruction(models[0])
    kept, added = [], []
    for rec in models[1:]:
        new = [im for im in rec.images.values() if im.has_pose and not (
            joined.exists_image(im.image_id) and joined.image(im.image_id).has_pose)]
        shared = len(rec.images) - len(new)
        sim = _alignment(rec, joined) if shared and new else None
        if sim is None:
            kept.append(rec)
            continue
        aligned = pycolmap.Reconstruction(rec)
        aligned.transform(sim)  # into the first model's frame
        for im in new:
            image = pycolmap.Image(name=im.name, keypoints=np.array([p.xy for p in im.points2D]),
                                   camera_id=im.camera_id, image_id=im.image_id)
            joined.add_image_with_trivial_frame(image, aligned.image(im.image_id).cam_from_world())
        added += [im.name for im in new]
    if not added:
        return models
    work_dir.mkdir(parents=True, exist_ok=True)
    options = pipeline_options(seed, sfm_threads)
    options.triangulation.ignore_two_view_tracks = False
    for _ in range(2):  # again after the adjustment: tracks split by the first alignment's error merge
        with _native_stderr_quiet():
            joined = pycolmap.triangulate_points(joined, database, image_dir, work_dir, clear_points=True,
                                                 options=options, refine_intrinsics=False)
        adjust(joined, priors, refine_focal=refine_focal, refine_extra=refine_extra, sfm_threads=sfm_threads)
    dropped = pycolmap.ObservationManager(joined).filter_all_points3D(max_reproj_error_px, 1.5)
    joined.update_point_3d_errors()
    log.info("joined %d photo(s) of %d model(s) into model 0 (%s): %d points, reprojection %.3f px, "
             "%d observations past %.0f px dropped", len(added), len(models) - 1 - len(kept), ", ".join(sorted(added)),
             joined.num_points3D(), joined.compute_mean_reprojection_error(), dropped, max_reproj_error_px)
    return [joined, *kept]
