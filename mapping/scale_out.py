"""Photo-to-model past one machine: split the survey into submodels, run them on Dask, merge.

``run_split(config, ScaleOut(...))`` splits the photos by GPS (:mod:`skyfix.mapping.submodels`), runs
each submodel's pipeline (:mod:`skyfix.mapping.pipeline`) in ``OUT/submodels/NNN/`` as a chain of Dask
tasks, one per stage group (features, matches, mapping + georeference, dense surface, orthophoto,
export), then aligns the submodels through their shared photos (:mod:`skyfix.mapping.align`) and
merges them (:mod:`skyfix.mapping.merge`) into ``OUT``. The default cluster is a ``LocalCluster``
sized to the machine; ``scheduler="tcp://HOST:8786"`` sends the same tasks to a running Dask cluster,
whose workers must see ``OUT`` and the photos at the same paths (a shared file system: each submodel's
``photos/`` holds links to the original files). A task's work survives in its folder (the pipeline's
stage markers), so a worker that dies is replaced and its task re-run by Dask from the last finished
stage, and a run stopped by a crash or Ctrl-C resumes: finished submodels are not redone.

Every submodel is mapped with one lens: the largest submodel's mapping runs first (its tasks have
priority) and estimates the radial distortion as a single model would; the others hold that lens fixed
(``PipelineConfig.shared_lens``) while their features and matches run beside it. Each estimating its own
lens, the three submodels of the Seneca survey found k = -0.0211, -0.0233 and -0.0158 (one model:
-0.0207) and their overlaps disagreed by up to 1.0 m in height and 9 px in the orthophoto.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skyfix import validate
from skyfix.errors import ConfigurationError, DataError, InputError, SkyfixError
from skyfix.mapping.pipeline import PipelineConfig, run_pipeline
from skyfix.mapping.report import peak_memory_mib

__all__ = ["ScaleOut", "run_split", "STAGE_GROUPS"]

log = logging.getLogger(__name__)

#: Dask tasks per submodel: each runs the pipeline up to and including this stage
STAGE_GROUPS = ("features", "matches", "georef", "dsm", "ortho", "export")


@dataclass(frozen=True)
class ScaleOut:
    """How to split and where to run. ``target_photos``: photos per submodel (core); ``overlap_m``:
    photos of neighbouring parts within this GPS distance are shared (None: 1.5 times the median distance
    from a photo to its 4th-nearest neighbour: on a grid survey, the next flight line and a photo or two
    along the line); ``scheduler``: a Dask scheduler address (None: a
    LocalCluster of ``workers`` processes, default the cores, at most the submodels); ``retries``: Dask
    re-runs of a task that raised."""

    target_photos: int
    overlap_m: float | None = None
    scheduler: str | None = None
    workers: int | None = None
    retries: int = 1
    dsm_band_m: float = 3.0
    ortho_band_m: float = 0.5

    def __post_init__(self) -> None:
        if self.target_photos < 3:
            raise InputError(f"--split must be at least 3 photos per submodel, got {self.target_photos}")
        if self.overlap_m is not None:
            validate.nonnegative_scalar("--split-overlap", self.overlap_m)
        if self.workers is not None and self.workers < 1:
            raise InputError(f"--workers must be at least 1, got {self.workers}")
        if self.scheduler is not None and "://" not in self.scheduler:
            raise InputError(f"--scheduler must be an address like tcp://HOST:8786, got {self.scheduler!r}")


def _stage_task(config: PipelineConfig, group: str, *previous) -> dict:
    """Run one submodel's pipeline up to ``group`` (on a Dask worker). Returns what the merge needs to
    know of it; a submodel that failed (nothing reconstructs) returns its error instead of raising, so
    the others still merge. ``previous``: the results of the tasks this one follows (the submodel's
    previous stage group, and for mapping the lens task), which carry the shared lens once known."""
    done = Path(config.out_dir) / "work" / "submodel_done.json"
    previous = tuple(p for p in previous if isinstance(p, dict))
    if any(p.get("error") and "lens" not in p for p in previous):
        return next(p for p in previous if p.get("error") and "lens" not in p)
    for p in previous:
        lens = p.get("lens", p.get("shared_lens"))
        if config.shared_lens is None and lens is not None:
            config = dataclasses.replace(config, shared_lens=_as_tuples(lens))
    cached = finished_result(config)
    if cached is not None:
        return cached
    _reset_peak_memory()
    try:
        report = run_pipeline(dataclasses.replace(config, stop_after=group))
    except SkyfixError as exc:
        return {"error": f"{type(exc).__name__}: {exc}", "group": group}
    peak = max([_task_peak_memory_mib()] + [p.get("worker_peak_memory_mib", 0.0) for p in previous
                                            if isinstance(p, dict)])
    result = {"group": group, "pid": os.getpid(), "worker_peak_memory_mib": peak,
              "registered": len(report.registered), "photos": len(report.photos_used),
              "georef_rms_m": report.georef_rms_m, "stage_seconds": report.stage_seconds,
              "crs_epsg": report.crs_epsg, "resolution_cm": report.resolution_cm,
              "dsm_resolution_m": report.dsm_resolution_m, "options": _all_options(config),
              "shared_lens": config.shared_lens}
    if group == STAGE_GROUPS[-1]:
        tmp = done.with_suffix(".part")
        tmp.write_text(json.dumps(result, indent=1, default=float))
        os.replace(tmp, done)
    return result


def _lens_task(config: PipelineConfig, previous: dict) -> dict:
    """The lens the lens submodel's mapping estimated, per camera group (on a Dask worker); an empty lens
    (each submodel then estimates its own) when that submodel failed."""
    from skyfix.mapping import sfm
    from skyfix.mapping.photos import load_photos
    from skyfix.mapping.project import Project

    name = Path(config.out_dir).name
    if previous.get("error"):
        log.warning("submodel %s failed (%s): every submodel estimates its own lens", name, previous["error"])
        return {"lens": (), "from": name, "error": previous["error"]}
    project = Project(Path(config.out_dir))
    models = sfm.load_models(project.sparse)
    photos, _ = load_photos(config.photos_dir)
    lens = sfm.model_lenses(models[0], photos) if models else ()
    return {"lens": lens, "from": name}


def _as_tuples(value):
    """A lens back from JSON or Dask: lists as tuples (a frozen config's option)."""
    return tuple(_as_tuples(v) for v in value) if isinstance(value, (list, tuple)) else value


def _all_options(config: PipelineConfig) -> dict:
    from skyfix.mapping.project import STAGES, stage_options

    return {stage: stage_options(config, stage) for stage in STAGES}


def finished_result(config: PipelineConfig) -> dict | None:
    """A submodel's result from an earlier run (``work/submodel_done.json``), when it was made with the
    options ``config`` has now; None otherwise (then its stages resume or re-run as their markers say)."""
    done = Path(config.out_dir) / "work" / "submodel_done.json"
    if not done.exists():
        return None
    result = json.loads(done.read_text())
    saved, now = result.get("options") or {}, json.loads(json.dumps(_all_options(config)))
    if config.shared_lens is None:  # this task runs before the lens is known: compare the rest
        for options in (saved, now):
            options.get("mapping", {}).pop("shared_lens", None)
    if saved != now:
        log.info("submodel %s: options changed since it finished: its stages are checked again",
                 Path(config.out_dir).name)
        return None
    return result


def _reset_peak_memory() -> None:
    """Start this worker process's peak-memory count again (Linux: VmHWM), so each task reports its own."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _task_peak_memory_mib() -> float:
    """Peak resident memory (MiB) since :func:`_reset_peak_memory`; elsewhere the process's lifetime peak."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return peak_memory_mib()


def _auto_overlap_m(en: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    k = min(5, len(en))
    if k < 2:
        return 0.0
    d, _ = cKDTree(en).query(en, k=k)
    return float(1.5 * np.median(d[:, -1]))


def _link_photos(folder: Path, paths: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    wanted = {Path(p).name for p in paths}
    for old in folder.iterdir():
        if old.name not in wanted:
            old.unlink()
    for p in paths:
        dst = folder / Path(p).name
        if not dst.exists():
            try:
                os.symlink(os.path.abspath(p), dst)
            except OSError:  # a file system without links: copy
                import shutil

                shutil.copy2(p, dst)


def _client(scale: ScaleOut, n_submodels: int):
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise ConfigurationError("--split runs on Dask, which is not installed: pip install 'skyfix[scale]'") from exc

    if scale.scheduler:
        try:
            return Client(scale.scheduler, timeout="20s"), None
        except OSError as exc:
            raise InputError(f"--scheduler {scale.scheduler}: no Dask scheduler answers there ({exc})") from exc
    cores = os.cpu_count() or 1
    workers = scale.workers or max(1, min(cores, n_submodels))
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=logging.ERROR)
    return Client(cluster), cluster


def run_split(config: PipelineConfig, scale: ScaleOut) -> dict:
    """Split, run on Dask, align and merge (see the module docs); returns the survey report, also written as
    ``OUT/report.json`` (per-submodel figures, alignment residuals, seams, worker memory)."""
    from skyfix.mapping.georef import survey_frame
    from skyfix.mapping.photos import load_photos
    from skyfix.mapping.submodels import load_split, save_split, split_photos

    start = time.perf_counter()
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    photos, rejected = load_photos(config.photos_dir)
    if not photos:
        raise DataError(f"{config.photos_dir}: no usable photo ({len(rejected)} rejected)")
    no_gps = [p.name for p in photos if not p.has_gps]
    if no_gps:
        raise InputError(f"{config.photos_dir}: --split places photos by GPS, and {len(no_gps)} have none "
                         f"(e.g. {', '.join(no_gps[:3])})")
    frame = survey_frame(photos)
    en = frame.to_enu_points(np.array([(p.gps_lat_deg, p.gps_lon_deg, p.gps_alt_amsl_m) for p in photos]))[:, :2]
    overlap_m = scale.overlap_m if scale.overlap_m is not None else _auto_overlap_m(en)
    subs = split_photos([p.name for p in photos], en, scale.target_photos, overlap_m)
    saved = load_split(out / "split.json")
    if saved is not None and [s.to_dict() for s in saved[0]] != [s.to_dict() for s in subs]:
        raise InputError(f"{out}: holds a split made from other photos or options (split.json); "
                         "use a new output folder")
    save_split(out / "split.json", subs, scale.target_photos, overlap_m)
    by_name = {p.name: p for p in photos}
    configs = []
    # the largest submodel estimates the lens every other one holds (none with a pre-calibrated lens)
    lens_index = None if config.calibration is not None else max(range(len(subs)), key=lambda i: len(subs[i].photos))
    for i, sub in enumerate(subs):
        folder = out / "submodels" / sub.name
        _link_photos(folder / "photos", [by_name[n].path for n in sub.photos])
        configs.append(dataclasses.replace(config, photos_dir=folder / "photos", out_dir=folder, stop_after=None,
                                           shared_lens=() if lens_index in (None, i) else None))
    log.info("%d photos in %d submodels (about %d each, %.0f m overlap)", len(photos), len(subs),
             scale.target_photos, overlap_m)
    results, lens = _run_on_dask(configs, scale, lens_index)
    run_s = time.perf_counter() - start
    from skyfix.mapping.merge_stage import merge_submodels

    report = merge_submodels(out, subs, results, by_name, scale, config.gps_sigma_m)
    report["shared_lens"] = lens
    report.update({"photos_dir": str(config.photos_dir), "photos": len(photos), "rejected": len(rejected),
                   "overlap_m": overlap_m, "target_photos": scale.target_photos,
                   "scheduler": scale.scheduler or "LocalCluster", "submodels_seconds": run_s,
                   "total_seconds": time.perf_counter() - start})
    from skyfix.jsonfile import json_safe

    (out / "report.json").write_text(json.dumps(json_safe(report), indent=1) + "\n")
    return report


def _run_on_dask(configs: list[PipelineConfig], scale: ScaleOut, lens_index: int | None) -> tuple[list[dict], dict]:
    """Every submodel's stage chain as Dask tasks; the last group's result per submodel, and the shared
    lens (``{}`` when each submodel estimated its own). The lens submodel's chain up to its mapping
    goes first; the others' mapping waits for its lens."""
    from distributed import as_completed

    from skyfix.progress import bar

    client, cluster = _client(scale, len(configs))
    try:
        if scale.scheduler is None:
            cores = os.cpu_count() or 1
            threads = max(1, cores // len(client.scheduler_info()["workers"]))
            configs = [dataclasses.replace(c, threads=c.threads if c.threads > 0 else threads) for c in configs]
        every, run = [], uuid.uuid4().hex[:8]  # a new run's keys: a shared scheduler may hold old ones
        lens = None
        order = ([] if lens_index is None else [lens_index]) + [i for i in range(len(configs)) if i != lens_index]
        chains: dict[int, object] = {}
        for i in order:
            cfg, prev = configs[i], None
            for group in STAGE_GROUPS:
                key = f"skyfix-map-{run}-{Path(cfg.out_dir).name}-{group}"
                after = () if prev is None else (prev,)
                if group == "georef" and lens is not None and i != lens_index:
                    after += (lens,)
                first = i == lens_index and STAGE_GROUPS.index(group) <= STAGE_GROUPS.index("georef")
                prev = client.submit(_stage_task, cfg, group, *after, key=key, pure=False, retries=scale.retries,
                                     priority=10 if first else 0)
                every.append(prev)
                if i == lens_index and group == "georef":
                    lens = client.submit(_lens_task, cfg, prev, key=f"skyfix-map-{run}-{Path(cfg.out_dir).name}-lens",
                                         pure=False, retries=scale.retries, priority=10)
                    every.append(lens)
            chains[i] = prev
        finals = [chains[i] for i in range(len(configs))]
        with bar(desc=f"{len(configs)} submodels", total=len(every), unit="stage") as progress:
            for _ in as_completed(every):
                progress.update(1)
        results = client.gather(finals)
        shared = {} if lens is None else client.gather(lens)
        return results, shared
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
