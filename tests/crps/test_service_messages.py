"""Swarm messages: round trips, and every kind of bad datagram dropped and counted under its reason."""

from __future__ import annotations

import hashlib
import hmac

import numpy as np
import pytest

from skyfix.crps.messages import (
    MAX_MESSAGE_BYTES,
    FusedEstimate,
    Heartbeat,
    HelpRequest,
    RelativeObs,
    SwarmCodec,
    read_key,
    relative_message,
    relative_observation,
)
from skyfix.errors import InputError
from skyfix.types import RelativeObservation

KEY = b"0123456789abcdef0123456789abcdef"


class Clock:
    def __init__(self, t: float = 1.7e9) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def pair(roster=("a", "b"), clock=None):
    clock = clock or Clock()
    return SwarmCodec("a", KEY, roster, clock=clock), SwarmCodec("b", KEY, roster, clock=clock), clock


def test_round_trip_of_every_body_and_small_size():
    a, b, _ = pair()
    bodies = [Heartbeat("ok", "gnss", 0.8, True, 2),
              FusedEstimate(1.7e9, 46.5, 6.6, 420.0, tuple(np.eye(3).ravel().tolist()), (1.0, 2.0, 0.0), ("gnss", "velocity")),
              RelativeObs("c", 1.7e9, (1.0, 0.0, 0.0), 25.0, tuple(np.eye(3).ravel().tolist()), 46.5, 6.6, 420.0),
              HelpRequest(True, 1.7e9 - 3, 46.5, 6.6, 420.0, 1.5)]
    for body in bodies:
        data = a.encode(body)
        assert len(data) < 400  # small: a few hundred bytes at most
        env = b.decode(data)
        assert env is not None and env.body == body and env.sender == "a"
    assert b.accepted == len(bodies) and not b.dropped
    seqs = [b.decode(a.encode(bodies[0])).seq for _ in range(3)]
    assert seqs == [5, 6, 7]  # per-sender sequence numbers go up by one


def test_relative_observation_survives_the_wire():
    obs = RelativeObservation("a", "c", 12.5, np.array([0.6, 0.8, 0.0]), 30.0, np.diag([1.0, 2.0, 3.0]),
                              46.5, 6.6, 420.0, np.eye(3) * 0.25)
    back = relative_observation(relative_message(obs), "a")
    assert back.target_id == "c" and back.range_m == 30.0
    np.testing.assert_array_equal(back.cov_enu_m2, obs.cov_enu_m2)
    np.testing.assert_array_equal(back.observer_cov_enu_m2, obs.observer_cov_enu_m2)


def test_bad_datagrams_are_dropped_and_counted():
    a, b, clock = pair()
    good = a.encode(Heartbeat("ok", "gnss", 1.0, True))
    assert b.decode(good) is not None
    assert b.decode(good) is None                                    # the same datagram again
    forged = SwarmCodec("a", b"another key of the same length!!", clock=clock).encode(Heartbeat("ok", "gnss", 1, True))
    assert b.decode(forged) is None
    assert b.decode(good[:-5]) is None                               # truncated: the tag no longer matches
    assert b.decode(good[:20]) is None                               # shorter than a tag
    rng = np.random.default_rng(1)
    for _ in range(50):
        assert b.decode(rng.bytes(int(rng.integers(0, 300)))) is None
    assert b.decode(b"x" * (MAX_MESSAGE_BYTES + 1)) is None
    flipped = bytearray(a.encode(Heartbeat("ok", "gnss", 1.0, True)))
    flipped[10] ^= 0x01
    assert b.decode(bytes(flipped)) is None
    garbage = b"\x00\x04\x93\x01\xa1a"
    assert b.decode(garbage + hmac.digest(KEY, garbage, hashlib.sha256)) is None  # right key, not an envelope
    assert b.decode(good + b"\x00") is None                        # longer than it says
    assert b.dropped["replayed"] == 1 and b.dropped["oversized"] == 1
    assert b.dropped["forged"] >= 2 and b.dropped["truncated"] >= 2 and b.dropped["malformed"] >= 2
    assert sum(b.dropped.values()) == 50 + 8  # every bad datagram counted once
    assert b.accepted == 1


def test_stale_unknown_sender_and_restart():
    a, b, clock = pair()
    old = a.encode(Heartbeat("ok", "gnss", 1.0, True))
    clock.t += 2.5
    assert b.decode(old) is None and b.dropped["stale"] == 1
    stranger = SwarmCodec("z", KEY, clock=clock)
    assert b.decode(stranger.encode(Heartbeat("ok", "gnss", 1.0, True))) is None
    assert b.dropped["unknown_sender"] == 1
    assert b.decode(a.encode(Heartbeat("ok", "gnss", 1.0, True))) is not None
    # a restarted sender begins its sequence again under a new boot id and is heard
    clock.t += 1.0
    restarted = SwarmCodec("a", KEY, clock=clock)
    assert b.decode(restarted.encode(Heartbeat("ok", "gnss", 1.0, True))) is not None
    # ... while the old boot's messages are refused from then on
    assert b.decode(a.encode(Heartbeat("ok", "gnss", 1.0, True))) is None


def test_out_of_order_within_the_window_is_accepted_once():
    a, b, _ = pair()
    msgs = [a.encode(Heartbeat("ok", "gnss", 1.0, True)) for _ in range(5)]
    order = [0, 2, 1, 4, 3, 3, 1]
    results = [b.decode(msgs[i]) is not None for i in order]
    assert results == [True, True, True, True, True, False, False]


def test_key_file(tmp_path):
    (tmp_path / "k").write_bytes(KEY + b"\n")
    assert read_key(tmp_path / "k") == KEY
    (tmp_path / "short").write_text("abc")
    with pytest.raises(InputError, match="at least 16 bytes"):
        read_key(tmp_path / "short")
    with pytest.raises(InputError, match="cannot read"):
        read_key(tmp_path / "missing")


def test_without_a_roster_the_sender_table_is_bounded():
    from skyfix.crps.messages import MAX_SENDERS

    clock = Clock()
    rx = SwarmCodec("rx", KEY, clock=clock)
    results = [rx.decode(SwarmCodec(f"s{i}", KEY, clock=clock).encode(Heartbeat("ok", "gnss", 1.0, True))) is not None
               for i in range(MAX_SENDERS + 3)]
    assert results == [True] * MAX_SENDERS + [False] * 3 and rx.dropped["unknown_sender"] == 3
