"""The append-only measurement log: every input the fusion engine is given, replayable.

Format ``skyfix.fusion.log`` version 1, JSON lines (UTF-8, one object per line):

- line 1, the header: ``{"format": "skyfix.fusion.log", "version": 1, "origin": [lat, lon,
  alt], "lag_s": ..., "config": {...FusionConfig...}, "created_utc": "..."}``;
- then one record per engine call, in call order: ``{"op": "gnss" | "velocity" |
  "altitude" | "fix" | "relative", "args": {...the add_<op> keyword arguments...}}``,
  ``{"op": "update"}`` whenever the smoother ran (replay runs it at the same points, so
  it reproduces the estimates exactly), ``{"op": "lag", "args": {"lag_s": s}}`` when the
  engine's lag changed (``FusionEngine.set_lag``), and optionally ``{"op": "truth", "drone": id,
  "t": s, "lat": deg, "lon": deg, "alt": m}`` written by simulators (ignored by the
  engine, plotted by ``skyfix fusion replay``).

Floats are written with Python's shortest round-trip repr, so replay sees the same bits.
Lines are flushed as written and fsync'ed at most every ``fsync_s`` seconds; a reader
skips a truncated last line (power cut) and records of unknown ops with a warning.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from skyfix.errors import DataError, InputError
from skyfix.jsonfile import json_safe
from skyfix.types import GeoFix, RelativeObservation

log = logging.getLogger(__name__)

LOG_FORMAT = "skyfix.fusion.log"
LOG_VERSION = 1
INPUT_OPS = ("gnss", "velocity", "altitude", "fix", "relative")
KNOWN_OPS = (*INPUT_OPS, "update", "lag", "truth")


def _plain(value):
    """JSON-ready copy of an argument (arrays to lists, measurement types to dicts)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, RelativeObservation):
        return {"type": "RelativeObservation", "observer_id": value.observer_id, "target_id": value.target_id,
                "time_s": value.time_s, "bearing_unit_enu": value.bearing_unit_enu.tolist(), "range_m": value.range_m,
                "cov_enu_m2": value.cov_enu_m2.tolist(), "observer_lat_deg": value.observer_lat_deg,
                "observer_lon_deg": value.observer_lon_deg, "observer_alt_m": value.observer_alt_m,
                "observer_cov_enu_m2": None if value.observer_cov_enu_m2 is None else value.observer_cov_enu_m2.tolist()}
    if isinstance(value, GeoFix):
        return {"type": "GeoFix", "lat_deg": value.lat_deg, "lon_deg": value.lon_deg, "alt_m": value.alt_m,
                "cov_enu_m2": value.cov_enu_m2.tolist(), "time_s": value.time_s, "source_id": value.source_id}
    return value


def _revive(value):
    """Inverse of :func:`_plain` for the measurement types (NaN observer fields were written as null)."""
    if isinstance(value, dict) and value.get("type") == "RelativeObservation":
        fields = {k: v for k, v in value.items() if k != "type"}
        if "bearing_enu" in fields:  # logs written before the field was renamed (issue 22)
            fields["bearing_unit_enu"] = fields.pop("bearing_enu")
        for name in ("observer_lat_deg", "observer_lon_deg", "observer_alt_m"):
            if fields.get(name) is None:
                fields[name] = float("nan")
        return RelativeObservation(**fields)
    if isinstance(value, dict) and value.get("type") == "GeoFix":
        return GeoFix(**{k: v for k, v in value.items() if k != "type"})
    return value


class MeasurementLog:
    """Writer of a measurement log; one per engine. Use as a context manager or call close()."""

    def __init__(self, path: str | Path, header: dict, fsync_s: float = 1.0) -> None:
        self.path = Path(path)
        if self.path.exists() and self.path.stat().st_size > 0:
            raise InputError(f"measurement log {self.path} already exists; the log is append-only per engine, "
                             "choose a new file")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - lives as long as the engine
        self._fsync_s = fsync_s
        self._last_sync = time.monotonic()
        self.n_records = 0
        self._write({"format": LOG_FORMAT, "version": LOG_VERSION, **header,
                     "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")})

    def _write(self, obj: dict) -> None:
        try:  # nearly every record is finite: json_safe's copy only when one is not (1.6 s of 60 000 records)
            text = json.dumps(obj, separators=(",", ":"), allow_nan=False)
        except ValueError:
            text = json.dumps(json_safe(obj), separators=(",", ":"), allow_nan=False)
        self._file.write(text + "\n")
        self._file.flush()
        now = time.monotonic()
        if now - self._last_sync >= self._fsync_s:
            os.fsync(self._file.fileno())
            self._last_sync = now

    def record(self, op: str, args: dict | None = None) -> None:
        """Append one engine call."""
        obj = {"op": op}
        if args is not None:
            obj["args"] = {k: _plain(v) for k, v in args.items()}
        self._write(obj)
        self.n_records += 1

    def truth(self, drone_id: str, time_s: float, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """Append a ground-truth position (simulators), for plots; the engine ignores it."""
        self._write({"op": "truth", "drone": str(drone_id), "t": float(time_s), "lat": float(lat_deg),
                     "lon": float(lon_deg), "alt": float(alt_m)})

    def close(self) -> None:
        if not self._file.closed:
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()

    def __enter__(self) -> MeasurementLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_log(path: str | Path) -> tuple[dict, Iterator[dict]]:
    """Open a measurement log: (header, iterator over records with ``args`` revived).

    Example:
        >>> import tempfile
        >>> from skyfix.fusion import FusionEngine
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     with FusionEngine((47.0, 8.0, 400.0), log_path=f"{tmp}/run.jsonl") as engine:
        ...         engine.add_gnss("A", 0.0, 47.0, 8.0, 400.0, h_sigma_m=1.5, v_sigma_m=2.5)
        ...         engine.update()
        ...     header, records = read_log(f"{tmp}/run.jsonl")
        ...     header["origin"], [r["op"] for r in records]
        ([47.0, 8.0, 400.0], ['gnss', 'update'])
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"measurement log {path} does not exist")
    with open(path, encoding="utf-8") as f:
        first = f.readline()
    try:
        header = json.loads(first)
    except json.JSONDecodeError:
        raise DataError(f"{path}: first line is not a JSON header; expected a {LOG_FORMAT} file") from None
    if not isinstance(header, dict) or header.get("format") != LOG_FORMAT:
        raise DataError(f"{path}: not a {LOG_FORMAT} file (header format {header.get('format')!r})"
                        if isinstance(header, dict) else f"{path}: header is not a JSON object")
    if header.get("version") != LOG_VERSION:
        raise DataError(f"{path}: log version {header.get('version')!r}; this skyfix reads version {LOG_VERSION}")
    return header, _records(path)


def _records(path: Path) -> Iterator[dict]:
    with open(path, encoding="utf-8") as f:
        f.readline()
        for lineno, line in enumerate(f, start=2):
            if not line.endswith("\n"):
                log.warning("%s:%d: truncated last line skipped", path, lineno)
                return
            try:
                obj = json.loads(line)
            except json.JSONDecodeError:
                log.warning("%s:%d: not JSON, skipped", path, lineno)
                continue
            op = obj.get("op") if isinstance(obj, dict) else None
            if op not in KNOWN_OPS:
                log.warning("%s:%d: unknown op %r skipped", path, lineno, op)
                continue
            if "args" in obj:
                obj["args"] = {k: _revive(v) for k, v in obj["args"].items()}
            obj["line"] = lineno
            yield obj
