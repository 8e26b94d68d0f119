"""JSON files a user names: read with a skyfix error that says which file and what is wrong,
checked against a msgspec model (one ``msgspec.Struct`` per file format), whose JSON Schema
is published in ``docs/schemas/``."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any, TypeVar

import msgspec

from skyfix.errors import DataError, SkyfixError

T = TypeVar("T")
_AT = re.compile(r"^(?P<msg>.*?)(?: - at `\$(?P<path>[^`]*)`)?$", re.S)


def read_json(path: str | os.PathLike, what: str, *, missing: type[SkyfixError] = DataError) -> Any:
    """Parsed content of the JSON file ``path``; ``what`` names it in errors ("camera file").

    A file that does not exist raises ``missing`` (DataError by default; pass InputError
    where the path is a command-line argument); an unreadable or malformed one DataError.
    """
    p = Path(path)
    if not p.is_file():
        raise missing(f"{what} {str(p)!r} does not exist")
    try:
        return json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{what} {p} is not readable JSON: {exc}") from exc


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, infinities: JSON has none) as None, through
    nested dicts, lists and tuples (tuples become lists), ready for ``json.dumps(allow_nan=False)``.

    Example:
        >>> json_safe({"rms_m": float("nan"), "xy": (1.0, float("inf")), "n": 3})
        {'rms_m': None, 'xy': [1.0, None], 'n': 3}
    """
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def convert(data: Any, model: type[T], source: str) -> T:
    """``data`` (parsed JSON) checked against and converted to ``model`` (a msgspec Struct or
    dataclass); DataError naming ``source`` and the key on a mismatch.

    Example:
        >>> class Point(msgspec.Struct):
        ...     x_m: float
        >>> convert({"x_m": 2}, Point, "p.json")
        Point(x_m=2.0)
        >>> convert({"x_m": "2"}, Point, "p.json")
        Traceback (most recent call last):
        ...
        skyfix.errors.DataError: p.json: x_m: expected `float`, got `str`
    """
    try:
        return msgspec.convert(data, model)
    except msgspec.ValidationError as exc:
        raise DataError(f"{source}: {_readable(str(exc))}") from None


def _readable(message: str) -> str:
    """msgspec's "Expected `int`, got `str` - at `$.a[0].b`" as "a[0].b: expected `int`, got `str`"."""
    m = _AT.match(message)
    msg = m["msg"][:1].lower() + m["msg"][1:] if m["msg"][:2] in ("Ex", "Ob", "In") else m["msg"]
    path = (m["path"] or "").lstrip(".")
    return f"{path}: {msg}" if path else msg


def json_schema(model: type, *extra: type) -> dict:
    """JSON Schema (2020-12) of ``model`` (and of ``extra`` types, in ``$defs``), for publishing.

    Example:
        >>> class Point(msgspec.Struct):
        ...     '''A point, metres.'''
        ...     x_m: float
        >>> json_schema(Point)["$defs"]["Point"]["required"]
        ['x_m']
    """
    (root, *_), defs = msgspec.json.schema_components((model, *extra), ref_template="#/$defs/{name}")
    for item in defs.values():  # a docstring's first paragraph, not its examples
        if "description" in item:
            item["description"] = " ".join(item["description"].split("\n\n")[0].split())
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **root, "$defs": defs}
