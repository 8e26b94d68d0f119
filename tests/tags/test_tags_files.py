"""Tag field and marker board files: saved files meet the published schemas (docs/schemas/,
checked with jsonschema, independently of msgspec), and malformed ones are refused by both the
schema and the reader with a DataError naming the file and the key."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest

from skyfix.errors import DataError
from skyfix.tags.aruco import ArucoField
from skyfix.tags.field import TagField

SCHEMAS = Path(__file__).resolve().parents[2] / "docs" / "schemas"


def _schema(name: str) -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(json.loads((SCHEMAS / name).read_text()))


@pytest.fixture(scope="module")
def small_field() -> TagField:
    return TagField.generate(3, 4, tile_m=0.05, gap_m=0.02, spacing_m=0.25, max_iterations=200, seed=1)


def test_saved_files_meet_their_schema_and_read_back(tmp_path, small_field):
    small_field.save(tmp_path / "field.json")
    saved = json.loads((tmp_path / "field.json").read_text())
    assert list(_schema("tag_field.schema.json").iter_errors(saved)) == []
    back = TagField.load(tmp_path / "field.json")
    assert (back.values == small_field.values).all() and back.placement == small_field.placement
    board = ArucoField("4x4_50", rows=2, cols=3, marker_m=0.2, spacing_m=0.3, first_id=4, origin_xy_m=(1.0, -2.0))
    board.save(tmp_path / "board.json")
    saved = json.loads((tmp_path / "board.json").read_text())
    assert list(_schema("marker_board.schema.json").iter_errors(saved)) == []
    assert ArucoField.from_dict(saved) == board


@pytest.mark.parametrize(("case", "change", "key"), [
    ("text_spacing", {"spacing_m": "0.25"}, "spacing_m"),
    ("negative_gap", {"gap_m": -0.01}, "gap_m"),
    ("palette_255", {"palette_rgb": [[255, 0, 0]] * 6}, r"palette_rgb\[0\]\[0\]"),
    ("no_values", {"values": None}, "values"),
    ("version_2", {"version": 2}, "version"),
])
def test_malformed_tag_field_is_refused_by_schema_and_reader(tmp_path, small_field, case, change, key):
    data = small_field.to_dict() | change
    assert not _schema("tag_field.schema.json").is_valid(data)
    (tmp_path / f"{case}.json").write_text(json.dumps(data))
    with pytest.raises(DataError, match=rf"{case}\.json: {key}"):
        TagField.load(tmp_path / f"{case}.json")


@pytest.mark.parametrize(("change", "key"), [({"rows": 0}, "rows"), ({"marker_m": True}, "marker_m"),
                                             ({"first_id": 2.5}, "first_id")])
def test_malformed_board_is_refused_by_schema_and_reader(change, key):
    data = ArucoField("4x4_50", rows=2, cols=3, marker_m=0.2, spacing_m=0.3).to_dict() | change
    assert not _schema("marker_board.schema.json").is_valid(data)
    with pytest.raises(DataError, match=rf"board\.json: {key}"):
        ArucoField.from_dict(data, "board.json")


def test_semantic_refusals_name_the_file(tmp_path):
    # Valid by type, refused by the field itself: a marker grid with more ids than the dictionary.
    data = ArucoField("4x4_50", rows=2, cols=3, marker_m=0.2, spacing_m=0.3).to_dict() | {"rows": 10, "cols": 10}
    assert _schema("marker_board.schema.json").is_valid(data)
    with pytest.raises(DataError, match=r"big\.json: 100 markers .* do not fit"):
        ArucoField.from_dict(data, "big.json")
