"""Positioning-source health: ok / degraded / lost / rejected, per drone and source.

One :class:`SourceMonitor` per (drone, source). It is told when a message arrives,
whether the message's own quality figures are good, and whether it passed the
innovation gate against the fused prediction; it answers whether to fuse it.

- **lost**: no usable message for longer than the source's time-out, or the receiver
  says it has no fix.
- **rejected**: ``reject_after`` consecutive messages failed the innovation gate (a
  spoofed jump, a multipath excursion, a misread tag).
- **degraded**: fused, but with a quality flag (few satellites, high HDOP, 2-D fix) or
  a single gate failure.
- A source that was lost or rejected is fused again on evidence: it has been heard for
  at least ``readmit_after_s`` since, and at least ``readmit_fraction`` of its messages in
  the last ``readmit_after_s`` passed the consistency test (one outlier does not restart
  the clock). The caller chooses the test: the innovation gate against the fused
  estimate, or, after a drift, agreement with GNSS-independent sources.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass


class HealthState(str, enum.Enum):
    OK = "ok"
    DEGRADED = "degraded"
    LOST = "lost"
    REJECTED = "rejected"

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class SourceHealth:
    """A source's state, why, and since when (measurement clock, s)."""

    state: HealthState
    reason: str
    since_s: float

    def to_dict(self) -> dict:
        return {"state": self.state.value, "reason": self.reason, "since_s": self.since_s}


