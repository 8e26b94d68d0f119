"""Write the JSON Schemas of skyfix's file formats into this folder, or check they are current.

    python docs/schemas/write_schemas.py            # (re)write every *.schema.json here
    python docs/schemas/write_schemas.py --check    # exit 1 naming the stale ones

Each schema comes from the msgspec model the reader uses (see skyfix.jsonfile), so the
published schema and the checks a file meets when it is read are the same source.
tests/foundation/test_schemas.py runs the check.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: schema file -> "module:function" returning the schema dict.
SCHEMAS = {
    "camera.schema.json": "skyfix.camera_io:camera_json_schema",
    "tag_field.schema.json": "skyfix.tags.field:tag_field_json_schema",
    "marker_board.schema.json": "skyfix.tags.aruco:aruco_field_json_schema",
    "mission.schema.json": "skyfix.drivers.mission:mission_json_schema",
}


def rendered() -> dict[str, str]:
    """{file name: schema text} as the code describes the formats today."""
    out = {}
    for name, target in SCHEMAS.items():
        module, function = target.split(":")
        schema = getattr(importlib.import_module(module), function)()
        out[name] = json.dumps(schema, indent=2, sort_keys=True) + "\n"
    return out


def stale(folder: Path = HERE) -> list[str]:
    """Schema files in ``folder`` that are missing or differ from :func:`rendered`."""
    return [name for name, text in rendered().items()
            if not (folder / name).is_file() or (folder / name).read_text() != text]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check; exit 1 naming stale files")
    args = parser.parse_args(argv)
    if args.check:
        bad = stale()
        for name in bad:
            print(f"{HERE / name} is stale: run python docs/schemas/write_schemas.py", file=sys.stderr)
        return 1 if bad else 0
    for name, text in rendered().items():
        (HERE / name).write_text(text)
        print(f"wrote {HERE / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
