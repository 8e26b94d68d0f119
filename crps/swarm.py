"""Who is in the swarm: the peer table (joined, lost, rejoined) and ``skyfix swarm status``.

A peer is *joined* by its first authenticated message, *lost* when nothing has been heard
from it for ``lost_after_s`` (1.5 s: a heartbeat goes out every 0.5 s and estimates at
10 Hz, so three heartbeats in a row are missing) and *rejoined* by its next message.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

from skyfix.crps.messages import Envelope, FusedEstimate, Heartbeat

LOST_AFTER_S = 1.5


@dataclass
class Peer:
    """What is known of one peer; times are UNIX seconds on this drone's clock."""

    drone_id: str
    first_heard_s: float
    last_heard_s: float
    lost: bool = False
    fix_source: str = ""
    health: str = ""
    sigma_h_m: float = math.nan
    lat_deg: float = math.nan
    lon_deg: float = math.nan
    alt_m: float = math.nan
    mavlink_ok: bool = False
    n_messages: int = 0
    rejoins: int = 0


@dataclass
class PeerEvent:
    """``kind``: 'joined', 'lost' or 'rejoined', at ``time_s`` (UNIX s)."""

    kind: str
    drone_id: str
    time_s: float


@dataclass
class PeerTable:
    """Thread-safe table of the peers heard; :meth:`heard` on every accepted message, :meth:`check`
    periodically (it returns the peers lost since the last call)."""

    lost_after_s: float = LOST_AFTER_S
    peers: dict[str, Peer] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def heard(self, env: Envelope, now_s: float | None = None) -> PeerEvent | None:
        """Account for one accepted message; a 'joined'/'rejoined' event when that is what it means."""
        now = time.time() if now_s is None else now_s
        event = None
        with self._lock:
            peer = self.peers.get(env.sender)
            if peer is None:
                peer = self.peers[env.sender] = Peer(env.sender, now, now)
                event = PeerEvent("joined", env.sender, now)
            elif peer.lost:
                peer.lost = False
                peer.rejoins += 1
                event = PeerEvent("rejoined", env.sender, now)
            peer.last_heard_s = now
            peer.n_messages += 1
            body = env.body
            if isinstance(body, Heartbeat):
                peer.health, peer.fix_source = body.health, body.fix_source
                peer.sigma_h_m, peer.mavlink_ok = body.sigma_h_m, body.mavlink_ok
            elif isinstance(body, FusedEstimate):
                peer.lat_deg, peer.lon_deg, peer.alt_m = body.lat_deg, body.lon_deg, body.alt_m
        return event

    def check(self, now_s: float | None = None) -> list[PeerEvent]:
        """Mark peers silent for longer than ``lost_after_s`` as lost; the new 'lost' events."""
        now = time.time() if now_s is None else now_s
        events = []
        with self._lock:
            for peer in self.peers.values():
                if not peer.lost and now - peer.last_heard_s > self.lost_after_s:
                    peer.lost = True
                    events.append(PeerEvent("lost", peer.drone_id, now))
        return events

    def live(self) -> list[str]:
        """Ids of the peers not lost."""
        with self._lock:
            return sorted(p.drone_id for p in self.peers.values() if not p.lost)

    def snapshot(self) -> list[Peer]:
        """A copy of every peer, sorted by id."""
        with self._lock:
            return [Peer(**vars(p)) for p in sorted(self.peers.values(), key=lambda p: p.drone_id)]


def status_table(peers: list[Peer], now_s: float) -> str:
    """The ``skyfix swarm status`` table: id, state, fix source, health, sigma, last heard."""
    rows = [("id", "state", "fix", "health", "sigma_m", "mavlink", "last_heard_s", "lat_deg", "lon_deg")]
    for p in peers:
        rows.append((p.drone_id, "LOST" if p.lost else "ok", p.fix_source or "-", p.health or "-",
                     f"{p.sigma_h_m:.2f}" if math.isfinite(p.sigma_h_m) else "-",
                     "up" if p.mavlink_ok else "down", f"{now_s - p.last_heard_s:.1f}",
                     f"{p.lat_deg:.7f}" if math.isfinite(p.lat_deg) else "-",
                     f"{p.lon_deg:.7f}" if math.isfinite(p.lon_deg) else "-"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows)


def register_status(subparsers) -> None:
    """Add ``skyfix swarm status``."""
    from pathlib import Path

    sw = subparsers.add_parser("swarm", help="look at a running swarm (skyfix serve processes)",
                               description="Listen to a swarm of skyfix serve processes.")
    sub = sw.add_subparsers(dest="swarm_command", metavar="ACTION", title="actions")
    sw.set_defaults(func=lambda args: (sw.print_help(), 2)[1])
    st = sub.add_parser("status", help="table of the drones heard: id, fix source, health, sigma, last heard",
                        description="Join the swarm as a silent listener for --listen-s seconds and print "
                                    "one row per drone heard (messages are verified with the swarm key).")
    st.add_argument("--swarm", required=True, metavar="ENDPOINTS",
                    help="zenoh endpoints of the drones, comma-separated (tcp/HOST:PORT)")
    st.add_argument("--swarm-key-file", required=True, type=Path, metavar="FILE", help="the swarm key")
    st.add_argument("--swarm-name", default="skyfix", help="swarm name (default skyfix)")
    st.add_argument("--listen-s", type=float, default=2.0, help="how long to listen, s (default 2)")
    st.add_argument("--json", action="store_true", help="print JSON instead of a table")
    st.set_defaults(func=run_status)


def run_status(args) -> int:
    """``skyfix swarm status``: exit 0 when at least one drone was heard, 1 when none, 2 on bad input."""
    import json
    import sys

    from skyfix.crps.messages import SwarmCodec, read_key
    from skyfix.crps.transport import Endpoints, ZenohTransport, check_name
    from skyfix.errors import InputError, LinkError

    try:
        check_name("--swarm-name", args.swarm_name)
        endpoints = Endpoints.parse(args.swarm)
        codec = SwarmCodec(f"status-{int(time.time() * 1000) % 100000}", read_key(args.swarm_key_file))
        transport = ZenohTransport(args.swarm_name, codec.sender_id, endpoints)
    except (InputError, LinkError) as exc:
        sys.stderr.write(f"skyfix swarm status: error: {exc}\n")
        return 2
    table = PeerTable()

    def on_datagram(_key: str, data: bytes) -> None:
        env = codec.decode(data)
        if env is not None:
            table.heard(env)

    transport.subscribe(on_datagram)
    time.sleep(max(0.1, float(args.listen_s)))
    transport.close()
    now = time.time()
    table.check(now)
    peers = table.snapshot()
    if args.json:
        print(json.dumps([{**vars(p), "last_heard_age_s": now - p.last_heard_s} for p in peers],
                         default=lambda x: None if x != x else x))
    else:
        print(status_table(peers, now) if peers else "no drone heard")
        dropped = {k: v for k, v in codec.dropped.items() if v}
        if dropped:
            print(f"dropped messages: {dropped}")
    return 0 if peers else 1
