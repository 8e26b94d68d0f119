"""``skyfix map --split`` end to end on a rendered survey of 100 photos split in 4, on a Dask cluster of two
worker processes, one of which is killed mid-run (skyfix.mapping.scale_out).

The survey: 10 lines x 10 nadir photos (512x288) 30 m above the take-off point over hills, buildings and
trees (skyfix.datasets.survey_scene, as tests/mapping/test_mapping_rendered_survey.py), GPS with a
correlated 0.4 m / 0.2 m random walk whose tags trail the photos by 0.3 s (1.5 m along alternating lines:
real tags lag, and the Seneca survey's lag is what broke a first alignment that held the submodels on
the raw tags). Bounds:
- submodels agree in their overlap within 2x the one model's georeference residual (the issue's rule);
- a seam's height step: the two DSMs' median difference where both measured, <= 5 cm (their cells are
  0.35 m and the dense surfaces differ by a median 3-5 cm anywhere: a step above that would be the
  misalignment); its image shift <= 0.5 px (4 cm at this GSD, a tenth of the GPS walk);
- the merged DSM within 0.3 m median of the true ground (issue 19's bound for one model), and the same on
  both sides of every boundary (steps against the truth <= 5 cm).
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from skyfix.datasets.survey_scene import make_scene, write_survey
from skyfix.mapping.pipeline import PipelineConfig, run_pipeline

LINES, PER_LINE = 10, 10
# Minutes of work: rendering 100 photos, one model to its georeference, four submodels of 42 photos on two
# worker processes and a re-run after one is killed (quiet 2-core machine: ~6 min; two suites at once: ~12)
pytestmark = pytest.mark.timeout(1800)


@pytest.fixture(scope="module")
def scene():
    return make_scene(size_m=(LINES * 14.0 + 50.0, PER_LINE * 8.0 + 50.0))


@pytest.fixture(scope="module")
def survey(scene, tmp_path_factory):
    folder = tmp_path_factory.mktemp("survey100")
    return folder, write_survey(folder, scene, lines=LINES, per_line=PER_LINE, gps_lag_s=0.3)


@pytest.fixture(scope="module")
def one_model(survey, tmp_path_factory):
    """The same photos as one model, as far as its georeference (the residual the split is judged by)."""
    return run_pipeline(PipelineConfig(survey[0], tmp_path_factory.mktemp("one"), threads=2, stop_after="georef"))


@pytest.fixture(scope="module")
def split_run(survey, tmp_path_factory):
    """``run_split`` on a LocalCluster of 2 workers; one worker is SIGKILLed once a submodel has mapped."""
    from distributed import Client, LocalCluster

    from skyfix.mapping.scale_out import ScaleOut, run_split

    out = tmp_path_factory.mktemp("split")
    killed: list[int] = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        pids = sorted(client.run(os.getpid).values())

        def kill_when_mapped():
            deadline = time.monotonic() + 900
            while time.monotonic() < deadline and not killed:
                if any((out / "submodels").glob("*/work/stages/georef.json")):
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(pids[0])
                    return
                time.sleep(0.2)

        watcher = threading.Thread(target=kill_when_mapped, daemon=True)
        watcher.start()
        t0 = time.perf_counter()
        report = run_split(PipelineConfig(survey[0], out, threads=1),
                           ScaleOut(25, scheduler=cluster.scheduler_address))
        seconds = time.perf_counter() - t0
        watcher.join(timeout=1)
        after = sorted(client.run(os.getpid).values())
    return out, report, killed, pids, after, seconds


def test_split_survives_a_killed_worker_and_registers_every_photo(split_run):
    out, report, killed, pids, after, _ = split_run
    assert killed, "no submodel reached its georeference: the worker was never killed"
    assert killed[0] not in after and len(after) == 2  # the nanny started a new worker process
    subs = report["submodels"]
    assert len(subs) == 4 and not any(s.get("error") for s in subs)
    assert sorted(s["core_photos"] for s in subs) == [25, 25, 25, 25]
    assert report["registered"] >= 98
    for s in subs:
        assert (Path(s["folder"]) / "work" / "submodel_done.json").exists()
        assert 0 < s["worker_peak_memory_mib"] < 4096
    for name in ("dsm.tif", "orthophoto.tif", "points.ply", "cameras.geojson", "report.json", "report.png",
                 "orthophoto.png"):
        assert (out / name).stat().st_size > 0, name
    assert json.loads((out / "report.json").read_text())["registered"] == report["registered"]


def test_every_submodel_is_mapped_with_the_lens_of_the_largest(split_run):
    """One lens for all: submodels that each refine their own radial term disagree in their overlap."""
    import pycolmap

    _, report, *_ = split_run
    subs = report["submodels"]
    lens = report["shared_lens"]
    largest = max(subs, key=lambda s: (s["photos"], -s["index"]))
    assert lens["from"] == Path(largest["folder"]).name and not lens.get("error")
    ((_, model, params),) = lens["lens"]  # one camera
    assert model == "SIMPLE_RADIAL"
    for s in subs:
        rec = pycolmap.Reconstruction(str(Path(s["folder"]) / "work" / "sparse" / "0"))
        for cam in rec.cameras.values():
            assert cam.model.name == model
            np.testing.assert_allclose(cam.params, params, rtol=0, atol=1e-9)


def test_submodels_agree_in_their_overlap_within_twice_the_one_model_residual(split_run, one_model):
    _, report, *_ = split_run
    rms1 = one_model.georef_rms_m
    assert 0 < rms1 < 1.0
    aligned = [s["alignment"] for s in report["submodels"]]
    assert len(aligned) == 4 and all(a["shared_photos"] >= 10 for a in aligned)
    for a in aligned:  # the shared photos' camera centres, two submodels apart, after the alignment
        assert a["rms_after_m"] <= 2 * rms1, a
    seams = report["seams"]
    assert len(seams) >= 3
    for key, seam in seams.items():
        assert seam["dsm_cells_compared"] > 1000, key
        assert abs(seam["dsm_median_difference_m"]) <= min(0.05, 2 * rms1), (key, seam)
        assert seam["ortho_shift_px"] <= 0.5, (key, seam)


def test_merged_dsm_matches_the_ground_with_no_step_at_submodel_boundaries(split_run, scene, survey):
    import rasterio
    from scipy.spatial import cKDTree

    from skyfix.mapping.grid import UtmToEnu

    out, report, *_ = split_run
    with rasterio.open(out / "dsm.tif") as ds:
        z = ds.read(1, masked=True).filled(np.nan)
        rows, cols = np.nonzero(np.isfinite(z))
        t = ds.transform
        east, north = t.c + t.a * (cols + 0.5), t.f + t.e * (rows + 0.5)
        to_enu = UtmToEnu(scene.frame, ds.crs.to_epsg(), (east.min(), north.min(), east.max(), north.max()))
    enu = to_enu(east, north, z[rows, cols])
    err = enu[:, 2] - scene.height_at(enu[:, 0], enu[:, 1])
    assert np.median(np.abs(err)) <= 0.3
    # ownership by the nearest core photo (true GPS positions of the survey, ENU)
    gps = {Path(p.path).name: np.array(p.gps_enu_m[:2]) for p in survey[1]}
    split = json.loads((out / "split.json").read_text())["submodels"]
    owner = np.concatenate([[s["index"]] * len(s["core"]) for s in split])
    tree = cKDTree(np.array([gps[n] for s in split for n in s["core"]]))
    d, idx = tree.query(enu[:, :2], k=2)
    label, other = owner[idx[:, 0]], owner[idx[:, 1]]
    near = (d[:, 1] - d[:, 0]) < 3.0  # within ~1.5 m of the boundary between two cores
    steps = []
    for a in range(4):
        for b in range(a + 1, 4):
            side_a = near & (label == a) & (other == b)
            side_b = near & (label == b) & (other == a)
            if side_a.sum() > 200 and side_b.sum() > 200:
                steps.append(float(np.median(err[side_a]) - np.median(err[side_b])))
    assert len(steps) >= 3
    assert max(abs(s) for s in steps) <= 0.05, steps


def test_a_finished_split_is_not_redone(split_run, survey):
    from skyfix.mapping.scale_out import ScaleOut, run_split

    out, report, *_ = split_run
    markers = {p: p.stat().st_mtime_ns for p in (out / "submodels").glob("*/work/stages/*.json")}
    t0 = time.perf_counter()
    again = run_split(PipelineConfig(survey[0], out, threads=1), ScaleOut(25, workers=1))
    assert time.perf_counter() - t0 < 120  # the merge only (a split of 100 photos is minutes of work)
    assert {p: p.stat().st_mtime_ns for p in markers} == markers
    assert again["registered"] == report["registered"]
