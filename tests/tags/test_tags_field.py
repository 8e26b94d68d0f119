import json
import time

import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.errors import DataError, InputError
from skyfix.tags.codec import TileCodec
from skyfix.tags.dimensioning import dimension
from skyfix.tags.field import TagField
from skyfix.tags.placement import king_edges, optimise_placement


def test_placement_400_tags_fast_and_beats_random():
    codec = TileCodec(6, 4)
    start = time.perf_counter()
    values, report = optimise_placement(codec, 20, 20, time_limit_s=4.0)
    assert time.perf_counter() - start < 10.0
    assert np.unique(values).size == 400
    assert report.min_distance > report.random_min
    # Recompute the reported objective independently.
    e = king_edges(20, 20)
    d = codec.tag_distance(values.ravel()[e[:, 0]], values.ravel()[e[:, 1]])
    assert d.min() == pytest.approx(report.min_distance, rel=1e-5)


def test_king_edges_count():
    assert len(king_edges(3, 4)) == 3 * 3 + 2 * 4 + 2 * 2 * 3


def test_too_many_tags_for_codec():
    with pytest.raises(InputError, match="distinct values"):
        optimise_placement(TileCodec(2, 4), 5, 5)


def test_save_load_round_trip(tmp_path, tag_field):
    path = tag_field.save(tmp_path / "f.json")
    back = TagField.load(path)
    assert np.array_equal(back.values, tag_field.values)
    assert np.allclose(back.codec.palette_rgb, tag_field.codec.palette_rgb)
    assert back.geometry == tag_field.geometry and back.spacing_m == tag_field.spacing_m
    assert back.index_of(tag_field.values[3, 4]).tolist() == [3 * 12 + 4]
    assert back.index_of([6 ** 4 - 1 + 10]).tolist() == [-1]


def test_load_rejects_bad_files(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        TagField.load(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(DataError, match="JSON"):
        TagField.load(tmp_path / "bad.json")
    (tmp_path / "other.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(DataError, match="not a skyfix tag field"):
        TagField.load(tmp_path / "other.json")


def test_duplicate_values_rejected(tag_field):
    v = tag_field.values.copy()
    v[0, 1] = v[0, 0]
    with pytest.raises(InputError, match="distinct"):
        TagField(tag_field.codec, tag_field.geometry, tag_field.spacing_m, v)


def test_print_outputs(tmp_path, tag_field):
    import cv2

    png = tag_field.write_png(tmp_path / "f.png", dpi=25.4 / 2.5)   # 2.5 mm per pixel
    img = cv2.imread(str(png))
    x0, y0, x1, y1 = tag_field.bounds_m(0.02)
    assert img.shape[1] == pytest.approx((x1 - x0) / 0.0025, abs=1)
    svg = tag_field.write_svg(tmp_path / "f.svg").read_text()
    assert svg.count("<rect") == 1 + 12 * 12 * 4


def test_rasterised_tiles_sit_at_field_coordinates(tag_field):
    mpp = 0.0025
    image, centre = tag_field.rasterise(mpp, margin_m=0.1)
    h, w = image.shape[:2]
    # Darkness-weighted centroid of the tiles of tag (row 2, col 5), compared with the field.
    idx = 2 * 12 + 5
    pts = tag_field.tile_points_m([idx])[0]
    for xy in pts:
        col = (xy[0] - centre[0]) / mpp + (w - 1) / 2.0
        row = (h - 1) / 2.0 - (xy[1] - centre[1]) / mpp
        r0, c0 = int(round(row)), int(round(col))
        patch = 1.0 - image[r0 - 14:r0 + 15, c0 - 14:c0 + 15].min(axis=2)
        rr, cc = np.mgrid[r0 - 14:r0 + 15, c0 - 14:c0 + 15]
        assert (patch * cc).sum() / patch.sum() == pytest.approx(col, abs=0.05)
        assert (patch * rr).sum() / patch.sum() == pytest.approx(row, abs=0.05)


def test_dimensioning_front_and_constraints():
    cam = Camera.from_fov(640, 480, 60.0)
    dim = dimension(4.75, 4.75, cam, 1.0, 3.0, tilt_deg=15.0)
    # Tiles >= 8 px at 3 m along a 15-degree-tilted axis.
    assert cam.fx * dim.tile_m / (3.0 / np.cos(np.radians(15))) == pytest.approx(8.0, rel=1e-6)
    for c, n in dim.admissible:
        assert c ** n >= dim.rows * dim.cols
    for c, n in dim.pareto:
        assert not any(c2 <= c and n2 <= n and (c2, n2) != (c, n) for c2, n2 in dim.admissible)
    assert dim.chosen in dim.pareto
    with pytest.raises(InputError, match="no \\(colours, tiles\\) pair"):
        dimension(40, 40, cam, 1.0, 3.0)
