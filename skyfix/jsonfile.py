"""Read a JSON file a user named, with a skyfix error that says which file and what is wrong."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from skyfix.errors import DataError, SkyfixError


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
