"""Survey planning: the source platform's grid and extension, photo coverage, split, handoff."""

from __future__ import annotations

import json

import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.errors import GeometryError, InputError
from skyfix.geo import destination
from skyfix.mapping.coverage import verify_coverage
from skyfix.mapping.split import handoff, split_survey
from skyfix.mapping.survey import (
    extend_survey,
    footprint_m,
    plan_polygon,
    plan_survey,
    plan_three_corners,
)

LAT0, LON0 = 40.6303, -8.6575  # University of Aveiro campus


def _at(bearing_deg: float, dist_m: float) -> tuple[float, float]:
    lat, lon = destination(LAT0, LON0, bearing_deg, dist_m)
    return float(lat), float(lon)


@pytest.fixture()
def campus_plan():
    """The source platform's experiment: 28 m x 35 m, waypoints 7 m apart."""
    return plan_three_corners((LAT0, LON0), _at(90, 28), _at(0, 35), 7.0, 10.0, hold_s=2.0)


def test_three_corner_grid_has_30_waypoints_in_boustrophedon_order(campus_plan):
    wp = campus_plan.waypoints_en_m
    assert campus_plan.n_waypoints == 30
    steps = np.hypot(*np.diff(wp, axis=0).T)
    assert steps == pytest.approx(np.full(29, 7.0), abs=1e-6)  # every hop is one step: no diagonal jumps
    assert wp[0] == pytest.approx([0, 0], abs=1e-6) and wp[4] == pytest.approx([28, 0], abs=1e-6)
    assert wp[5] == pytest.approx([28, 7], abs=1e-6)  # next row comes back
    assert wp[:, 0].max() == pytest.approx(28, abs=1e-6) and wp[:, 1].max() == pytest.approx(35, abs=1e-6)


def test_extension_for_two_drones_reproduces_56_waypoints(campus_plan):
    alarm = _at(45, 20)
    big = extend_survey(campus_plan, alarm, joining_drones=2)
    assert big.n_waypoints == 56
    assert np.hypot(*big.v_en_m) == pytest.approx(42) and np.hypot(*big.w_en_m) == pytest.approx(49)
    assert big.step_m == campus_plan.step_m
    area = abs(big.v_en_m[0] * big.w_en_m[1] - big.v_en_m[1] * big.w_en_m[0])
    assert area == pytest.approx(2058.0)  # the thesis' figure: +110 %
    centre = big.waypoints_en_m.mean(axis=0)
    e, n, _ = campus_plan.frame.to_enu(*alarm, 0.0)
    assert centre == pytest.approx([float(e), float(n)], abs=1e-6)
    assert extend_survey(campus_plan, alarm, 0).n_waypoints == 30


def test_split_is_contiguous_balanced_and_assigned_to_nearest(campus_plan):
    big = extend_survey(campus_plan, _at(45, 20), 2)
    start, end = big.waypoints_latlon()[0], big.waypoints_latlon()[-1]
    drones = {"far": (float(end[0]) + 0.0005, float(end[1])), "near": (float(start[0]), float(start[1]) - 0.0001),
              "mid": (LAT0 + 0.0003, LON0 + 0.0002)}
    parts = split_survey(big, drones)
    lengths = [p.length_m for p in parts]
    assert max(lengths) - min(lengths) <= big.step_m + 1e-9
    assert sum(p.plan.n_waypoints for p in parts) == 56
    for p in parts:  # contiguous: a slice of the whole path, possibly flown backwards
        chunk = big.waypoints_en_m[p.first_index:p.first_index + p.plan.n_waypoints]
        assert np.allclose(p.plan.waypoints_en_m, chunk) or np.allclose(p.plan.waypoints_en_m, chunk[::-1])
    by_id = {p.drone_id: p for p in parts}
    assert by_id["near"].first_index == 0 and by_id["far"].first_index == parts[-1].first_index


@pytest.fixture()
def photo_plan():
    camera = Camera.from_fov(1200, 900, 60.0)
    polygon = [(LAT0, LON0), _at(90, 250), _at(60, 260), _at(10, 180)]
    return plan_polygon(polygon, camera, 70.0, 0.75, 0.6, heading_deg=None)


def test_photo_survey_covers_area_at_requested_overlap(photo_plan):
    across, along = footprint_m(photo_plan.camera, 70.0)
    assert photo_plan.step_m == pytest.approx(across * 0.4)
    assert photo_plan.trigger_distance_m == pytest.approx(along * 0.25)
    cov = verify_coverage(photo_plan)
    assert cov.uncovered_m2 < 1e-6 * cov.area_m2
    # Footprints on the curved earth differ from the flat formula by ~1e-5 relative.
    assert cov.forward_overlap_min >= 0.75 - 1e-3
    assert cov.side_overlap_min >= 0.60 - 1e-3


def test_photo_survey_lines_have_turnaround_margins(photo_plan):
    wp, on = photo_plan.waypoints_en_m, photo_plan.trigger_on
    photos, _ = photo_plan.photo_positions_en_m()
    # First segment is the run-in: no photos, half the along-track footprint long by default.
    assert not on[0] and np.hypot(*(wp[1] - wp[0])) == pytest.approx(photo_plan.turnaround_m)
    assert photos[0] == pytest.approx(wp[1])


