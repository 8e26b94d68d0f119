"""``skyfix map PHOTOS_DIR -o OUT_DIR``: the photo-to-model pipeline on the command line."""

from __future__ import annotations

import argparse
import sys

__all__ = ["register_map"]


def _map(args: argparse.Namespace) -> int:
    import os

    os.environ.setdefault("GLOG_minloglevel", "1")  # pycolmap: warnings and errors only
    from skyfix.camera_io import load_camera
    from skyfix.mapping.lens import parse_barrel
    from skyfix.mapping.pipeline import PipelineConfig, run_pipeline

    if args.barrel is not None and args.calibration is not None:
        from skyfix.errors import InputError

        raise InputError("give at most one of --barrel 'a b c [d]' or --calibration cal.json")
    config = PipelineConfig(
        args.photos_dir, args.out_dir, barrel=parse_barrel(args.barrel) if args.barrel else None,
        calibration=load_camera(args.calibration) if args.calibration else None,
        resolution_cm=args.resolution_cm, dsm_resolution_m=args.dsm_resolution_m,
        max_image_size_px=args.max_image_size, max_features=args.max_features,
        exhaustive_max_photos=args.exhaustive_max, max_agl_m=args.max_agl, threads=args.threads,
        sfm_threads=args.sfm_threads, match_threads=args.match_threads,
        refine_focal=args.refine_focal, gps_sigma_m=tuple(args.gps_sigma) if args.gps_sigma[0] > 0 else (),
        seed=args.seed, dense=not args.sparse_dsm, dense_scale=args.dense_scale,
        ortho_seams=not args.feathered_ortho, max_ortho_mpx=args.max_ortho_mpx,
        force=tuple(args.force or ()))
    if args.split is not None:
        return _map_split(config, args)
    if args.scheduler is not None or args.split_overlap is not None or args.workers is not None:
        from skyfix.errors import InputError

        raise InputError("--split-overlap, --scheduler and --workers only apply with --split N")
    report = run_pipeline(config)
    out = sys.stdout
    out.write(f"registered {len(report.registered)}/{len(report.photos_used)} photos "
              f"({len(report.rejected)} rejected) in {len(report.models)} model(s); "
              f"reprojection error {report.mean_reprojection_error_px:.2f} px\n")
    if report.georeferenced:
        out.write(f"georeferenced to GPS: RMS {report.georef_rms_m:.2f} m, EPSG:{report.crs_epsg}, "
                  f"GSD {report.gsd_cm:.1f} cm, covered {report.covered_area_m2 / 1e4:.2f} ha\n")
    lag = report.gps_lag
    if lag:
        out.write(f"GPS time lag {lag['lag_s']:+.2f} s {'removed' if lag['applied'] else 'not significant, kept'}: "
                  f"camera-to-GPS RMS {lag['rms_without_m']:.2f} m without, {lag['rms_with_m']:.2f} m with it\n")
    if report.flying_height:
        out.write(report.flying_height["line"] + "\n")
    if report.dense_points:
        out.write(f"DSM: {100 * report.dsm_valid_share:.1f} % of the area two photos see measured by dense matching, "
                  f"{100 * report.dsm_interpolated_share:.1f} % interpolated in small enclosed holes "
                  "(dsm_interpolated.tif marks them)\n")
    for warning in report.warnings:
        out.write(f"warning: {warning}\n")
    for name, path in report.outputs.items():
        out.write(f"{name}: {path}\n")
    out.write(f"{report.total_seconds:.0f} s, peak memory {report.peak_memory_mib:.0f} MiB\n")
    return 0 if report.registered else 1


def _map_split(config, args: argparse.Namespace) -> int:
    from skyfix.mapping.scale_out import ScaleOut, run_split

    report = run_split(config, ScaleOut(args.split, overlap_m=args.split_overlap, scheduler=args.scheduler,
                                        workers=args.workers))
    out = sys.stdout
    subs = report["submodels"]
    out.write(f"registered {report['registered']}/{report['photos']} photos in {len(subs)} submodels "
              f"({report['target_photos']} photos each, {report['overlap_m']:.0f} m overlap) on "
              f"{report['scheduler']}\n")
    for sub in subs:
        if sub.get("error"):
            out.write(f"  submodel {sub['index']}: failed: {sub['error']}\n")
            continue
        a = sub.get("alignment") or {}
        out.write(f"  submodel {sub['index']}: {sub['registered']}/{sub['photos']} registered, georef RMS "
                  f"{sub['georef_rms_m']:.2f} m, {a.get('shared_photos')} photos shared with others "
                  f"({a.get('rms_before_m', float('nan')):.3f} -> {a.get('rms_after_m', float('nan')):.3f} m apart "
                  f"aligned, {len(a.get('left_out') or [])} left out, cameras moved {a.get('moved_rms_m', float('nan')):.2f} m), "
                  f"worker peak {sub['worker_peak_memory_mib']:.0f} MiB\n")
    for key, seam in report["seams"].items():
        dz, shift = seam["dsm_median_difference_m"], seam["ortho_shift_px"]
        out.write(f"  seam {key}: height step {'-' if dz is None else f'{dz:+.3f} m'}, "
                  f"image shift {'-' if shift is None else f'{shift:.2f} px'}\n")
    for name, path in report["outputs"].items():
        out.write(f"{name}: {path}\n")
    out.write(f"{report['total_seconds']:.0f} s, worker peak memory {report['worker_peak_memory_mib']:.0f} MiB, "
              f"merge peak {report['merge_peak_memory_mib']:.0f} MiB\n")
    return 0 if report["registered"] else 1


