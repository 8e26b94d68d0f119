"""One drone's part in GPS-loss recovery on the swarm: both roles bound to a codec and a transport.

The service (or the simulator) calls :meth:`HelpAgent.receive` for every accepted envelope
and :meth:`HelpAgent.step` from its main loop (a few Hz); the agent signs and publishes the
help messages itself and returns the decisions. A drone asking for help never offers help.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from skyfix.crps.help_protocol import HelpConfig, HelperStatus
from skyfix.crps.messages import TOPIC_OF, Body, Envelope, SwarmCodec
from skyfix.crps.roles import Decision, HelperDecision, HelperRole, RequesterConfig, RequesterRole
from skyfix.crps.swarm import PeerTable
from skyfix.crps.transport import Transport
from skyfix.crps.vantage import VantageConfig
from skyfix.fusion.estimate import Estimate
from skyfix.fusion.health import SourceHealth
from skyfix.geo import LocalFrame


@dataclass(frozen=True)
class AgentDecisions:
    """What the drone should do now: as a requester and as a helper (at most one is not idle)."""

    requester: Decision
    helper: HelperDecision


class HelpAgent:
    """The help roles of ``codec.sender_id``, publishing on ``transport``; ``peers`` is the service's
    peer table (its lost signal replaces quiet helpers); ``home`` (lat_deg, lon_deg, alt_m)."""

    def __init__(self, codec: SwarmCodec, transport: Transport, peers: PeerTable, home: tuple[float, float, float],
                 frame: LocalFrame, *, requester_cfg: RequesterConfig | None = None,
                 help_cfg: HelpConfig | None = None, vantage_cfg: VantageConfig | None = None) -> None:
        help_cfg = help_cfg or HelpConfig()
        self.codec, self.transport, self.peers = codec, transport, peers
        self.requester = RequesterRole(codec.sender_id, home, requester_cfg or RequesterConfig(), help_cfg)
        self.helper = HelperRole(codec.sender_id, frame, vantage_cfg or VantageConfig(), help_cfg)
        self.sent = 0

    def receive(self, env: Envelope, now_s: float, me: HelperStatus) -> None:
        """Account for one accepted envelope (every topic: any message keeps its sender live)."""
        self._send(self.requester.on_message(env, now_s))
        self._send(self.helper.on_message(env, now_s, self._as_helper(me)))

    def step(self, now_s: float, gnss: SourceHealth | None, fused: Estimate | None, me: HelperStatus,
             peer_positions: Mapping[str, tuple[float, float, float]], *, alt_rel_m: float | None = None,
             floor_up_m: float = -math.inf,
             peer_velocities: Mapping[str, np.ndarray] | None = None) -> AgentDecisions:
        """Periodic work: ``gnss`` this drone's GNSS health and ``fused`` its estimate (fusion);
        ``me`` its status; ``peer_positions`` every other drone's latest (lat_deg, lon_deg, alt_m);
        ``alt_rel_m`` its autopilot's height above home (None: unknown); ``floor_up_m`` the lowest it may
        fly as a helper (ENU up of its frame); ``peer_velocities`` their ENU velocities (m/s) where known."""
        live = self.peers.live()
        decision, out = self.requester.step(now_s, gnss, fused, live, alt_rel_m)
        self._send(out)
        helper, out = self.helper.step(now_s, self._as_helper(me), peer_positions, live, floor_up_m=floor_up_m,
                                       velocities=peer_velocities)
        self._send(out)
        return AgentDecisions(decision, helper)

    def stand_down(self, now_s: float, why: str) -> None:
        """The requester needs no more help (e.g. it has landed): cancel its request, release its helpers."""
        if self.requester.protocol.active:
            self._send(self.requester.protocol.cancel(now_s, why))

    def _as_helper(self, me: HelperStatus) -> HelperStatus:
        return replace(me, localised=False) if self.requester.protocol.active else me

    def _send(self, bodies: list[Body]) -> None:
        for body in bodies:
            self.transport.publish(TOPIC_OF[type(body)], self.codec.encode(body))
            self.sent += 1
