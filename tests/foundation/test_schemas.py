"""Published JSON Schemas (docs/schemas/): current with the code, and they agree with the readers.

The schemas are generated from the msgspec models the readers use; an independent validator
(jsonschema) checks that files skyfix writes pass them and that malformed ones the reader
refuses fail them too.
"""

from __future__ import annotations

import functools
import importlib.util
import json
from pathlib import Path

import jsonschema
import pytest

from skyfix.camera import Camera
from skyfix.camera_io import camera_to_dict, load_camera
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import DataError

SCHEMAS = Path(__file__).resolve().parents[2] / "docs" / "schemas"


def _writer():
    spec = importlib.util.spec_from_file_location("write_schemas", SCHEMAS / "write_schemas.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@functools.cache
def _validator(name: str) -> jsonschema.Draft202012Validator:
    schema = json.loads((SCHEMAS / name).read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_published_schemas_are_current():
    writer = _writer()
    assert set(writer.SCHEMAS) == {p.name for p in SCHEMAS.glob("*.schema.json")}
    assert writer.stale() == [], "run python docs/schemas/write_schemas.py"


@pytest.mark.parametrize("lens", [None, BrownConrady(k1=-0.1, p2=1e-4), Fisheye(k4=0.01), Barrel(0.1, -0.32, 0.0)])
def test_written_camera_files_meet_the_schema(lens):
    data = camera_to_dict(Camera(4000, 3000, 2900.0, 2901.0, 1999.5, 1499.5, lens), rms_px=0.4)
    assert list(_validator("camera.schema.json").iter_errors(data)) == []


BASE = {"width": 640, "height": 512, "fx_px": 600.0, "fy_px": 600.0, "cx_px": 319.5, "cy_px": 255.5}
REFUSED = {  # malformed camera files: the reader refuses each, and so does the published schema
    "text_f": BASE | {"fy_px": "600"},
    "frac_w": BASE | {"width": 640.5},
    "zero_f": BASE | {"fx_px": 0.0},
    "typo_coef": BASE | {"model": "brown_conrady", "coefficients": {"k9": 1.0}},
    "barrel_a_only": BASE | {"model": "barrel", "coefficients": {"a": 0.1}},
    "model": BASE | {"model": "kannala"},
    "fov_180": {"width": 640, "height": 480, "hfov_deg": 180.0},
    "two_forms": BASE | {"fx": 600.0, "fy": 600.0, "cx": 319.5, "cy": 255.5},
    "no_form": {"width": 640, "height": 480},
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_schema_and_reader_refuse_the_same_camera_files(tmp_path, case):
    assert not _validator("camera.schema.json").is_valid(REFUSED[case])
    path = tmp_path / f"{case}.json"
    path.write_text(json.dumps(REFUSED[case]))
    with pytest.raises(DataError, match=rf"{case}\.json"):
        load_camera(path)
