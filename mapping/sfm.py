"""Structure from motion with pycolmap: feature extraction, matching, incremental mapping.

One camera model per camera group (same make, model, size, focal length): a
``SIMPLE_RADIAL`` model seeded with the EXIF focal length, or a pre-calibrated lens
(Brown-Conrady -> ``FULL_OPENCV``, fisheye -> ``OPENCV_FISHEYE``, pinhole -> ``PINHOLE``)
passed through to pycolmap with its distortion held fixed. pycolmap is imported inside
the functions.
"""

from __future__ import annotations

import copy
import logging
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skyfix.camera import Camera
from skyfix.distortion import BrownConrady, Fisheye
from skyfix.errors import ConfigurationError
from skyfix.geo import LocalFrame
from skyfix.mapping import sfm_refine
from skyfix.mapping.photos import Photo, camera_groups

__all__ = ["ColmapCamera", "PairModel", "colmap_camera", "extract", "load_models", "match", "pair_models",
           "reconstruct", "set_pose_priors"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ColmapCamera:
    """A pycolmap camera model name with its parameter string; ``fixed`` when calibrated."""

    model: str
    params: tuple[float, ...]
    fixed: bool

    @property
    def params_text(self) -> str:
        return ",".join(f"{v:.10g}" for v in self.params)


def colmap_camera(photo: Photo, calibration: Camera | None = None) -> ColmapCamera:
    """The pycolmap camera for ``photo``: EXIF focal (refined by mapping) or ``calibration``.

    A calibration for another resolution of the same aspect ratio is rescaled.
    """
    if calibration is None:
        return ColmapCamera("SIMPLE_RADIAL", (photo.focal_px, photo.width / 2.0, photo.height / 2.0, 0.0), False)
    cam = calibration
    if (cam.width, cam.height) != (photo.width, photo.height):
        factor = photo.width / cam.width
        if abs(cam.height * factor - photo.height) > 0.5:
            raise ConfigurationError(f"{photo.name} is {photo.width}x{photo.height} but the calibration is "
                                     f"{cam.width}x{cam.height} (different aspect ratio)")
        cam = cam.scaled(factor)
    # pycolmap's pixel centres are at +0.5 (OpenCV's at 0).
    base = (cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5)
    dist = cam.distortion
    if dist is None:
        return ColmapCamera("PINHOLE", base, True)
    if isinstance(dist, BrownConrady):
        return ColmapCamera("FULL_OPENCV", (*base, dist.k1, dist.k2, dist.p1, dist.p2, dist.k3, 0.0, 0.0, 0.0),
                            True)
    if isinstance(dist, Fisheye):
        return ColmapCamera("OPENCV_FISHEYE", (*base, dist.k1, dist.k2, dist.k3, dist.k4), True)
    raise ConfigurationError(f"lens model {type(dist).__name__} has no pycolmap equivalent; correct the photos "
                             "first (the pipeline's --barrel option)")


def _colmap_logging():
    """pycolmap, its native log (glog) at the level skyfix's CLI gave the ``pycolmap``
    logger (ERROR unless -v): set here because glog reads its environment only when the
    library loads, which may be before the CLI chose."""
    import pycolmap

    level = logging.getLogger("pycolmap").getEffectiveLevel()
    pycolmap.logging.minloglevel = 0 if level <= logging.INFO else (1 if level <= logging.WARNING else 2)
    return pycolmap


@contextmanager
def _native_stderr_quiet():
    """fd 2 to /dev/null while the body runs, unless -v: ``pycolmap.bundle_adjustment``
    resets glog to INFO itself and prints its heading whatever the level set."""
    import os

    if logging.getLogger("pycolmap").getEffectiveLevel() <= logging.INFO:
        yield
        return
    saved = os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


@contextmanager
def _database_progress(database: Path, table: str, desc: str, total: int | None, unit: str):
    """A progress bar (skyfix.progress) counting the rows of ``table`` in the pycolmap
    database while the body runs: pycolmap's extraction and matching are single native
    calls without a callback, but they write each image's features / each pair as it is done."""
    import sqlite3
    import threading

    from skyfix import progress

    if not progress.enabled():
        yield
        return
    done = threading.Event()

    def poll(bar) -> None:
        con = None
        finished = False
        while not finished:
            finished = done.wait(0.5)  # one last count after the work is done
            try:
                con = con or sqlite3.connect(f"file:{database}?mode=ro", uri=True, timeout=0.2)
                count = con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]  # noqa: S608 - fixed names
            except sqlite3.Error:
                continue  # the database is being created or locked: try again
            bar.update(count - bar.n)
        if con is not None:
            con.close()

    with progress.bar(desc=desc, total=total, unit=unit) as bar:
        thread = threading.Thread(target=poll, args=(bar,), daemon=True, name="sfm-progress")
        thread.start()
        try:
            yield
        finally:
            done.set()
            thread.join()


