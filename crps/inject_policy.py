"""What a requester injects as its GPS (GPS_INPUT) while it flies on skyfix's fix: the policy of
:class:`skyfix.crps.service.Service` for the moments no camera measures it, and its guard against a position that
pins the autopilot's EKF.

The fused fix is injected while observations of the drone arrive. Without them, with an autopilot whose velocity
echoes the injected fix (ArduPilot, PX4: not the built-in simulator, whose drones report their true velocity),
dead reckoning on that echo only integrates its bias estimate, so the fix is not flown on (see :meth:`fix`).
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from skyfix.types import GeoFix

log = logging.getLogger(__name__)

INJECT_HOLD_AFTER_S = 2.0  # no camera observation of a holding or landing drone arrived this long: its injected position held
INJECT_HOLD_MAX_S = 8.0  # a hover nothing measures is injected at most this long (its own position), then nothing
# the autopilot leaning at least WINDUP_TILT_DEG while its own estimate says it moves at most WINDUP_SPEED_MPS, for
# WINDUP_FOR_S: its position controller winds up against an injected position that pins its EKF (see _windup_guard)
WINDUP_TILT_DEG = 20.0
WINDUP_SPEED_MPS = 3.0
WINDUP_FOR_S = 3.0
OWN_POSITION_FRESH_S = 1.0  # the autopilot's own position, injected back while it holds unobserved, at most this old
LANDING_HOLD_SIGMA_M = 0.3  # horizontal accuracy stated to the autopilot for a landing's held position (a control value)


class InjectionPolicy:
    """The fix ``service`` injects now (:meth:`fix`, called by its injector thread) and why none is; ``service``
    provides ``clock``, ``node``, ``help`` (its help loop or None), ``vehicle`` and ``cfg`` (``drone_id``,
    ``injected_velocity_sigma_mps``)."""

    def __init__(self, service) -> None:
        self.svc = service
        self._held_fix: GeoFix | None = None  # a low landing's injected position, held to the ground
        self._seen_s = -math.inf  # exposure time of the newest camera observation of this drone fused (clock s)
        self._seen_at_s = -math.inf  # when it was found fused (clock s)
        self._quiet_since_s: float | None = None  # since when a hover or high landing has gone unmeasured (clock s)
        self._cut = False  # that lasted INJECT_HOLD_MAX_S: nothing injected until an observation arrives
        self._hover_fix: GeoFix | None = None  # a hover's held fix when the autopilot reports no fresh position
        self._windup_since_s: float | None = None  # since when the autopilot leans hard standing still (clock s)
        self.cut_reason: str | None = None  # set by _windup_guard: nothing injected until GNSS is back

    @property
    def withheld(self) -> bool:
        """True while no position is injected on purpose (a hover past INJECT_HOLD_MAX_S unmeasured, or the wind-up
        guard)."""
        return self._cut or self.cut_reason is not None

    def gnss_back(self) -> None:
        """The injection ended (GNSS healthy again): the wind-up guard's cut ends with it."""
        self.cut_reason, self._windup_since_s = None, None

    def fix(self) -> GeoFix | None:
        """The fix injected now (stamped UNIX time). While the drone holds, or lands still high, with no camera
        observation of it arriving for INJECT_HOLD_AFTER_S and its autopilot's velocity echoes the injected fix,
        dead-reckoning on that echo only integrates its bias estimate, so the fix is not flown on. It then injects
        the autopilot's own position (GLOBAL_POSITION_INT, :meth:`_autopilot_position`; without fresh telemetry the
        last fix, held) with the fused covariance, for at most INJECT_HOLD_MAX_S, then nothing until an observation
        arrives: the autopilot's own GPS-loss failsafe flies it (ArduPilot: EKF failsafe, LAND without position
        hold, drifting with the wind). A *constant* position is no hold: ArduPilot SITL's EKF, told it stood still,
        kept its velocity near zero while its position controller's integrator wound up against the injected point,
        and the copter flew away (helpers' cameras looking away, no load: 100 m in 20 s; loaded, helpers' frames
        6 s late: 840 m at 30 deg of pitch; the same in a landing held from 40 m: 165 m at 30 deg of roll). On its
        own position the EKF brakes on its IMU and stops, and the bound ends the slower wind-up that remains (35 m in
        30 s on SITL). See ``benchmarks/recovery_sitl_loaded.py --blind-s``.

        A landing low (the help loop's ``landing_low``) holds at once, observed or not, where the fix is then and
        to the ground (:meth:`_landing_hold`): the helpers' fixes of a drone near the ground are the worst it gets
        (SITL, loaded machine: chasing late fixes in its last 2 m, 4.5 m of drift; held on a 6.9 m sigma, its EKF
        walked; both times the copter stood on the ground armed), and a stated accuracy growing by the second let
        ArduPilot's EKF walk ~0.5 m/s on the ground (SITL: 4.6 m in 20 s, the position controller tilting 20-27
        deg), so it never reached LAND_COMPLETE and never disarmed. A landing whose injection was cut stays
        without one until an observation arrives."""
        now = self.svc.clock()
        if self.svc.cfg.injected_velocity_sigma_mps is not None and self._windup_guard(now):
            return None
        fix = self.svc.node.fix(self.svc.cfg.drone_id, now, time_stamp_s=time.time())
        mode = self.svc.help.mode.value if self.svc.help is not None else None
        seen_s = self.svc.node.observed_s.get(self.svc.cfg.drone_id, -math.inf)
        if seen_s > self._seen_s:  # a new observation fused since the last look
            self._seen_s, self._seen_at_s = seen_s, now
        # quiet: none *arrived* for INJECT_HOLD_AFTER_S. Not judged on its exposure time: under load every
        # observation is more than that old when it arrives, and the held position was injected for good while the
        # helpers' fixes went unused (SITL, loaded machine: 2-4 s late, the copter flew away at 30 deg of tilt)
        quiet = now - self._seen_at_s > INJECT_HOLD_AFTER_S
        # a landing once held low stays held to the ground: a late or new sighting near touchdown would move the
        # position it comes down on (a loaded SITL run stood landed and armed while helpers came and went)
        landing_low = mode == "land" and (self._held_fix is not None or self.svc.help.landing_low)
        if fix is None or self.svc.cfg.injected_velocity_sigma_mps is None or mode not in ("hold", "land") \
                or not (quiet or landing_low):
            self._held_fix = self._hover_fix = self._quiet_since_s = None
            self._cut = False
            return fix
        if not quiet:
            self._quiet_since_s, self._cut = None, False
        elif not landing_low:  # hovering, or landing still high: nothing measures it
            self._quiet_since_s = now if self._quiet_since_s is None else self._quiet_since_s
            self._cut = self._cut or now - self._quiet_since_s > INJECT_HOLD_MAX_S
        if self._cut:  # until an observation arrives, even once low: the fix is no better than the failsafe's
            return None  # the autopilot's own GPS-loss failsafe flies it: no position rather than a made-up one
        if not landing_low:
            own = self._autopilot_position()
            if own is not None:
                return GeoFix(own.lat_deg, own.lon_deg, fix.alt_m, fix.cov_enu_m2, fix.time_s, fix.source_id)
            self._hover_fix = self._hover_fix or fix  # no fresh telemetry position: the last fix, held
            held = self._hover_fix
            return GeoFix(held.lat_deg, held.lon_deg, held.alt_m, fix.cov_enu_m2, fix.time_s, fix.source_id)
        if self._held_fix is None:
            self._held_fix = self._landing_hold(fix)
        held = self._held_fix
        return GeoFix(held.lat_deg, held.lon_deg, held.alt_m, held.cov_enu_m2, fix.time_s, fix.source_id)

    def _windup_guard(self, now_s: float) -> bool:
        """True once the autopilot has leant WINDUP_TILT_DEG or more for WINDUP_FOR_S while its own velocity said
        WINDUP_SPEED_MPS or less: the injected positions pin its EKF and its position controller winds up against
        them, flying it away (SITL: the EKF still, the copter at 30 deg and 10 m/s). Then nothing more is injected
        in this GNSS outage: the autopilot's own GPS-loss failsafe lands it level (a fix that did this once is not
        flown on again). On 46 SITL dataflash logs of this flow (a by-hand scan of ATT and XKF1, 2026-11-29, not a
        committed benchmark) every flyaway lasted 6.8-16.1 s in that state and no other flight more than 0.8 s
        (from level flight, braking or landing)."""
        if self.cut_reason is not None:
            return True
        vehicle = self.svc.vehicle
        state = vehicle.state if vehicle is not None else None
        att, vel = (state.attitude, state.velocity) if state is not None else (None, None)
        fresh = att is not None and vel is not None and time.time() - min(att.time_s, vel.time_s) <= OWN_POSITION_FRESH_S
        tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, math.cos(math.radians(att.roll_deg))
                                                              * math.cos(math.radians(att.pitch_deg)))))) if fresh else 0.0
        if not (fresh and tilt_deg >= WINDUP_TILT_DEG and vel.ground_speed_mps <= WINDUP_SPEED_MPS
                and state.position is not None and state.position.alt_rel_m > 1.0):
            self._windup_since_s = None
            return False
        self._windup_since_s = now_s if self._windup_since_s is None else self._windup_since_s
        if now_s - self._windup_since_s < WINDUP_FOR_S:
            return False
        self.cut_reason = (f"the autopilot leans {tilt_deg:.0f} deg while its estimate says "
                           f"{vel.ground_speed_mps:.1f} m/s: its EKF is pinned by the injected positions")
        log.error("%s: injection stopped: %s; its own failsafe flies it now", self.svc.cfg.drone_id,
                  self.cut_reason)
        if self.svc.help is not None:
            self.svc.help.note(now_s, f"injection stopped ({self.cut_reason})")
        return True

    def _autopilot_position(self):
        """The autopilot's own fused position (GLOBAL_POSITION_INT) received in the last OWN_POSITION_FRESH_S
        (UNIX time), else None."""
        vehicle = self.svc.vehicle
        state = vehicle.state if vehicle is not None else None
        if state is None or not state.link_ok or state.position is None \
                or not time.time() - state.position.time_s <= OWN_POSITION_FRESH_S:
            return None
        return state.position

    def _landing_hold(self, fix: GeoFix) -> GeoFix:
        """The fix a landing holds: where ``fix`` is now (a jump at touchdown winds up ArduPilot's position
        controller: SITL on the ground asked 20-22 deg of tilt, the throttle mix never reached its minimum and
        it never disarmed), stated LANDING_HOLD_SIGMA_M accurate horizontally. That accuracy is a control value,
        not an estimate (the fused fix keeps its own covariance): the held position is a constant the drone comes
        down on and then does not leave. On a looser one (the tightest recent sighting's, 1.5-2 m) SITL's EKF slid
        2.3 m on the ground after the touchdown's jolt; on this one 1.2 m, pulled back within 6 s, but the position
        controller's demand can still wind up against the ground, and the help loop's landed backstop disarms what
        the land detector then misses (:mod:`skyfix.crps.help_loop`)."""
        cov = np.array(fix.cov_enu_m2, dtype=float)
        cov[:2, :] = 0.0
        cov[:, :2] = 0.0
        cov[0, 0] = cov[1, 1] = LANDING_HOLD_SIGMA_M ** 2
        return GeoFix(fix.lat_deg, fix.lon_deg, fix.alt_m, cov, fix.time_s, fix.source_id)
