"""Swarm messages: typed, versioned, small, authenticated.

Every datagram is ``length || payload || HMAC-SHA256(swarm key, length || payload)`` with
``payload = msgpack(Envelope)`` and ``length`` its size in bytes (unsigned 16 bit, big-endian),
so a cut datagram is told from a forged one.
The envelope carries the wire version, the sender's id, its boot id (milliseconds of
UNIX time at start, so a restarted sender's sequence numbers are new), a per-sender
sequence number, the send time (UNIX seconds) and one typed body. Bodies are msgspec
Structs tagged by name, encoded as arrays (small and fast). Frames: positions WGS84
(ellipsoidal heights), covariances 3x3 row-major in the local ENU axes at the position, m^2.

:class:`SwarmCodec` signs outgoing messages and checks incoming ones in a fixed order:
size, length, HMAC, decoding, version, roster, self, age, replay. A message that fails any step
is dropped and counted under that reason (:attr:`SwarmCodec.dropped`), logged, never raised.
"""

from __future__ import annotations

import hashlib
import hmac
import itertools
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable
from pathlib import Path

import msgspec
import numpy as np

from skyfix.errors import InputError
from skyfix.types import GeoFix, RelativeObservation

log = logging.getLogger(__name__)

WIRE_VERSION = 1
TAG_BYTES = 32  # HMAC-SHA256
MAX_MESSAGE_BYTES = 2048  # every body fits in ~400 bytes; anything far larger is refused unread
MIN_KEY_BYTES = 16
REPLAY_WINDOW = 64  # sequence numbers older than the newest by less than this are accepted once
MAX_SENDERS = 64  # senders tracked without a roster: a key holder cannot grow the tables without bound
DROP_REASONS = ("oversized", "truncated", "forged", "malformed", "version", "unknown_sender", "self",
                "stale", "replayed")


class Heartbeat(msgspec.Struct, tag=True, array_like=True, frozen=True):
    """Sent at 2 Hz: the sender's health. ``fix_source`` the source fusion relies on ('gnss',
    'relative', 'none'...); ``sigma_h_m`` horizontal 1-sigma of its fused position, m;
    ``mavlink_ok`` whether its autopilot link is up."""

    health: str
    fix_source: str
    sigma_h_m: float
    mavlink_ok: bool
    n_peers: int = 0


class FusedEstimate(msgspec.Struct, tag=True, array_like=True, frozen=True):
    """The sender's fused position at ``time_s`` (UNIX s) with its ENU covariance, m^2 (9, row-major),
    and ENU velocity, m/s."""

    time_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    cov_enu_m2: tuple[float, ...]
    vel_enu_mps: tuple[float, float, float]
    sources: tuple[str, ...] = ()


class RelativeObs(msgspec.Struct, tag=True, array_like=True, frozen=True):
    """A camera observation of ``target_id`` by the sender (see :class:`skyfix.types.RelativeObservation`):
    unit bearing in ENU at the observer, range m, covariance m^2 (9), observer's own position."""

    target_id: str
    time_s: float
    bearing_enu: tuple[float, float, float]
    range_m: float
    cov_enu_m2: tuple[float, ...]
    observer_lat_deg: float
    observer_lon_deg: float
    observer_alt_m: float
    observer_cov_enu_m2: tuple[float, ...] = ()


# Help protocol (see :mod:`skyfix.crps.help_protocol`). Fields added after the first release
# are trailing and defaulted: msgspec fills a missing trailing field with its default and
# ignores unknown trailing ones, so old and new senders understand each other (wire version 1).
class HelpRequest(msgspec.Struct, tag=True, array_like=True, frozen=True):
    """The sender asks for (``active``) or cancels help with its position; carries its last good
    position (WGS84, ellipsoidal m) at ``last_good_time_s`` with horizontal 1-sigma ``sigma_h_m``,
    its ENU covariance there, m^2 (9, row-major; empty from old senders), and ``epoch``, which
    goes up by one with every new request of the sender (a repeat keeps it)."""

    active: bool
    last_good_time_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    sigma_h_m: float
    cov_enu_m2: tuple[float, ...] = ()
    epoch: int = 0


class HelpResponse(msgspec.Struct, tag=True, array_like=True, frozen=True):
    """A helper offers (``accept``) or declines ``requester_id``'s request ``epoch``; ``eta_s`` until it
    can observe; its position (WGS84, ellipsoidal m), battery share 0-1 and distance to the requester's
    last good fix, m. ``assigned`` True acknowledges a :class:`HelpAssign` naming the sender."""

    requester_id: str
    accept: bool
    eta_s: float = 0.0
    lat_deg: float = math.nan
    lon_deg: float = math.nan
    alt_m: float = math.nan
    battery_frac: float = math.nan
    distance_m: float = math.nan
    epoch: int = 0
    assigned: bool = False