def extract(database: Path, image_dir: Path, photos: list[Photo], *, calibration: Camera | None = None,
            max_image_size_px: int = 1600, max_features: int = 4000, threads: int = -1) -> None:
    """SIFT features of ``photos`` into ``database``; images already there are skipped by pycolmap.

    The images are registered in the database first, one by one in name order, so their
    ids do not depend on which extraction thread finishes first (the mapper's choices
    follow the ids: without this two runs on the same photos differ).
    """
    pycolmap = _colmap_logging()

    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size = int(max_image_size_px)
    options.sift.max_num_features = int(max_features)
    options.num_threads = int(threads)
    for key, group in camera_groups(photos).items():
        cam = colmap_camera(group[0], calibration)
        reader = pycolmap.ImageReaderOptions(camera_model=cam.model, camera_params=cam.params_text)
        log.info("extracting features of %d photo(s) from camera %s %s (%s)", len(group), key[0], key[1], cam.model)
        names = sorted(p.name for p in group)
        pycolmap.Database.open(str(database)).close()  # import_images needs the file to exist
        pycolmap.import_images(database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, image_names=names,
                               options=reader)
        with _database_progress(database, "keypoints", "map: features", len(photos), "photo"):
            pycolmap.extract_features(database, image_dir, image_names=names,
                                      camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                      extraction_options=options, device=pycolmap.Device.cpu)


def lens_key(photo: Photo) -> str:
    """A photo's camera group (:attr:`Photo.camera_key`) as one string (a JSON and option value)."""
    return "|".join(str(v) for v in photo.camera_key)


def model_lenses(model, photos: list[Photo]) -> tuple[tuple[str, str, tuple[float, ...]], ...]:
    """The lens ``model`` (a pycolmap.Reconstruction) estimated for each camera group of
    ``photos`` it registered: ``(lens_key, COLMAP model name, params)``, to hold another model of
    the same survey to it (:func:`set_lenses`)."""
    registered = {im.name: im.camera_id for im in model.images.values() if im.has_pose}
    found = {}
    for group in camera_groups(photos).values():
        named = next((p.name for p in group if p.name in registered), None)
        if named is not None:
            cam = model.cameras[registered[named]]
            found[lens_key(group[0])] = (cam.model.name, tuple(float(v) for v in cam.params))
    return tuple((k, m, p) for k, (m, p) in sorted(found.items()))


def set_lenses(database: Path, photos: list[Photo], lenses: tuple) -> int:
    """Write ``lenses`` (from :func:`model_lenses`) into the database's cameras of ``photos``'
    camera groups, for mapping with the lens held fixed; returns the cameras changed. A group
    the lenses do not name keeps its own (refined) camera."""
    pycolmap = _colmap_logging()

    by_key = {k: (m, p) for k, m, p in lenses}
    db = pycolmap.Database.open(str(database))
    changed = 0
    try:
        ids = {im.name: im.camera_id for im in db.read_all_images()}
        for group in camera_groups(photos).values():
            lens = by_key.get(lens_key(group[0]))
            cam_ids = {ids[p.name] for p in group if p.name in ids}
            for cam_id in cam_ids if lens is not None else ():
                cam = db.read_camera(cam_id)
                if cam.model.name != lens[0] or len(cam.params) != len(lens[1]):
                    raise ConfigurationError(f"the shared lens is a {lens[0]} camera, the database's camera "
                                             f"{cam_id} a {cam.model.name}")
                cam.params = np.asarray(lens[1], dtype=float)
                cam.has_prior_focal_length = True
                db.update_camera(cam)
                changed += 1
    finally:
        db.close()
    return changed