def test_split_photo_survey_equal_lengths_and_coverage_kept(photo_plan):
    parts = split_survey(photo_plan, {"a": (LAT0, LON0), "b": _at(60, 260), "c": _at(10, 180)})
    lengths = np.array([p.length_m for p in parts])
    assert np.ptp(lengths) < 1e-6 * lengths.max()
    assert lengths.sum() == pytest.approx(photo_plan.path_length_m)
    photos = np.concatenate([p.plan.photo_positions_en_m()[0] for p in parts])
    whole = photo_plan.photo_positions_en_m()[0]
    # Every planned photo of the whole plan has a photo of some part within one trigger distance.
    d = np.min(np.linalg.norm(whole[:, None] - photos[None], axis=2), axis=1)
    assert d.max() <= photo_plan.trigger_distance_m + 1e-6


def test_handoff_goes_to_nearest_and_starts_where_it_stopped(photo_plan):
    stop = photo_plan.waypoints_latlon()[5] * 0.5 + photo_plan.waypoints_latlon()[6] * 0.5
    part = handoff(photo_plan, 6, {"x": _at(0, 5000), "y": (float(stop[0]), float(stop[1]) + 0.0001)},
                   stopped_at_latlon=stop)
    assert part.drone_id == "y" and part.first_index == 6
    assert part.plan.n_waypoints == photo_plan.n_waypoints - 6 + 1
    assert part.plan.waypoints_latlon()[0] == pytest.approx(stop, abs=1e-9)
    assert part.plan.trigger_on[0] == photo_plan.trigger_on[5]
    with pytest.raises(InputError):
        handoff(photo_plan, photo_plan.n_waypoints, {"x": (LAT0, LON0)})


def test_bad_inputs_get_clear_errors():
    with pytest.raises(GeometryError, match="collinear"):
        plan_three_corners((LAT0, LON0), _at(90, 28), _at(90, 50), 7, 10)
    with pytest.raises(GeometryError, match="coincide"):
        plan_three_corners((LAT0, LON0), (LAT0, LON0), _at(0, 35), 7, 10)
    with pytest.raises(GeometryError, match="longer than a side"):
        plan_three_corners((LAT0, LON0), _at(90, 28), _at(0, 35), 30, 10)
    with pytest.raises(InputError, match="step_m"):
        plan_three_corners((LAT0, LON0), _at(90, 28), _at(0, 35), 0, 10)
    cam = Camera.from_fov(1200, 900, 60.0)
    square = [(LAT0, LON0), _at(90, 100), _at(45, 141), _at(0, 100)]
    for fwd, side in ((1.0, 0.6), (0.7, 1.2), (-0.1, 0.5)):
        with pytest.raises(InputError, match="overlap"):
            plan_polygon(square, cam, 50, fwd, side)
    with pytest.raises(GeometryError, match="simple"):
        plan_polygon([(LAT0, LON0), _at(90, 100), _at(0, 100), _at(45, 141)], cam, 50, 0.7, 0.6)
    with pytest.raises(InputError):
        plan_survey(altitude_m=10)
    with pytest.raises(InputError, match="latitude"):
        plan_three_corners((95.0, LON0), _at(90, 28), _at(0, 35), 7, 10)


def test_plan_json_round_trip(photo_plan, tmp_path):
    from skyfix.mapping.plan_io import load_plan, save_plan

    save_plan(tmp_path / "p.json", photo_plan)
    back = load_plan(tmp_path / "p.json")
    assert np.allclose(back.waypoints_en_m, photo_plan.waypoints_en_m)
    assert back.camera == photo_plan.camera and np.array_equal(back.trigger_on, photo_plan.trigger_on)
    json.loads((tmp_path / "p.json").read_text())


def test_photo_spacing_continues_across_waypoints_inside_a_run():
    from skyfix.mapping.survey import SurveyPlan

    base = plan_three_corners((LAT0, LON0), _at(90, 28), _at(0, 35), 7.0, 10.0)
    # One straight run split by a waypoint at 25 m: photos every 10 m from 0 m, none twice.
    wp = np.array([[0.0, 0.0], [25.0, 0.0], [60.0, 0.0]])
    plan = SurveyPlan(base.frame, "lines", wp, 10.0, wp, 10.0, np.array([True, True]), trigger_distance_m=10.0)
    photos, headings = plan.photo_positions_en_m()
    assert photos[:, 0] == pytest.approx([0, 10, 20, 30, 40, 50, 60])
    wp2 = np.array([[0.0, 0.0], [20.0, 0.0], [45.0, 0.0]])  # waypoint exactly on a photo
    plan2 = SurveyPlan(base.frame, "lines", wp2, 10.0, wp2, 10.0, np.array([True, True]), trigger_distance_m=10.0)
    assert plan2.photo_positions_en_m()[0][:, 0] == pytest.approx([0, 10, 20, 30, 40])