class HelpAssign(msgspec.Struct, tag=True, array_like=True, frozen=True):
    """The requester (sender) assigns ``helper_ids`` to its request ``epoch``; repeated until each acknowledges."""

    helper_ids: tuple[str, ...]
    epoch: int


class HelpRelease(msgspec.Struct, tag=True, array_like=True, frozen=True):
    """The requester (sender) releases ``helper_ids`` (back to their missions); ``reason`` in words."""

    helper_ids: tuple[str, ...]
    epoch: int
    reason: str = ""


Body = Heartbeat | FusedEstimate | RelativeObs | HelpRequest | HelpResponse | HelpAssign | HelpRelease
TOPIC_OF = {Heartbeat: "heartbeat", FusedEstimate: "estimate", RelativeObs: "relative",
            HelpRequest: "help", HelpResponse: "help", HelpAssign: "help", HelpRelease: "help"}


class Envelope(msgspec.Struct, array_like=True, frozen=True):
    """What is signed: wire version, sender id, boot id (ms), sequence number, send time (UNIX s), body."""

    version: int
    sender: str
    boot_id: int
    seq: int
    time_s: float
    body: Body


def read_key(path: str | Path) -> bytes:
    """The swarm key from a file (its bytes, surrounding whitespace stripped), at least 16 bytes."""
    p = Path(path)
    try:
        key = p.read_bytes().strip()
    except OSError as exc:
        raise InputError(f"--swarm-key-file {p}: cannot read it ({exc.strerror})") from None
    if len(key) < MIN_KEY_BYTES:
        raise InputError(f"--swarm-key-file {p}: the key must have at least {MIN_KEY_BYTES} bytes, "
                         f"got {len(key)}")
    return key


class _Window:
    """Sequence numbers seen from one sender boot: the newest and a bitmask of the 64 before it."""

    __slots__ = ("boot_id", "newest", "mask")

    def __init__(self, boot_id: int, seq: int) -> None:
        self.boot_id, self.newest, self.mask = boot_id, seq, 1

    def accept(self, seq: int) -> bool:
        if seq > self.newest:
            shift = seq - self.newest
            self.mask = ((self.mask << shift) | 1) & ((1 << REPLAY_WINDOW) - 1) if shift < REPLAY_WINDOW else 1
            self.newest = seq
            return True
        age = self.newest - seq
        if age >= REPLAY_WINDOW or self.mask >> age & 1:
            return False
        self.mask |= 1 << age
        return True