def match(database: Path, photos: list[Photo], *, exhaustive_max_photos: int = 40, neighbours: int = 12,
          seed: int = 0, threads: int = 1) -> str:
    """Match features; returns the method used ('exhaustive' or 'spatial').

    Small sets (or any set with photos lacking GPS) are matched exhaustively; larger ones
    pair each photo with its ``neighbours`` nearest GPS positions (pycolmap spatial matching
    on the EXIF positions the extractor stored as pose priors). ``threads`` = 1 (one
    matcher thread beside one verifier thread) gives the same matches every run; with more,
    COLMAP's matcher threads build and search their faiss indices at once and now and then
    a pair loses matches (mapping/README, Repeatable).
    """
    pycolmap = _colmap_logging()

    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = int(threads)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = int(seed)  # each pair's RANSAC seeded: the same matches every run
    if len(photos) <= exhaustive_max_photos or not all(p.has_gps for p in photos):
        log.info("exhaustive matching of %d photos (%d pairs)", len(photos), len(photos) * (len(photos) - 1) // 2)
        with _database_progress(database, "two_view_geometries", "map: matching", len(photos) * (len(photos) - 1) // 2,
                                "pair"):
            pycolmap.match_exhaustive(database, matching_options=options, verification_options=verification,
                                      device=pycolmap.Device.cpu)
        return "exhaustive"
    pairing = pycolmap.SpatialPairingOptions()
    pairing.max_num_neighbors = int(neighbours)
    pairing.max_distance = 1e6  # neighbours by count, not by distance
    pairing.ignore_z = True
    log.info("spatial matching of %d photos with their %d nearest GPS neighbours", len(photos), neighbours)
    with _database_progress(database, "two_view_geometries", "map: matching", None, "pair"):
        pycolmap.match_spatial(database, matching_options=options, pairing_options=pairing,
                               verification_options=verification, device=pycolmap.Device.cpu)
    return "spatial"


def set_pose_priors(database: Path, photos: list[Photo], frame: LocalFrame, sigma_m: tuple[float, float]) -> int:
    """Replace the database's pose priors (pycolmap stores EXIF GPS as WGS84 without a
    covariance) by the photos' GPS in ``frame`` (ENU metres, CARTESIAN) with a diagonal
    covariance of (horizontal, vertical) standard deviations ``sigma_m``; returns how many."""
    pycolmap = _colmap_logging()

    by_name = {p.name: p for p in photos if p.has_gps}
    cov = np.diag([sigma_m[0] ** 2, sigma_m[0] ** 2, sigma_m[1] ** 2])
    db = pycolmap.Database.open(str(database))
    try:
        existing = {prior.corr_data_id.id: prior for prior in db.read_all_pose_priors()}
        written = 0
        for image in db.read_all_images():
            photo = by_name.get(image.name)
            if photo is None:
                continue
            prior = existing.get(image.data_id.id) or pycolmap.PosePrior()
            prior.corr_data_id = image.data_id
            prior.position = frame.to_enu_points(np.array([[photo.gps_lat_deg, photo.gps_lon_deg,
                                                            photo.gps_alt_amsl_m]]))[0]
            prior.position_covariance = cov
            prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
            if image.data_id.id in existing:
                db.update_pose_prior(prior)
            else:
                db.write_pose_prior(prior)
            written += 1
    finally:
        db.close()
    return written


def reconstruct(database: Path, image_dir: Path, out_dir: Path, *, calibrated: bool = False,
                refine_focal: bool = True, pose_priors: bool = False, seed: int = 0,
                sfm_threads: int = 1) -> list:
    """Incremental mapping; every model (largest first) as a ``pycolmap.Reconstruction``.

    Registration thresholds are lowered from COLMAP's defaults (30 -> 15 absolute-pose
    inliers, 100 -> 50 initial-pair inliers) and two-view tracks are triangulated, because
    nadir survey photos at 1-2 Mpx over fields share few features across flight lines
    (on the Seneca photos this joins two partial models into one); every registration
    still passes RANSAC and bundle adjustment with the 4 px reprojection filter. Models
    that share photos with the largest are then joined into it (one triangulation over
    all their photos and one adjustment with the GPS priors,
    :func:`skyfix.mapping.sfm_refine.join_models`), and a radial distortion term the
    photos do not support is dropped (:func:`~skyfix.mapping.sfm_refine.without_unsupported_distortion`).
    Models are written under ``out_dir/<i>``.

    ``refine_focal=False`` holds the focal length at its prior (a nadir grid at constant
    height cannot tell focal length from depth: both scale the image of the ground alike);
    radial distortion is still refined. ``pose_priors``: the database's pose priors (see
    :func:`set_pose_priors`) enter every global bundle adjustment as position priors, so
    the model lies in their frame and cannot drift away from GPS. ``seed`` fixes
    pycolmap's random sampling (RANSAC, initial pair, triangulation) and ``sfm_threads`` = 1
    keeps registration and bundle adjustment on one thread, so a run repeats exactly
    (:func:`~skyfix.mapping.sfm_refine.pipeline_options`).
    """
    pycolmap = _colmap_logging()

    out_dir.mkdir(parents=True, exist_ok=True)
    pycolmap.set_random_seed(int(seed))
    options = sfm_refine.pipeline_options(seed, sfm_threads)
    options.use_prior_position = bool(pose_priors)
    options.use_robust_loss_on_prior_position = True
    options.min_model_size = 3
    options.mapper.abs_pose_min_num_inliers = 15
    options.mapper.init_min_num_inliers = 50
    options.triangulation.ignore_two_view_tracks = False
    if calibrated or not refine_focal:
        options.ba_refine_focal_length = False
        options.mapper.abs_pose_refine_focal_length = False
    if calibrated:
        options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_extra_params = False
    models = list(pycolmap.incremental_mapping(database, image_dir, out_dir, options=options).values())
    models += _leftover_models(database, image_dir, out_dir / "leftover", options, models)
    ordered = sorted(models, key=lambda r: r.num_reg_images(), reverse=True)
    priors = sfm_refine.pose_priors(database) if pose_priors else []
    refine_focal, refine_extra = options.ba_refine_focal_length, options.ba_refine_extra_params
    ordered = sfm_refine.join_models(ordered, database, image_dir, out_dir / "join", priors,
                                     refine_focal=refine_focal, refine_extra=refine_extra, seed=seed,
                                     sfm_threads=sfm_threads)
    if not calibrated:
        ordered = [sfm_refine.without_unsupported_distortion(rec, priors, sfm_threads=sfm_threads) for rec in ordered]
    shutil.rmtree(out_dir / "join", ignore_errors=True)
    shutil.rmtree(out_dir / "leftover", ignore_errors=True)
    for path in out_dir.iterdir():  # pycolmap's own numbering; the joined, ordered models replace it
        if path.is_dir() and path.name.isdigit():
            shutil.rmtree(path)
    for i, rec in enumerate(ordered):
        path = out_dir / str(i)
        path.mkdir(exist_ok=True)
        rec.write(str(path))
    return ordered


def _leftover_models(database: Path, image_dir: Path, work_dir: Path, options, models: list,
                     max_passes: int = 3) -> list:
    """Further models over the photos ``models`` left out, each pass mapping only those
    photos and, for each, the registered photo it shares the most verified matches with
    (so that :func:`~skyfix.mapping.sfm_refine.join_models` can join the result). A model
    is kept only where it places two or more of those photos: one photo beside registered
    ones is left to its two-view model (:func:`pair_models`, checked against GPS on its
    own). On the Seneca survey the pass put IMG_0460 into the main model 4.8 m above its
    neighbour and tilted 8 degrees, its dense pair with IMG_0461 failed and the DSM
    measured 91.6 % of the stereo area instead of 95.6 %.

    COLMAP's mapper stops looking for another model once all but one photo have been
    registered in some model, counting the photos of a model it then discards as too
    small: on the six-photo Seneca line one mapper thread built 0477-0479, tried 0474+0475
    (no third photo, discarded) and stopped with 0474-0476 unplaced."""
    pycolmap = _colmap_logging()

    db = pycolmap.Database.open(str(database))
    try:
        names = {im.name for im in db.read_all_images()}
    finally:
        db.close()
    found: list = []
    for attempt in range(max_passes):
        registered = {im.name for rec in models + found for im in rec.images.values() if im.has_pose}
        leftover = names - registered
        if len(leftover) < max(2, options.min_model_size - 1):
            break
        partners = {old for old, _ in _best_partners(database, leftover, registered, 1).values()}
        pass_options = copy.deepcopy(options)
        pass_options.image_names = sorted(leftover | partners)
        out = work_dir / str(attempt)
        out.mkdir(parents=True, exist_ok=True)
        new = [rec for rec in pycolmap.incremental_mapping(database, image_dir, out, options=pass_options).values()
               if sum(im.has_pose and im.name in leftover for im in rec.images.values()) >= 2]
        if not new:
            break
        log.info("mapping pass %d over %d photo(s) left out: %d more model(s)", attempt + 2,
                 len(leftover), len(new))
        found += new
    return found


@dataclass(frozen=True)
class PairModel:
    """A two-photo model placing ``photo`` (left out of the main models) next to ``partner``."""

    photo: str
    partner: str
    inliers: int


def _best_partners(database: Path, unregistered: set[str], registered: set[str],
                   min_inliers: int) -> dict[str, tuple[str, int]]:
    """For each unregistered photo, the registered photo it shares the most verified inliers with."""
    pycolmap = _colmap_logging()

    db = pycolmap.Database.open(str(database))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    best: dict[str, tuple[str, int]] = {}
    for pair_id, geometry in zip(pair_ids, geometries, strict=True):
        a, b = (names.get(i) for i in pycolmap.pair_id_to_image_pair(pair_id))
        count = len(geometry.inlier_matches)
        for new, old in ((a, b), (b, a)):
            if new in unregistered and old in registered and count >= min_inliers \
                    and count > best.get(new, ("", 0))[1]:
                best[new] = (old, count)
    return best


def pair_models(database: Path, image_dir: Path, out_dir: Path, unregistered: set[str], main_models: list, *,
                min_inliers: int = 30, seed: int = 0,
                sfm_threads: int = 1) -> list[tuple[object, PairModel]]:
    """Two-photo models for photos incremental mapping could not place.

    A photo that overlaps only one registered photo has no 3-D points to be located
    against (no third photo sees the overlap), so PnP cannot register it. Its verified
    two-view geometry with that photo (at least ``min_inliers`` inliers) still fixes the
    relative pose: mapping restricted to the pair, started from it, gives a two-photo
    model (relative pose up to scale), written under ``out_dir/<i>``. Two views of flat
    ground barely constrain the focal length, so the pair runs with the lens as the
    model holding the partner refined it, held fixed (its ground depth then scales the
    pair consistently). The caller anchors it on the partner's pose in the main model and
    checks it against GPS (:func:`skyfix.mapping.georef.attach_pair`).
    """
    pycolmap = _colmap_logging()

    registered = {im.name for rec in main_models for im in rec.images.values() if im.has_pose}
    partners = _best_partners(database, unregistered, registered, min_inliers)
    if not partners:
        return []
    out_dir.mkdir(parents=True, exist_ok=True)
    pair_db = out_dir / "pairs.db"
    shutil.copyfile(database, pair_db)
    db = pycolmap.Database.open(str(pair_db))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
    finally:
        db.close()
    found = []
    for photo, (partner, count) in sorted(partners.items()):
        host = next(rec for rec in main_models if any(im.name == partner and im.has_pose
                                                      for im in rec.images.values()))
        db = pycolmap.Database.open(str(pair_db))
        try:
            for camera in host.cameras.values():  # the database's camera ids are the models' camera ids
                db.update_camera(camera)
        finally:
            db.close()
        options = sfm_refine.pipeline_options(seed, sfm_threads)
        options.image_names = [photo, partner]
        options.init_image_id1, options.init_image_id2 = ids[photo], ids[partner]
        options.min_model_size = 2
        options.multiple_models = False
        options.mapper.init_min_num_inliers = int(min_inliers)
        options.triangulation.ignore_two_view_tracks = False
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = False
        work = out_dir / f"run_{len(found)}"
        work.mkdir(exist_ok=True)
        models = pycolmap.incremental_mapping(pair_db, image_dir, work, options=options)
        rec = next((r for r in models.values() if r.num_reg_images() == 2), None)
        shutil.rmtree(work)
        if rec is None:
            log.info("%s: no two-view model with %s", photo, partner)
            continue
        path = out_dir / str(len(found))
        path.mkdir(exist_ok=True)
        rec.write(str(path))
        found.append((rec, PairModel(photo, partner, count)))
        log.info("%s: two-view model with %s (%d inliers)", photo, partner, count)
    pair_db.unlink()
    return found


def load_models(out_dir: Path) -> list:
    """Models written by :func:`reconstruct` (``out_dir/0``, ``out_dir/1`` ...), in order."""
    pycolmap = _colmap_logging()

    models = []
    i = 0
    while (out_dir / str(i) / "images.bin").exists() or (out_dir / str(i) / "images.txt").exists():
        models.append(pycolmap.Reconstruction(str(out_dir / str(i))))
        i += 1
    return models
