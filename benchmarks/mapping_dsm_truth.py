"""Dense DSM cells against the truth: the rendered survey (skyfix.datasets.survey_scene).

``benchmarks/mapping.py`` counts how much of the real Seneca survey the dense DSM measures,
but Seneca has no ground truth. This benchmark renders the test survey (15 photos, 3 lines
x 5, 30 m above hills, buildings and trees: tests/mapping/test_mapping_rendered_survey.py),
runs ``skyfix map`` on it once, then builds the dense DSM twice on the same model and grid:

- baseline: the fill rules before the mirrored band pass (one round per coarser pass, the
  smooth-ground checks at 0.5 m, no band pass: ``band_fill=False, fill_rounds=1,
  fill_max_range_m=0.5``);
- skyfix: the defaults (the mirrored band pass, each pass's fill grown from the rims while it
  adds cells, the checks at 1 m);

and prints, for each, the share of the stereo area measured and the height error against
the true surface of the first pass's cells and of every cell the band and fill passes add
(median, 90th percentile, share over 1 m). Goal (the issue's 0.3 m median for the DSM, and
tests/mapping's 1 m for 90 % of filled cells): added cells within 0.3 m median and 1 m for
90 %; exits non-zero when missed. Headline on the last line.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BASELINE = {"band_fill": False, "fill_rounds": 1, "fill_max_range_m": 0.5}


def _errors_m(scene, grid, surface: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """|DSM height - true surface height| (m) at the ``mask`` cells."""
    from skyfix.mapping.grid import UtmToEnu

    rows, cols = np.nonzero(mask)
    east, north = grid.centres_m(rows, cols)
    to_enu = UtmToEnu(scene.frame, grid.epsg, grid.bounds_m)  # the truth's frame
    enu = to_enu(np.asarray(east, float), np.asarray(north, float), surface[rows, cols].astype(float))
    return np.abs(enu[:, 2] - scene.height_at(enu[:, 0], enu[:, 1]))


def _stats(errors: np.ndarray) -> str:
    if not errors.size:
        return "no cells"
    return (f"{errors.size} cells, {np.median(errors):.3f} m median, {np.percentile(errors, 90):.3f} m for 90 %, "
            f"{100 * np.mean(errors > 1.0):.1f} % over 1 m")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="work folder (default: a temporary one)")
    args = parser.parse_args()
    from skyfix.datasets.survey_scene import make_scene, write_survey
    from skyfix.geo import LocalFrame
    from skyfix.mapping import sfm
    from skyfix.mapping.dense import dense_dsm, stereo_area
    from skyfix.mapping.grid import EnuToUtm, Grid
    from skyfix.mapping.ortho import load_views
    from skyfix.mapping.surface_stages import points

    root = args.out or Path(tempfile.mkdtemp(prefix="skyfix-dsm-truth-"))
    scene = make_scene()
    load_start, start = os.getloadavg()[0], time.perf_counter()
    if not (root / "project" / "report.json").exists():
        write_survey(root / "survey", scene)
        subprocess.run([sys.executable, "-m", "skyfix.cli", "-q", "map", str(root / "survey"), "-o",
                        str(root / "project")], check=True, env=dict(os.environ, GLOG_minloglevel="2"))
    stages = root / "project" / "work" / "stages"
    frame = LocalFrame(*json.loads((stages / "georef.json").read_text())["frame"])
    grid = Grid(**json.loads((stages / "dsm.json").read_text())["grid"])
    models = sfm.load_models(root / "project" / "work" / "georef")
    sparse, _ = points(models)
    views = load_views(models, root / "survey")
    lo, hi = sparse[:, :2].min(axis=0), sparse[:, :2].max(axis=0)
    up = (float(sparse[:, 2].min()) - 20.0, float(sparse[:, 2].max()) + 20.0)
    to_utm = EnuToUtm(frame, grid.epsg, (lo[0], lo[1], hi[0], hi[1]), up)
    paths = {v.name: v.path for v in views}
    area = stereo_area(views, grid, to_utm, float(np.median(sparse[:, 2])))
    first, _ = dense_dsm(views, paths, sparse, to_utm, grid, fill_scales=(), band_fill=False)
    kept = np.isfinite(first.surface_m)
    print(f"first pass: {100 * kept[area].mean():.2f} % of the stereo area; vs truth: "
          f"{_stats(_errors_m(scene, grid, first.surface_m, kept))}")
    results = {}
    for name, options in (("baseline", BASELINE), ("skyfix", {})):
        dsm, cloud = dense_dsm(views, paths, sparse, to_utm, grid, **options)
        added = np.isfinite(dsm.surface_m) & ~kept
        errors = _errors_m(scene, grid, dsm.surface_m, added)
        results[name] = (100 * np.isfinite(dsm.surface_m)[area].mean(), errors)
        passes = ", ".join(f"{'band ' if f.get('band') else ''}{f['scale']:g}: +{f['cells_added']}"
                           for f in cloud.fills)
        print(f"{name}: {results[name][0]:.2f} % of the stereo area measured; cells added by the passes "
              f"({passes}) vs truth: {_stats(errors)}")
    share, errors = results["skyfix"]
    met = errors.size > 0 and np.median(errors) <= 0.3 and np.percentile(errors, 90) <= 1.0
    revision = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent).stdout.strip()
    print(f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC, load {load_start:.1f}-{os.getloadavg()[0]:.1f}, "
          f"{time.perf_counter() - start:.0f} s, revision {revision}")
    print(f"dsm truth: measured {share:.2f} % of the stereo area ({share / results['baseline'][0]:.3f}x the "
          f"baseline's {results['baseline'][0]:.2f} %), added cells {np.median(errors) if errors.size else np.nan:.2f} m "
          f"median and {np.percentile(errors, 90) if errors.size else np.nan:.2f} m for 90 % off the truth "
          f"(goal 0.3 / 1 m): {'met' if met else 'NOT met'}")
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
