"""Progress bars for long work, silenced by ``skyfix -q`` and when stderr is not a terminal."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")

_enabled: bool | None = None  # None: decide from whether stderr is a terminal


def set_enabled(enabled: bool | None) -> None:
    """Force progress bars on (True), off (False), or back to automatic (None)."""
    global _enabled
    _enabled = enabled


def progress(iterable: Iterable[T], *, desc: str, total: int | None = None, unit: str = "it") -> Iterator[T]:
    """Wrap ``iterable`` in a tqdm bar on stderr labelled ``desc``."""
    disable = (not sys.stderr.isatty()) if _enabled is None else not _enabled
    return iter(tqdm(iterable, desc=desc, total=total, unit=unit, disable=disable,
                     dynamic_ncols=True, leave=False))
