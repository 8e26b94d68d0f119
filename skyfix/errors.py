"""The skyfix exception hierarchy.

Every error skyfix raises on purpose derives from :class:`SkyfixError`. Messages name
the offending input and say what was expected, so a user can fix the call without
reading skyfix's source.

``InputError`` also derives from ``ValueError`` and ``SkyfixTimeout`` from
``TimeoutError`` so that generic handlers in user code keep working.

Example:
    >>> from skyfix.geo import LocalFrame
    >>> try:
    ...     LocalFrame(95.0, 8.0)
    ... except ValueError as exc:  # an InputError is a ValueError too
    ...     print(type(exc).__name__, isinstance(exc, SkyfixError), exc)
    InputError True lat0_deg must be within [-90, 90] degrees, got [95.]
"""

from __future__ import annotations


class SkyfixError(Exception):
    """Base class of every exception raised by skyfix."""


class InputError(SkyfixError, ValueError):
    """An argument has the wrong type, shape, dtype or value (NaN, out of range...)."""


class GeometryError(InputError):
    """A geometric query has no valid answer, e.g. a ray at or above the horizon."""


class DataError(SkyfixError):
    """A file or external record is unusable: corrupt image, missing EXIF, bad log line."""


class ConfigurationError(SkyfixError):
    """A setting (of skyfix or of the autopilot) prevents the requested operation.

    The message names the setting and the value it needs.
    """


class LinkError(SkyfixError, ConnectionError):
    """A MAVLink (or other) link could not be opened or was lost."""


class SkyfixTimeout(SkyfixError, TimeoutError):
    """An operation did not complete within its time limit."""


class CommandRejected(SkyfixError):
    """The autopilot refused a command; ``reason`` carries its own explanation."""

    def __init__(self, message: str, *, command: str = "", result: int | None = None,
                 reason: str = "") -> None:
        super().__init__(message)
        self.command = command
        self.result = result
        self.reason = reason


class SafetyViolation(SkyfixError):
    """A setpoint or state violates the configured safety envelope (geofence, speed...)."""


class EstimationError(SkyfixError):
    """The estimator cannot produce a trustworthy answer (unconstrained, diverged...)."""


class NotAvailableError(SkyfixError):
    """A feature is not available here (optional dependency missing, not built yet)."""