class SourceMonitor:
    """The health state machine of one positioning source of one drone.

    Example (two gate failures in a row reject the source):
        >>> monitor = SourceMonitor(timeout_s=1.0, reject_after=2, readmit_after_s=5.0, now_s=0.0)
        >>> monitor.judge(0.0, True), monitor.judge(0.2, False), monitor.judge(0.4, False)
        (True, False, False)
        >>> monitor.state
        <HealthState.REJECTED: 'rejected'>
    """

    def __init__(self, timeout_s: float, reject_after: int, readmit_after_s: float, now_s: float,
                 readmit_fraction: float = 0.8, probation_after_silence: bool = True) -> None:
        self.timeout_s = timeout_s
        self.probation_after_silence = probation_after_silence
        self.reject_after = reject_after
        self.readmit_after_s = readmit_after_s
        self.readmit_fraction = readmit_fraction
        self._state = HealthState.OK
        self._reason = "first message"
        self._since_s = now_s
        self.last_heard_s = now_s
        self.last_fused_s = -float("inf")
        self._failures = 0
        self._probation = False
        self._probation_first_s: float | None = None   # first message judged on probation
        self._evidence: deque[tuple[float, bool]] = deque()  # (time, passed) on probation
        self._recent_s: list[float] = []   # last message times, for the rate
        self._stamps: deque[float] = deque(maxlen=64)  # recent time stamps, for duplicates
        self._usual_rate_hz = 0.0
        self._last_value: tuple | None = None  # the previous message's content, for re-sent ones

    def repeat(self, t_s: float) -> bool:
        """True if a message with this exact time stamp was already seen (a duplicate delivered twice,
        e.g. over two links); records ``t_s`` otherwise."""
        if t_s in self._stamps:
            return True
        self._stamps.append(t_s)
        return False

    def resent(self, t_s: float, value: tuple) -> bool:
        """True if ``value`` (e.g. a fix's coordinates) equals the previous message's: the same measurement
        sent again under a newer time stamp (an autopilot streams its receiver's last fix at its own rate),
        no new evidence. It still counts as heard at ``t_s``: a receiver that repeats itself is not silent."""
        same = value == self._last_value
        self._last_value = value
        if same:
            self.last_heard_s = max(self.last_heard_s, t_s)
        return same

    def rate_issue(self, t_s: float) -> str | None:
        """Record a message time; describe the problem if the rate fell below half the usual one.

        The usual rate is the highest rate seen over 10 messages (a receiver's nominal rate).
        """
        recent = self._recent_s
        if recent and t_s <= recent[-1]:
            return None  # late or repeated: says nothing about the rate
        recent.append(t_s)
        if len(recent) > 10:
            del recent[0]
        if len(recent) < 10:
            return None
        rate = (len(recent) - 1) / (recent[-1] - recent[0])
        self._usual_rate_hz = max(self._usual_rate_hz, rate)
        if rate < 0.5 * self._usual_rate_hz:
            return f"rate {rate:.1f} Hz (usually {self._usual_rate_hz:.1f} Hz)"
        return None

    @property
    def health(self) -> SourceHealth:
        return SourceHealth(self._state, self._reason, self._since_s)

    @property
    def state(self) -> HealthState:
        return self._state

    def _set(self, state: HealthState, reason: str, t_s: float) -> None:
        if state != self._state or reason != self._reason:
            if state != self._state:
                self._since_s = t_s
            self._state = state
            self._reason = reason

    def no_fix(self, t_s: float, reason: str) -> None:
        """The source reports it has nothing (e.g. GNSS fix type 0/1)."""
        self.last_heard_s = max(self.last_heard_s, t_s)
        self._enter_probation()
        self._set(HealthState.LOST, reason, t_s)

    def _enter_probation(self) -> None:
        self._probation = True
        self._probation_first_s = None
        self._evidence.clear()
        self._failures = 0

    @property
    def on_probation(self) -> bool:
        return self._probation

    def reject(self, t_s: float, reason: str) -> None:
        """Reject the source for a reason found outside the per-message gate (e.g. a drift test)."""
        self._enter_probation()
        self._set(HealthState.REJECTED, reason, t_s)

    def _readmit(self, t_s: float, consistent: bool) -> bool:
        """Record one probation result; True when the evidence is enough to fuse again."""
        if self._probation_first_s is None:
            self._probation_first_s = t_s
        ev = self._evidence
        ev.append((t_s, consistent))
        while ev and ev[0][0] < t_s - self.readmit_after_s - 1e-9:
            ev.popleft()
        waited_s = t_s - self._probation_first_s
        passed = sum(ok for _, ok in ev) / len(ev)
        if self._state is not HealthState.OK:
            self._reason = (f"{self._reason.split(';')[0]}; on probation {waited_s:.1f} s, {100 * passed:.0f} % "
                            f"consistent (re-admitted at >= {100 * self.readmit_fraction:.0f} % over "
                            f"{self.readmit_after_s:g} s)")
        return consistent and waited_s >= self.readmit_after_s - 1e-9 and passed >= self.readmit_fraction

    def judge(self, t_s: float, consistent: bool, quality_issue: str | None = None) -> bool:
        """Record a usable message at ``t_s``; return True when it should be fused.

        ``consistent``: it passed the innovation gate (True when nothing to gate against).
        ``quality_issue``: why its own figures are poor (fused as degraded), or None.
        """
        self.last_heard_s = max(self.last_heard_s, t_s)
        if self._probation:
            if not consistent and self._state is HealthState.LOST:
                self._set(HealthState.REJECTED, "inconsistent with the fused estimate after recovery", t_s)
            if not self._readmit(t_s, consistent):
                return False
            self._probation = False
            self._failures = 0
        elif not consistent:
            self._failures += 1
            if self._failures >= self.reject_after:
                self._enter_probation()
                self._set(HealthState.REJECTED, f"{self.reject_after} consecutive innovation-gate failures", t_s)
            else:
                self._set(HealthState.DEGRADED, "innovation outlier dropped", t_s)
            return False
        self._failures = 0
        if quality_issue:
            self._set(HealthState.DEGRADED, quality_issue, t_s)
        else:
            self._set(HealthState.OK, "consistent", t_s)
        self.last_fused_s = max(self.last_fused_s, t_s)
        return True

    def tick(self, now_s: float) -> None:
        """Apply the time-out at the engine's current time ``now_s``. A source that was only silent goes on
        probation unless ``probation_after_silence`` is False: then its next message that passes the gate is
        fused again at once (a camera observer that lost sight of its target for a while)."""
        silent_s = now_s - self.last_heard_s
        if silent_s > self.timeout_s and self._state is not HealthState.LOST:
            if self.probation_after_silence or self._probation:  # a rejected source stays on probation
                self._enter_probation()
            self._set(HealthState.LOST, f"silent for more than {self.timeout_s:g} s", self.last_heard_s + self.timeout_s)
