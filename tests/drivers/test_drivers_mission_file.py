"""Mission JSON (drivers.mission.MissionFile): the form `mission download` writes meets the
published schema (docs/schemas/mission.schema.json, checked with jsonschema) and reads back;
a malformed plan is refused by schema and CLI alike, before any link is opened."""

from __future__ import annotations

import json
import re
from dataclasses import asdict
from pathlib import Path

import jsonschema
import pytest

from skyfix.cli import main
from skyfix.drivers.mission import MissionFile, MissionItem
from skyfix.jsonfile import convert

SCHEMA = jsonschema.Draft202012Validator(json.loads(
    (Path(__file__).resolve().parents[2] / "docs" / "schemas" / "mission.schema.json").read_text()))
ITEMS = [MissionItem.takeoff(10.0), MissionItem.waypoint(46.52, 6.63, 12.0, hold_s=2.0, acceptance_m=1.5)]


def test_downloaded_form_meets_the_schema_and_reads_back():
    doc = json.loads(json.dumps({"system_id": 1, "items": [asdict(it) for it in ITEMS]}))
    assert list(SCHEMA.iter_errors(doc)) == []
    plan = convert(doc, MissionFile, "m.json")
    assert plan.items == ITEMS and plan.system_id == 1


@pytest.mark.parametrize(("case", "items", "says"), [
    ("lat_91", [{"command": 16, "lat_deg": 91.0}], r"items\[0\]\.lat_deg: expected `float` <= 90"),
    ("no_command", [{"lat_deg": 1.0}], r"items\[0\]: object missing required field `command`"),
    ("text_alt", [{"command": 16, "alt_m": "ten"}], r"items\[0\]\.alt_m: expected `float`, got `str`"),
])
def test_malformed_plan_is_refused_naming_file_and_key(tmp_path, caplog, case, items, says):
    assert not SCHEMA.is_valid({"items": items})
    plan = tmp_path / f"{case}.json"
    plan.write_text(json.dumps({"items": items}))
    # udpout to the discard port: the plan must be refused before the link is used.
    assert main(["vehicle", "mission", "upload", "udpout:127.0.0.1:9", str(plan), "--timeout", "0.5"]) == 2
    assert f"{case}.json" in caplog.text
    assert any(re.search(says, r.getMessage()) for r in caplog.records), caplog.text
