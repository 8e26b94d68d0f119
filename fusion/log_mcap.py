"""The measurement log in MCAP: crash-tolerant, one topic per stream, readable in Foxglove.

:class:`McapLog` writes the same records as the JSON-lines :class:`skyfix.fusion.log.MeasurementLog`
(every engine input, ``update`` points, optional truth) on topics ``/fusion/<op>``, JSON
encoded with a JSON schema each; the log header (origin, lag, configuration) is the MCAP
metadata record ``skyfix.fusion.log``. Other layers add their own topics through
:meth:`McapLog.channel` (JSON with a schema, or any encoding with its schema, e.g.
Foxglove's protobuf ``LocationFix``); a log may be opened before the header is known
(:meth:`McapLog.set_header`). Message ``log_time`` is the UNIX time of writing (ns),
``publish_time`` the measurement's own time where it has one.

Durability: records are written unchunked (each record goes to the file as it is, so the
writer holds nothing per record and its memory stays flat over hours of flight; the price
is no compression and no index: ~130 bytes per record, readers scan) and the file buffer is
flushed at least every ``flush_s`` (default 50 ms) by a background thread, so a killed
process loses at most the last ``flush_s`` of records; the file is fsync'ed about every
second. :func:`read_mcap_log` and :func:`iter_messages` read the records in order and stop
quietly at a tail cut off by a crash (no summary, a half-written record).
"""

from __future__ import annotations

import json
import logging
import os
import struct
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import msgspec
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import Writer
from zstandard import ZstdError

from skyfix.errors import DataError, InputError
from skyfix.fusion.log import KNOWN_OPS, LOG_FORMAT, LOG_VERSION, _plain, _revive

log = logging.getLogger(__name__)

_ANY_OBJECT = {"type": "object"}
_OP_SCHEMA = {"type": "object", "properties": {"op": {"type": "string"}, "args": {"type": "object"}},
              "required": ["op"]}
_TRUTH_SCHEMA = {"type": "object", "properties": {
    "op": {"const": "truth"}, "drone": {"type": "string"}, "t": {"type": "number", "description": "s"},
    "lat": {"type": "number", "description": "deg"}, "lon": {"type": "number", "description": "deg"},
    "alt": {"type": "number", "description": "m, ellipsoidal"}}}


# msgspec writes NaN as null (as the JSON-lines log does) and is several times faster than json here;
# numpy arrays and measurement types go through the JSON-lines log's own conversion.
_json = msgspec.json.Encoder(enc_hook=_plain).encode


