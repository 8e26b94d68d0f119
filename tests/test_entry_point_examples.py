"""The entry points of thermal/, crps/, mapping/ and datasets/ carry runnable ``Example:`` sections.

pytest runs them as doctests because pyproject's testpaths hold those folders and its
addopts ``--doctest-modules`` (checked below, so dropping either fails too). The
foundation's own check is tests/foundation/test_examples.py.
"""

from __future__ import annotations

import importlib
import inspect

import pytest

ENTRY_POINTS = {
    "thermal": ["skyfix.thermal.detect:detect_hotspots", "skyfix.thermal.geolocate:geolocate",
                "skyfix.thermal.ground:FlatGround", "skyfix.thermal.pose:camera_pose",
                "skyfix.thermal.tracker:FireTracker"],
    "crps": ["skyfix.crps.silhouette:SilhouetteDetector", "skyfix.crps.fit:SilhouetteFit", "skyfix.crps.track:Tracker",
             "skyfix.crps.observation:observe", "skyfix.crps.observation:locate",
             "skyfix.crps.ranging:range_from_size", "skyfix.crps.ranging:range_from_reference",
             "skyfix.crps.model:DroneModel"],
    "mapping": ["skyfix.mapping.lens:parse_barrel", "skyfix.mapping.lens:barrel_to_opencv",
                "skyfix.mapping.correct:Undistortion.for_barrel", "skyfix.mapping.survey:plan_three_corners",
                "skyfix.mapping.survey:plan_polygon", "skyfix.mapping.coverage:verify_coverage",
                "skyfix.mapping.mission:mission_items", "skyfix.mapping.split:split_survey"],
    "datasets": ["skyfix.datasets.render:GroundTexture", "skyfix.datasets.drone_view:render_drone_view",
                 "skyfix.datasets.gauss_markov:gauss_markov"],
}


def _resolve(spec: str):
    module, qualname = spec.split(":")
    obj = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


@pytest.mark.parametrize("spec", [s for specs in ENTRY_POINTS.values() for s in specs])
def test_entry_point_has_an_example(spec):
    assert "Example:" in (inspect.getdoc(_resolve(spec)) or ""), f"{spec} has no Example: section"


def test_pytest_runs_the_folders_doctests(pytestconfig):
    assert set(ENTRY_POINTS) <= set(pytestconfig.getini("testpaths"))
    assert "--doctest-modules" in pytestconfig.getini("addopts")