class SwarmCodec:
    """Signs and checks swarm messages for ``sender_id`` with the shared ``key``.

    ``roster``: ids allowed to speak (None: anyone with the key); ``max_age_s``: a message
    whose send time differs from ``clock()`` by more is stale (clocks of the swarm are
    assumed GNSS/NTP-synchronised to well under that).
    """

    def __init__(self, sender_id: str, key: bytes, roster: Iterable[str] | None = None, *,
                 max_age_s: float = 2.0, max_bytes: int = MAX_MESSAGE_BYTES,
                 clock: Callable[[], float] = time.time) -> None:
        if len(key) < MIN_KEY_BYTES:
            raise InputError(f"swarm key must have at least {MIN_KEY_BYTES} bytes, got {len(key)}")
        self.sender_id = str(sender_id)
        self.roster = None if roster is None else frozenset(str(r) for r in roster)
        self.max_age_s, self.max_bytes, self.clock = float(max_age_s), int(max_bytes), clock
        self.boot_id = int(clock() * 1000)
        self._key = key
        self._seq = itertools.count(1)
        self._encoder = msgspec.msgpack.Encoder()
        self._decoder = msgspec.msgpack.Decoder(Envelope)
        self._windows: dict[str, _Window] = {}
        self.dropped: Counter[str] = Counter()
        self.accepted = 0

    def encode(self, body: Body) -> bytes:
        """Sign ``body`` into one datagram (next sequence number, stamped now)."""
        return self.seal(body)[1]

    def seal(self, body: Body) -> tuple[Envelope, bytes]:
        """The envelope of ``body`` (next sequence number, stamped now) and its signed datagram."""
        env = Envelope(WIRE_VERSION, self.sender_id, self.boot_id, next(self._seq), self.clock(), body)
        payload = self._encoder.encode(env)
        signed = len(payload).to_bytes(2, "big") + payload
        return env, signed + hmac.digest(self._key, signed, hashlib.sha256)

    def decode(self, data: bytes) -> Envelope | None:
        """The checked envelope of datagram ``data``, or None (dropped and counted)."""
        n = len(data)
        if n > self.max_bytes:
            return self._drop("oversized", f"{n} bytes > {self.max_bytes}")
        expected = 2 + int.from_bytes(data[:2], "big") + TAG_BYTES if n >= 2 else math.inf
        if n < expected:
            return self._drop("truncated", f"{n} bytes, the datagram says {expected}")
        if n > expected:
            return self._drop("malformed", f"{n} bytes, the datagram says {expected}")
        signed, tag = data[:-TAG_BYTES], data[-TAG_BYTES:]
        if not hmac.compare_digest(hmac.digest(self._key, signed, hashlib.sha256), tag):
            return self._drop("forged", "HMAC does not match the swarm key")
        try:
            env = self._decoder.decode(signed[2:])
        except (msgspec.DecodeError, msgspec.ValidationError) as exc:
            return self._drop("malformed", str(exc))
        if env.version != WIRE_VERSION:
            return self._drop("version", f"wire version {env.version}, expected {WIRE_VERSION}")
        if self.roster is not None and env.sender not in self.roster:
            return self._drop("unknown_sender", f"sender {env.sender!r} is not on the roster")
        if env.sender not in self._windows and len(self._windows) >= MAX_SENDERS:
            return self._drop("unknown_sender", f"sender {env.sender!r}: already {MAX_SENDERS} senders tracked")
        if env.sender == self.sender_id:
            return self._drop("self", "own message echoed back")
        if not math.isfinite(env.time_s) or abs(self.clock() - env.time_s) > self.max_age_s:
            return self._drop("stale", f"from {env.sender!r} sent {self.clock() - env.time_s:.3f} s ago")
        if not self._fresh(env):
            return self._drop("replayed", f"from {env.sender!r} boot {env.boot_id} seq {env.seq}")
        self.accepted += 1
        return env

    def _fresh(self, env: Envelope) -> bool:
        win = self._windows.get(env.sender)
        if win is None or env.boot_id > win.boot_id:
            self._windows[env.sender] = _Window(env.boot_id, env.seq)
            return True
        return env.boot_id == win.boot_id and win.accept(env.seq)

    def _drop(self, reason: str, detail: str) -> None:
        self.dropped[reason] += 1
        count = self.dropped[reason]
        if count <= 5 or count % 1000 == 0:  # every drop is counted; the log is not flooded
            log.warning("swarm message dropped (%s, %d so far): %s", reason, count, detail)
        return None


# -- conversions to and from the measurement types ----------------------------------------------
def _flat(cov) -> tuple[float, ...]:
    return tuple(float(x) for x in np.asarray(cov, dtype=float).reshape(9))


def estimate_message(est) -> FusedEstimate:
    """A :class:`skyfix.fusion.Estimate` as a message."""
    return FusedEstimate(float(est.time_s), est.lat_deg, est.lon_deg, est.alt_m, _flat(est.cov_enu_m2),
                         tuple(float(v) for v in est.vel_enu_mps), tuple(est.sources))


def estimate_fix(msg: FusedEstimate, sender: str) -> GeoFix:
    """A peer's estimate as a :class:`GeoFix` (raises InputError on non-physical values)."""
    return GeoFix(msg.lat_deg, msg.lon_deg, msg.alt_m, np.reshape(msg.cov_enu_m2, (3, 3)), msg.time_s,
                  f"peer:{sender}")


def relative_message(obs: RelativeObservation) -> RelativeObs:
    """A :class:`RelativeObservation` made by this drone, as a message."""
    return RelativeObs(obs.target_id, obs.time_s, tuple(float(v) for v in obs.bearing_unit_enu), obs.range_m,
                       _flat(obs.cov_enu_m2), obs.observer_lat_deg, obs.observer_lon_deg, obs.observer_alt_m,
                       () if obs.observer_cov_enu_m2 is None else _flat(obs.observer_cov_enu_m2))


def relative_observation(msg: RelativeObs, sender: str) -> RelativeObservation:
    """A peer's observation back as a :class:`RelativeObservation` (InputError when invalid)."""
    cov_obs = np.reshape(msg.observer_cov_enu_m2, (3, 3)) if len(msg.observer_cov_enu_m2) == 9 else None
    return RelativeObservation(sender, msg.target_id, msg.time_s, np.asarray(msg.bearing_enu), msg.range_m,
                               np.reshape(msg.cov_enu_m2, (3, 3)), msg.observer_lat_deg, msg.observer_lon_deg,
                               msg.observer_alt_m, cov_obs)


def to_builtins(env: Envelope) -> dict:
    """JSON-ready form of an envelope (for the log and the live view)."""
    body = {name: msgspec.to_builtins(getattr(env.body, name)) for name in env.body.__struct_fields__}
    return {"version": env.version, "sender": env.sender, "boot_id": env.boot_id, "seq": env.seq,
            "time_s": env.time_s, "type": type(env.body).__name__, "body": body}