class McapLog:
    """An MCAP measurement log (and other topics); thread-safe; use as a context manager or close()."""

    def __init__(self, path: str | Path, header: dict | None, *, flush_s: float = 0.05, fsync_s: float = 1.0
                 ) -> None:
        self.path = Path(path)
        if self.path.exists() and self.path.stat().st_size > 0:
            raise InputError(f"log {self.path} already exists; choose a new file")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - lives as long as the log
        # unchunked: the mcap writer keeps an index entry per chunk for the summary, which at one chunk
        # per flush (20 a second) grows by ~30 MB an hour; unchunked records keep nothing
        self._writer = Writer(self._file, use_chunking=False)
        self._writer.start(profile="", library="skyfix")
        self._lock = threading.Lock()
        self.has_header = False
        if header is not None:
            self.set_header(header)
        self._channels: dict[str, int] = {}
        self._seq = 0
        self._dirty = False
        self.n_records = 0
        self._fsync_s, self._last_sync = fsync_s, time.monotonic()
        self._flush_s = flush_s
        self._closed = threading.Event()
        self._writer.flush()
        self._flusher = threading.Thread(target=self._flush_loop, daemon=True, name="skyfix-mcap-flush")
        self._flusher.start()

    def set_header(self, header: dict) -> None:
        """Write the measurement-log header (origin, lag, configuration) before the first engine record;
        a log opened before the origin was known gets it here."""
        with self._lock:
            if self.has_header:
                raise InputError(f"log {self.path} already has its header")
            self._writer.add_metadata(LOG_FORMAT, {"header": json.dumps(
                {"format": LOG_FORMAT, "version": LOG_VERSION, **header})})
            self.has_header = True

    # -- channels and writing ---------------------------------------------------------------
    def channel(self, topic: str, schema_name: str, schema: dict | bytes = _ANY_OBJECT, *,
                encoding: str = "json", schema_encoding: str = "jsonschema") -> int:
        """Register ``topic`` (once) with its schema; returns the channel id."""
        with self._lock:
            if topic not in self._channels:
                data = schema if isinstance(schema, bytes) else json.dumps(schema).encode()
                sid = self._writer.register_schema(schema_name, schema_encoding, data)
                self._channels[topic] = self._writer.register_channel(topic, encoding, sid)
            return self._channels[topic]

    def write(self, topic: str, obj: dict | bytes, time_s: float | None = None) -> None:
        """One message on a registered ``topic``: a JSON-ready dict (NaN written as null) or encoded bytes;
        ``time_s`` its own time (UNIX s), default now."""
        now_ns = time.time_ns()
        data = obj if isinstance(obj, bytes) else _json(obj)
        pub_ns = now_ns if time_s is None else int(time_s * 1e9)
        with self._lock:
            if self._closed.is_set():
                return
            self._seq += 1
            self._writer.add_message(self._channels[topic], now_ns, data, pub_ns, self._seq)
            self._dirty = True
            self.n_records += 1

    def record(self, op: str, args: dict | None = None) -> None:
        """One engine call, as :meth:`MeasurementLog.record`."""
        topic = f"/fusion/{op}"
        if topic not in self._channels:
            self.channel(topic, f"skyfix.fusion.{op}", _OP_SCHEMA)
        # measurement types by the JSON-lines log's conversion (tagged with their type, for replay)
        obj = {"op": op} if args is None else {"op": op, "args": {k: _plain(v) for k, v in args.items()}}
        self.write(topic, obj, args.get("time_s") if args else None)

    def truth(self, drone_id: str, time_s: float, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """A ground-truth position (simulators), for plots; the engine ignores it."""
        if "/fusion/truth" not in self._channels:
            self.channel("/fusion/truth", "skyfix.fusion.truth", _TRUTH_SCHEMA)
        self.write("/fusion/truth", {"op": "truth", "drone": str(drone_id), "t": float(time_s),
                                     "lat": float(lat_deg), "lon": float(lon_deg), "alt": float(alt_m)})

    # -- durability ---------------------------------------------------------------------------
    def flush(self) -> None:
        """Write what is buffered to the file now (fsync about every ``fsync_s``)."""
        with self._lock:
            if self._closed.is_set() or not self._dirty:
                return
            self._writer.flush()
            self._dirty = False
            now = time.monotonic()
            if now - self._last_sync >= self._fsync_s:
                os.fsync(self._file.fileno())
                self._last_sync = now

    def _flush_loop(self) -> None:
        while not self._closed.wait(self._flush_s):
            try:
                self.flush()
            except (OSError, ValueError) as exc:  # disk full, file closed under us: keep the service alive
                log.error("log %s: flush failed: %s", self.path, exc)

    def close(self) -> None:
        """Finish the file (summary and index) and close it."""
        with self._lock:
            if self._closed.is_set():
                return
            self._closed.set()
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
        self._flusher.join(timeout=1.0)

    def __enter__(self) -> McapLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- reading -----------------------------------------------------------------------------------
def _stream(path: Path) -> Iterator[object]:
    """Every record of the file in order, stopping quietly where a crash cut the tail off."""
    with open(path, "rb") as f:
        try:
            yield from StreamReader(f, skip_magic=False).records
        # a crash-cut tail surfaces as whichever decoding step ran out of bytes
        except (McapError, EOFError, ValueError, KeyError, RuntimeError, struct.error, ZstdError) as exc:
            log.info("%s: log ends in an incomplete record (%s: %s); read up to there",
                        path, type(exc).__name__, exc)


def iter_messages(path: str | Path, topics: Iterable[str] | None = None
                  ) -> Iterator[tuple[str, int, int, bytes]]:
    """(topic, log_time_ns, publish_time_ns, data) of every message on ``topics`` (all by default).

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     with McapLog(f"{tmp}/run.mcap", {"origin": [47.0, 8.0, 400.0], "lag_s": 2.0}) as mcap_log:
        ...         mcap_log.record("update")
        ...     [topic for topic, *_ in iter_messages(f"{tmp}/run.mcap")]
        ['/fusion/update']
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"log {path} does not exist")
    wanted = None if topics is None else set(topics)
    channels: dict[int, str] = {}
    try:
        for rec in _stream(path):
            if isinstance(rec, Channel):
                channels[rec.id] = rec.topic
            elif isinstance(rec, Message):
                topic = channels.get(rec.channel_id)
                if topic is not None and (wanted is None or topic in wanted):
                    yield topic, rec.log_time, rec.publish_time, rec.data
    except McapError as exc:  # the start of the file is not MCAP at all
        raise DataError(f"{path}: not an MCAP file ({exc})") from None


def read_header(path: str | Path) -> dict:
    """The ``skyfix.fusion.log`` header of an MCAP log (DataError if it has none)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"log {path} does not exist")
    try:
        for rec in _stream(path):
            if isinstance(rec, Metadata) and rec.name == LOG_FORMAT:
                header = json.loads(rec.metadata["header"])
                if header.get("version") != LOG_VERSION:
                    raise DataError(f"{path}: log version {header.get('version')!r}; this skyfix reads "
                                    f"version {LOG_VERSION}")
                return header
            if isinstance(rec, Channel) and rec.topic.startswith("/fusion/"):
                break  # the header precedes every engine record
    except McapError as exc:
        raise DataError(f"{path}: not an MCAP file ({exc})") from None
    raise DataError(f"{path}: MCAP file without a {LOG_FORMAT} header; not a skyfix measurement log")


def read_mcap_log(path: str | Path) -> tuple[dict, Iterator[dict]]:
    """Open an MCAP measurement log like :func:`skyfix.fusion.log.read_log`: (header, records in order,
    ``args`` revived, ``line`` the message's index).

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     with McapLog(f"{tmp}/run.mcap", {"origin": [47.0, 8.0, 400.0], "lag_s": 2.0}) as mcap_log:
        ...         mcap_log.record("update")
        ...     header, records = read_mcap_log(f"{tmp}/run.mcap")
        ...     header["lag_s"], [r["op"] for r in records]
        (2.0, ['update'])
    """
    header = read_header(path)
    return header, _records(Path(path))


def _records(path: Path) -> Iterator[dict]:
    for index, (topic, _, _, data) in enumerate(iter_messages(path), start=1):
        if not topic.startswith("/fusion/"):
            continue
        try:
            obj = json.loads(data)
        except json.JSONDecodeError:
            log.warning("%s: message %d on %s is not JSON, skipped", path, index, topic)
            continue
        if not isinstance(obj, dict) or obj.get("op") not in KNOWN_OPS:
            log.warning("%s: message %d: unknown op skipped", path, index)
            continue
        if "args" in obj:
            obj["args"] = {k: _revive(v) for k, v in obj["args"].items()}
        obj["line"] = index
        yield obj