def register_map(subparsers: argparse._SubParsersAction) -> None:
    """Add ``map`` to the ``skyfix`` command line."""
    from skyfix.mapping.project import STAGES

    p = subparsers.add_parser(
        "map", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="geotagged photos -> orthophoto, DSM, point cloud (pycolmap)",
        description="Build a georeferenced orthophoto (GeoTIFF, UTM), a surface model, a point cloud and a "
                    "report from a folder of geotagged JPEG photos. Stages write into OUT_DIR, so an "
                    "interrupted run resumes where it stopped (extraction and matching are never redone). "
                    "Heights are AMSL as recorded by the photos' GPS. Outputs: orthophoto.tif/.png, dsm.tif, "
                    "points.ply, cameras.geojson, report.json/.png.")
    p.add_argument("photos_dir", metavar="PHOTOS_DIR", help="folder of JPEG photos with GPS in EXIF")
    p.add_argument("-o", "--out-dir", required=True, metavar="OUT_DIR", help="project/output folder")
    p.add_argument("--barrel", default=None, metavar="'A B C [D]'",
                   help="correct photos with this ImageMagick barrel model first")
    p.add_argument("--calibration", default=None, metavar="CAL.json",
                   help="pre-calibrated lens (skyfix lens calibrate), passed to pycolmap and held fixed")
    p.add_argument("--resolution-cm", type=float, default=None,
                   help="orthophoto pixel size in cm (default: the photos' median ground sample distance)")
    p.add_argument("--dsm-resolution-m", type=float, default=None,
                   help="DSM cell size in metres (default: 2 densely matched pixels, i.e. 4x the photos' ground "
                        "sample distance at --dense-scale 0.5; with --sparse-dsm twice the sparse point spacing)")
    p.add_argument("--dense-scale", type=float, default=0.5,
                   help="photos are densely matched at this fraction of their size")
    p.add_argument("--sparse-dsm", action="store_true",
                   help="DSM from the sparse structure-from-motion points only (fast, no trees or roofs)")
    p.add_argument("--feathered-ortho", action="store_true",
                   help="orthophoto as a feathered mean of all photos instead of one photo per pixel with seams")
    p.add_argument("--max-ortho-mpx", type=float, default=None,
                   help="coarsen the orthophoto to stay within this many megapixels (default: full resolution; "
                        "the report states any coarsening)")
    p.add_argument("--max-image-size", type=int, default=1600, help="photos are downscaled to this for features")
    p.add_argument("--max-features", type=int, default=4000, help="SIFT features per photo")
    p.add_argument("--exhaustive-max", type=int, default=40,
                   help="match exhaustively up to this many photos, by GPS neighbours beyond")
    p.add_argument("--max-agl", type=float, default=120.0,
                   help="highest possible flight height above ground (m), for the GPS overlap check")
    p.add_argument("--refine-focal", action="store_true",
                   help="let bundle adjustment move the focal length (by default it is held at the photos' "
                        "calibrated/sensor value: over a nadir grid flown at constant height focal length and "
                        "depth trade off and the whole model can end up metres too low)")
    p.add_argument("--gps-sigma", type=float, nargs=2, default=(2.0, 4.0), metavar=("H_M", "V_M"),
                   help="GPS standard deviations (horizontal, vertical, metres) of the pose priors in bundle "
                        "adjustment; 0 0 turns the priors off")
    p.add_argument("--seed", type=int, default=0, help="random seed (the same photos and seed give the same outputs)")
    p.add_argument("--threads", type=int, default=-1,
                   help="worker threads of feature extraction and dense matching (-1: all cores)")
    p.add_argument("--match-threads", type=int, default=1,
                   help="threads of feature matching; 1 (the default) gives the same matches every run, more "
                        "(-1: all cores) are faster but COLMAP's matcher threads then race and a pair now and "
                        "then loses matches")
    p.add_argument("--sfm-threads", type=int, default=1,
                   help="threads of structure from motion's registration and bundle adjustments; 1 (the default) "
                        "gives the same model every run, more (-1: all cores) are faster on large surveys but "
                        "COLMAP's threads then race (parallel RANSAC, thread-ordered sums) and runs differ")
    p.add_argument("--split", type=int, default=None, metavar="N",
                   help="split the survey by GPS into submodels of about N photos, reconstruct them as Dask tasks "
                        "and merge them (large surveys; needs the 'scale' extra)")
    p.add_argument("--split-overlap", type=float, default=None, metavar="M",
                   help="with --split: photos of neighbouring submodels within M metres are shared, to align them "
                        "(default: 1.5x the median distance from a photo to its 4th-nearest neighbour)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:8786",
                   help="with --split: a running Dask scheduler whose workers see OUT_DIR and the photos at the "
                        "same paths (default: a local cluster on this machine)")
    p.add_argument("--workers", type=int, default=None,
                   help="with --split and no --scheduler: local worker processes (default: the cores, at most "
                        "the submodels)")
    p.add_argument("--force", action="append", choices=STAGES, metavar="STAGE",
                   help=f"re-run this stage and the ones after it (repeat); one of {', '.join(STAGES)}")
    from skyfix.mapping.cli_args import flags_named

    p.set_defaults(func=flags_named(_map))
