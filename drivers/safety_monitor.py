"""A Vehicle's safety monitor: its :class:`~skyfix.drivers.safety.SafetyGate` checked on every
position report, and the gate's action (a mode change) sent and confirmed.

Mixed into :class:`skyfix.drivers.vehicle.Vehicle` (which owns the command lock and sequence,
``safety`` and ``safety_log``); ``_check_safety`` runs on the reader thread, so the action goes
out within one telemetry message of the breach.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time

from skyfix.drivers.mav import mavlink
from skyfix.drivers.modes import PX4_MODES, custom_mode_of, mode_name, role_mode
from skyfix.drivers.safety import SafetyGate
from skyfix.drivers.state import Position, Velocity
from skyfix.errors import CommandRejected, LinkError, SkyfixTimeout

log = logging.getLogger("skyfix.drivers.vehicle")  # the Vehicle's logger: one name for its whole story
M = mavlink
#: the gate's mode change is re-sent every 0.5 s for up to 4 s: over a link that loses 15 % each
#: way, eight silent attempts in a row are a 4e-5 chance (five were 2e-3)
SAFETY_ACK_TIMEOUT_S = 0.5
SAFETY_RETRIES = 7


#: the messages that answer a command: its ACK, or the state that proves it took effect when every ACK was lost
CONFIRMING_TYPES = ("COMMAND_ACK", "HEARTBEAT", "EXTENDED_SYS_STATE")


def _confirming(msg) -> bool:
    return msg.get_type() in CONFIRMING_TYPES


class SafetyMonitor:
    """Gate installation, the per-report check and the confirmed action."""

    def set_safety(self, gate: SafetyGate | None) -> None:
        """Install (or remove) the safety gate checked on setpoints and telemetry."""
        self.safety = gate
        self._safety_latched = False

    def _check_safety(self, pos: Position, vel: Velocity, t_mono: float) -> None:
        st = self._state
        if not st.armed:
            self._safety_latched = False
            return
        why = self.safety.violation(pos.lat_deg, pos.lon_deg, pos.alt_rel_m, vel.speed_mps)
        if not why:
            self._safety_latched = False
            return
        if self._safety_latched:
            return
        self._safety_latched = True
        self._stop_setpoints()
        mode = role_mode(self.autopilot, self.safety.action)
        params = self._mode_params(mode)
        # the action goes out now from the reader thread when no command is in flight;
        # otherwise the safety thread sends it right after the current one (one channel)
        generation = self._command_seq
        sent = self._command_lock.acquire(blocking=False)
        replies = None
        if sent:
            # subscribed before the send: the ACK can come back before the confirming thread runs
            replies = self._open_subscription(_confirming)
            self._send_command_long(M.MAV_CMD_DO_SET_MODE, params, 0)
        latency_s = time.monotonic() - t_mono
        self.safety_log.append((latency_s, why))
        log.warning("vehicle %d safety violation: %s -> %s (%.1f ms after telemetry%s)", self.system_id,
                    why, mode, latency_s * 1e3, "" if sent else ", queued behind a command in flight")
        self._emit("safety_violation", why, action=mode, latency_s=latency_s)
        threading.Thread(target=self._safety_action, args=(mode, params, generation, replies), daemon=True,
                         name=f"skyfix-safety-{self.system_id}").start()

    def _safety_action(self, mode: str, params: list[float], generation: int, replies) -> None:
        """Confirm the gate's mode change (its ACK, or a heartbeat already in the new mode when
        the ACKs are lost) without ever overriding a command the user gave after the violation,
        and without acting on a time-out. ``replies``: the subscription opened when the reader
        thread sent attempt 0 itself (it then holds the command lock); None when queued."""
        holding = replies is not None
        if not holding:
            self._command_lock.acquire()
        try:
            if self._command_seq != generation:
                log.warning("vehicle %d: safety action %s dropped: a newer command was given",
                            self.system_id, mode)
                return
            self._command_seq += 1
            generation = self._command_seq
            if replies is None:  # opened only now: a DO_SET_MODE ACK before this was the user's
                replies = self._open_subscription(_confirming)
            self._command_locked(M.MAV_CMD_DO_SET_MODE, params, SAFETY_ACK_TIMEOUT_S, SAFETY_RETRIES,
                                 first_sent=holding, replies=replies.queue,
                                 confirmed_by=lambda msg: self._heartbeat_in_mode(msg, mode))
        except CommandRejected as exc:
            if self._command_seq == generation:  # refused outright: land (envelope already breached)
                log.error("vehicle %d: safety action %s refused (%s); landing", self.system_id, mode, exc)
                self._emit("safety_action_failed", str(exc), action=mode)
                with contextlib.suppress(Exception):
                    self._command_locked(M.MAV_CMD_NAV_LAND, [], 0.5, 4)
            return
        except Exception as exc:  # no ACK / link lost: report, do not act on a time-out
            log.error("vehicle %d: safety action %s not confirmed: %s", self.system_id, mode, exc)
            self._emit("safety_action_failed", str(exc), action=mode)
            return
        finally:
            if replies is not None:
                self._close_subscription(replies)
            self._command_lock.release()
        with contextlib.suppress(SkyfixTimeout, LinkError):
            self.wait_until(lambda s: s.mode == mode or self._command_seq != generation, 3.0,
                            what=f"safety action {mode}")

    def _from_autopilot(self, msg, kind: str) -> bool:
        return msg.get_type() == kind and msg.get_srcSystem() == self.system_id \
            and msg.get_srcComponent() == self.component_id

    def _heartbeat_in_mode(self, msg, mode: str) -> bool:
        """True for this vehicle's autopilot heartbeat reporting ``mode``."""
        return self._from_autopilot(msg, "HEARTBEAT") and mode_name(self.autopilot, msg.custom_mode) == mode

    def _heartbeat_armed(self, msg, armed: bool) -> bool:
        """True for this vehicle's autopilot heartbeat reporting the motors ``armed`` (or disarmed)."""
        return self._from_autopilot(msg, "HEARTBEAT") and bool(msg.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED) == armed

    def _reports_airborne(self, msg) -> bool:
        """True for this vehicle's EXTENDED_SYS_STATE reporting it taking off or in the air."""
        return self._from_autopilot(msg, "EXTENDED_SYS_STATE") and msg.landed_state in (
            M.MAV_LANDED_STATE_TAKEOFF, M.MAV_LANDED_STATE_IN_AIR)

    def _mode_params(self, mode: str) -> list[float]:
        """DO_SET_MODE params for a mode name (PX4: main and sub mode)."""
        if self.autopilot == "px4":
            main, sub = PX4_MODES[mode]
            return [M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub]
        return [M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom_mode_of(self.autopilot, mode)]
