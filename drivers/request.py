"""The one request helper: send a MAVLink message, wait for the reply that answers it,
re-send on silence, give up after a bounded number of attempts.

Commands, parameters, mission transfers, the EKF origin and the injection settings check
all go through :func:`transact`. ``verdict(msg)`` classifies each incoming message:
``None`` (not an answer to this request), :data:`DONE` (the answer: returned),
:data:`WAIT` (the autopilot is working on it, e.g. ``MAV_RESULT_IN_PROGRESS``: the time-out
restarts) or :data:`AGAIN` (refused for now, e.g. ``TEMPORARILY_REJECTED``: re-sent after
``pause_s``; on the last attempt it is returned like DONE).
"""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from skyfix.errors import LinkError, SkyfixTimeout

if TYPE_CHECKING:
    from skyfix.drivers.vehicle import Vehicle

DONE, WAIT, AGAIN = "done", "wait", "again"


def transact(vehicle: Vehicle, message: Any | Callable[[int], Any], verdict: Callable[[Any], str | None],
             *, types: Iterable[str], timeout_s: float, retries: int, what: str,
             first_sent: bool = False, pause_s: float = 0.1, replies: queue.Queue | None = None,
             on_resend: Callable[[], None] | None = None) -> Any:
    """Send ``message`` (or ``message(attempt)``) until ``verdict`` accepts a reply.

    ``types``: the message types that can answer (a cheap filter before ``verdict``).
    ``first_sent``: the caller already sent attempt 0 (the safety gate sends from the
    reader thread without waiting). ``replies``: a queue from ``vehicle.subscribe`` the
    caller keeps open across several steps (mission transfers), so that no reply falls
    between two requests; ``on_resend()`` is called for every re-send. Raises SkyfixTimeout after ``retries + 1`` silent
    attempts of ``timeout_s`` each, LinkError when the vehicle's heartbeat is lost.
    """
    if replies is not None:
        return _attempts(vehicle, message, verdict, replies, timeout_s, retries, what, first_sent,
                         pause_s, on_resend)
    wanted = frozenset(types)
    with vehicle.subscribe(lambda m: m.get_type() in wanted) as q:
        return _attempts(vehicle, message, verdict, q, timeout_s, retries, what, first_sent, pause_s,
                         on_resend)


def _attempts(vehicle, message, verdict, replies, timeout_s, retries, what, first_sent, pause_s, on_resend):
    t0 = time.monotonic()
    for attempt in range(retries + 1):
        if attempt and on_resend is not None:
            on_resend()
        if attempt or not first_sent:
            vehicle.send(message(attempt) if callable(message) else message)
        deadline = time.monotonic() + timeout_s
        again = False
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg, _ = replies.get(timeout=left)
            except queue.Empty:
                break
            v = verdict(msg)
            if v == DONE or (v == AGAIN and attempt == retries):
                return msg
            if v == WAIT:
                deadline = time.monotonic() + timeout_s
            elif v == AGAIN:
                again = True
                break
        if again:
            time.sleep(pause_s)
        elif not vehicle.state.link_ok:
            raise LinkError(f"vehicle {vehicle.system_id}: no heartbeat; {what} not answered")
    raise SkyfixTimeout(f"vehicle {vehicle.system_id}: no answer to {what} after {retries + 1} "
                        f"attempts of {timeout_s:.2f} s{vehicle._reasons(t0)}")
