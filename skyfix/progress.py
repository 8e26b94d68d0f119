"""Progress bars for long work, silenced by ``skyfix -q`` and when stderr is not a terminal.

:func:`progress` wraps an iterable, :func:`bar` gives a bar to advance by hand (work that
is not one loop: thread pools, simulation steps). Log lines go through :class:`LogHandler`
(the CLI installs it), which prints above a running bar instead of through it.
"""

from __future__ import annotations

import logging
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


def enabled_setting() -> bool | None:
    """The setting as :func:`set_enabled` left it (None: automatic)."""
    return _enabled


def enabled() -> bool:
    """Whether bars are shown now: the forced setting, else whether stderr is a terminal."""
    return sys.stderr.isatty() if _enabled is None else _enabled


def bar(*, desc: str, total: int | None = None, unit: str = "it", disable: bool = False) -> tqdm:
    """A tqdm bar on stderr labelled ``desc`` to advance with ``.update(n)`` and ``.close()``
    (or use as a context manager); ``disable=True`` hides it whatever the setting."""
    return tqdm(total=total, desc=desc, unit=unit, disable=disable or not enabled(), dynamic_ncols=True,
                leave=False, file=sys.stderr)


def progress(iterable: Iterable[T], *, desc: str, total: int | None = None, unit: str = "it") -> Iterator[T]:
    """Wrap ``iterable`` in a tqdm bar on stderr labelled ``desc``."""
    return iter(tqdm(iterable, desc=desc, total=total, unit=unit, disable=not enabled(),
                     dynamic_ncols=True, leave=False, file=sys.stderr))


class LogHandler(logging.Handler):
    """A handler that writes to the current ``sys.stderr`` through ``tqdm.write``, so a log
    line appears above a running progress bar and the bar is redrawn below it instead of
    being cut in two."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # logging must never raise into the caller
            self.handleError(record)
