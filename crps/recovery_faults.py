"""Faults of a recovery run (:mod:`skyfix.crps.recovery`): lossy swarm links, a MAVLink drop, a helper
that goes silent, an impostor without the swarm key, GNSS that comes back off, a gimbal looking away.

Each fault acts where it would in the field: on datagrams (swarm, MAVLink), on the simulated
receiver, on a service's life; none touches the code under test. Times are simulated seconds.
"""

from __future__ import annotations

import logging
import math
import random
import threading

from skyfix.crps.messages import TOPIC_OF, RelativeObs, SwarmCodec
from skyfix.datasets.sim.relay import UdpRelay

log = logging.getLogger(__name__)

GNSS_BACK_AFTER_S = 25.0    # with gnss_return_offset_m: the receiver reports again this long after the loss
OUTAGE_INTO_RETURN_S = 5.0  # the MAVLink drop starts this long after the lost drone starts home
FORGED_PERIOD_S = 0.2
FOV_FAULT_AFTER_S = 10.0    # a helper's gimbal looks away this long after it starts helping ...
FOV_FAULT_FOR_S = 12.0      # ... for this long


class LossyLink:
    """A swarm transport whose deliveries to this drone are each lost with probability ``rate``
    (independent per sender -> receiver message); ``muted`` drops everything both ways."""

    def __init__(self, link, rate: float, seed: int) -> None:
        self.link, self.rate = link, float(rate)
        self._rng = random.Random(seed)
        self._lock = threading.Lock()
        self.muted = False
        self.lost = self.delivered = 0

    def _drop(self) -> bool:
        if self.muted:
            return True
        lose = False
        if self.rate > 0.0:
            with self._lock:
                lose = self._rng.random() < self.rate
        self.lost += lose
        self.delivered += not lose
        return lose

    def publish(self, topic: str, data: bytes) -> None:
        if not self.muted:
            self.link.publish(topic, data)

    def subscribe(self, callback) -> None:
        self.link.subscribe(lambda key, data: None if self._drop() else callback(key, data))

    def close(self) -> None:
        self.link.close()


