"""The helper eye's frame loop: a pipeline slower than the camera skips frames, never queues them.

A camera delivering frames at 20 Hz whose processing takes 0.2 s (four frame periods) must be
processed at the newest frame each time, with the frames that went by meanwhile counted as
dropped; a backlog would show as frames getting older and older when processed.
"""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np

from skyfix.crps.helper_eye import EyeConfig, HelperEye
from skyfix.types import GeoFix

FRAME_HZ = 20.0
PROCESS_S = 0.2  # the camera call plus processing: 4 frame periods


class _SlowCamera:
    """A camera whose every frame (grab + processing) takes PROCESS_S of wall time; frames stamped now."""

    def __init__(self) -> None:
        self.grabbed: list[float] = []

    def point(self, yaw_deg: float, pitch_deg: float) -> None:
        pass

    def __call__(self):
        t_s = time.monotonic()
        self.grabbed.append(t_s)
        time.sleep(PROCESS_S)
        return SimpleNamespace(t_s=t_s, image=None, yaw_deg=0.0, pitch_deg=0.0, camera=None)


def test_a_slow_pipeline_processes_the_newest_frame_and_counts_the_dropped_ones():
    cam = _SlowCamera()
    processed = threading.Event()
    seen: list[float] = []

    def on_frame(frame, _target, _detected) -> None:
        seen.append(frame.t_s)
        if len(seen) >= 6:
            processed.set()

    # no own fix: every frame is grabbed and scored, none observed (the loop is what is tested)
    eye = HelperEye(cam, "h", lambda _t: None, time.monotonic, EyeConfig(frame_hz=FRAME_HZ), on_frame=on_frame)
    try:
        eye.set_target("t", GeoFix(46.52, 6.63, 400.0, np.eye(3), 0.0, "request:t"))
        assert processed.wait(60.0), f"only {len(seen)} frames processed in 60 s"
        dropped, n = eye.frames_dropped, len(seen)
    finally:
        eye.close()
    gaps = np.diff(seen[:n])
    # each frame was grabbed when the previous one was done (no frame waited in a queue) ...
    assert np.all(gaps >= PROCESS_S * 0.95), gaps
    # ... and the frame slots that went by while processing were dropped: ~3-4 per processed frame
    # (at least 3: PROCESS_S is 4 periods; more when a loaded machine is slower still)
    assert dropped >= 3 * (n - 1), (dropped, n)
    assert len(eye.frames) >= n  # every processed frame is in the eye's record