class Faults:
    """The faults ``cfg`` asks for, scheduled against ``run`` (a :class:`skyfix.crps.recovery._Run`)."""

    def __init__(self, cfg, run) -> None:
        self.cfg, self.run = cfg, run
        self.relay: UdpRelay | None = None
        self.outage: tuple[float, float] | None = None
        self.dropped_helper: str | None = None
        self._forger: tuple[SwarmCodec, object] | None = None
        self._forged_next_s = -math.inf
        self.forged_sent = 0
        self.first_assigned_s: float | None = None
        self.fov_helper: str | None = None
        self.blinded = False

    def mavlink_url(self, index: int, url: str) -> str:
        """The URL the service of vehicle ``index`` uses (through a relay for the lost drone's outage)."""
        from skyfix.crps.recovery import LOST

        if index != LOST or self.cfg.mav_outage_s <= 0.0:
            return url
        self.relay = UdpRelay(self.run.sim.addresses[self.run.sim_index[index]], self._mavlink_blocked)
        return self.relay.url

    def _mavlink_blocked(self) -> bool:
        return self.outage is not None and self.outage[0] <= self.run.sim.time_s < self.outage[1]

    def lose_gnss(self, index: int, t_s: float) -> None:
        """The receiver of vehicle ``index`` stops at ``t_s`` (and comes back off, if asked)."""
        from skyfix.datasets.sim.gps import GpsFault

        if self.run.sim_index[index] is None:  # an external autopilot (SITL): its simulated receiver off
            self.run.services[index].vehicle.set_param("SIM_GPS1_ENABLE", 0)
            return
        offset = self.cfg.gnss_return_offset_m
        if offset is None:
            self.run.sim.add_gps_fault(self.run.sim_index[index], GpsFault("loss", t_s))
            return
        self.run.sim.add_gps_fault(self.run.sim_index[index], GpsFault("loss", t_s, GNSS_BACK_AFTER_S))
        self.run.sim.add_gps_fault(self.run.sim_index[index], GpsFault("jump", t_s + GNSS_BACK_AFTER_S,
                                                   offset_enu_m=(float(offset), 0.0, 0.0)))

    def tick(self) -> None:
        """Called by the harness a few times per second."""
        from skyfix.crps.recovery import IDS, LOST
        from skyfix.crps.roles import Mode

        run, cfg = self.run, self.cfg
        if run.t_loss is None or cfg.healthy:
            return
        now = run.sim.time_s
        lost = run.services[LOST].help
        if lost is None:
            return
        if cfg.mav_outage_s > 0 and self.outage is None and lost.mode is Mode.RETURN_HOME:
            start = now + OUTAGE_INTO_RETURN_S
            self.outage = (start, start + cfg.mav_outage_s)
            run.note(f"MAVLink link to {IDS[LOST]} will drop for {cfg.mav_outage_s:.0f} s at t={start:.1f} s")
        if cfg.helper_dropout_s is not None and self.dropped_helper is None and lost.helpers \
                and now >= run.t_loss + cfg.helper_dropout_s:
            self._drop_helper(lost.helpers[0])
        if lost.helpers and self.first_assigned_s is None:
            self.first_assigned_s = now
        if cfg.target_leaves_fov and self.fov_helper is None and lost.helpers \
                and now >= self.first_assigned_s + FOV_FAULT_AFTER_S:
            self._look_away(lost.helpers[0], now)
        if cfg.helpers_blind_s is not None and not self.blinded:
            self._blind(run.t_loss, cfg.helpers_blind_s)
        if cfg.forged_observation and now >= self._forged_next_s:
            self._forged_next_s = now + FORGED_PERIOD_S
            self._forge(now)

    def _look_away(self, helper_id: str, now_s: float) -> None:
        from skyfix.crps.recovery import IDS
        from skyfix.datasets.sim.world_camera import GimbalFault

        self.fov_helper = helper_id
        self.run.cameras[IDS.index(helper_id)].set_gimbal_fault(GimbalFault(now_s, FOV_FAULT_FOR_S, 90.0))
        self.run.note(f"{helper_id}'s gimbal looks 90 deg away for {FOV_FAULT_FOR_S:.0f} s: the target leaves its view")

    def _blind(self, start_s: float, duration_s: float) -> None:
        from skyfix.crps.recovery import LOST
        from skyfix.datasets.sim.world_camera import GimbalFault

        self.blinded = True
        for index, camera in enumerate(self.run.cameras):
            if index != LOST and camera is not None:
                camera.set_gimbal_fault(GimbalFault(start_s, duration_s, 90.0))
        self.run.note(f"every helper's gimbal looks 90 deg away for {duration_s:.0f} s from the loss: "
                      "nobody can see the lost drone")

    def figures(self) -> dict[str, float]:
        """Evidence that each fault happened (counts as floats, NaN where it does not apply)."""
        links = [s.transport for s in self.run.services]
        return {"swarm_delivered": float(sum(k.delivered for k in links)), "swarm_lost": float(sum(k.lost for k in links)),
                "mavlink_dropped": float(self.relay.dropped) if self.relay is not None else math.nan,
                "forged_sent": float(self.forged_sent),
                "gnss_back_t_s": self.run.t_loss + GNSS_BACK_AFTER_S
                if self.cfg.gnss_return_offset_m is not None and self.run.t_loss is not None else math.nan}

    def _drop_helper(self, helper_id: str) -> None:
        from skyfix.crps.recovery import IDS

        self.dropped_helper = helper_id
        service = self.run.services[IDS.index(helper_id)]
        service.transport.muted = True
        service.stop.set()
        self.run.note(f"{helper_id} drops out (its service stops, nothing more is heard from it)")

    def _forge(self, now_s: float) -> None:
        """An impostor claiming to be d1, without the swarm key: an observation putting the lost drone 40 m off."""
        from skyfix.crps.recovery import IDS, LOST

        if self._forger is None:
            codec = SwarmCodec(IDS[0], b"not-the-swarm-key-" + bytes(14), clock=self.run.clock)
            self._forger = (codec, self.run.bus.attach("skyfix", IDS[0]))
            self.run.note("an impostor without the swarm key starts sending observations of "
                          f"{IDS[LOST]} as {IDS[0]}")
        codec, link = self._forger
        world = self.run.sim.world  # the impostor claims to look from above the field's origin
        body = RelativeObs(IDS[LOST], now_s, (1.0, 0.0, 0.0), 40.0, (0.25, 0.0, 0.0, 0.0, 0.25, 0.0, 0.0, 0.0, 0.25),
                           world.lat0_deg, world.lon0_deg, world.alt0_m + 15.0)
        link.publish(TOPIC_OF[RelativeObs], codec.encode(body))
        self.forged_sent += 1

    def close(self) -> None:
        if self.relay is not None:
            self.relay.close()
