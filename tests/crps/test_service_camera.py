"""Camera frames into the service: a folder source reaches the detector; a full queue drops the
oldest frame (never blocks the reader), counted."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from test_swarm_transport import wait_for

from skyfix.crps.camera_feed import FRAME_QUEUE, CameraFeed
from skyfix.errors import InputError


class Sink:
    """Collects what the feed writes (the service passes its Outputs)."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, dict]] = []

    def json(self, topic: str, obj: dict, time_s: float | None = None) -> None:
        self.messages.append((topic, obj))


def drone_on_sky(centre_uv: tuple[int, int]) -> np.ndarray:
    """A dark quadcopter silhouette (two arms, four rotors, ~50 px span) on a bright sky gradient."""
    img = np.full((480, 640), 200, np.uint8) + np.linspace(0, 30, 480)[:, None].astype(np.uint8)
    u, v = centre_uv
    for du, dv in ((-20, -10), (20, 10), (-20, 10), (20, -10)):
        cv2.circle(img, (u + du, v + dv), 6, 50, -1)
    cv2.line(img, (u - 20, v - 10), (u + 20, v + 10), 40, 3)
    cv2.line(img, (u - 20, v + 10), (u + 20, v - 10), 40, 3)
    return img


def test_folder_frames_reach_the_detector(tmp_path):
    centres = [(200, 150), (320, 240), (450, 300)]
    for i, c in enumerate(centres):
        cv2.imwrite(str(tmp_path / f"frame_{i:03d}.png"), drone_on_sky(c))
    sink = Sink()
    feed = CameraFeed(str(tmp_path), sink, folder_fps=20.0).start()
    try:
        assert wait_for(lambda: len(sink.messages) >= 6, 20.0)
    finally:
        feed.stop()
    found = [tuple(d["centroid_uv"]) for _, m in sink.messages for d in m["detections"]]
    for c in centres:  # each drawn drone found within 2 px of its centre
        assert min(np.hypot(f[0] - c[0], f[1] - c[1]) for f in found) < 2.0
    assert all(topic == "/camera/detections" for topic, _ in sink.messages)


def test_a_full_queue_drops_the_oldest_frame(tmp_path):
    cv2.imwrite(str(tmp_path / "f.png"), drone_on_sky((320, 240)))
    feed = CameraFeed(str(tmp_path), Sink())  # not started: nobody takes frames out
    t0 = time.time()
    for k in range(5):
        feed._offer(t0 + k, np.zeros((4, 4), np.uint8))
    assert feed.n_frames == 5 and feed.n_dropped == 5 - FRAME_QUEUE
    assert [feed.frames.get_nowait()[0] - t0 for _ in range(FRAME_QUEUE)] == [3.0, 4.0]  # the newest kept


def test_bad_sources(tmp_path):
    with pytest.raises(InputError, match="no images"):
        CameraFeed(str(tmp_path), Sink())
    with pytest.raises(InputError, match="OpenCV cannot open"):
        CameraFeed(str(tmp_path / "no-such-stream.mp4"), Sink())


def test_sim_camera_frames_show_the_nearest_peer_to_the_detector():
    """--camera sim: the renderer draws the nearest peer (here 25 m north, 3 m up; another at 80 m) where
    the camera is pointed, and the same feed finds it at the image centre."""
    from skyfix.crps.sim_camera import SimCamera
    from skyfix.geo import LocalFrame

    frame = LocalFrame(46.52, 6.63, 420.0)
    near = tuple(float(c) for c in frame.to_geodetic(0.0, 25.0, 3.0))
    far = tuple(float(c) for c in frame.to_geodetic(80.0, 0.0, 0.0))
    cam = SimCamera(lambda: (46.52, 6.63, 420.0), lambda: [far, near], width=640, height=480, hfov_deg=40.0)
    image = cam()
    assert image.shape == (480, 640) and image.dtype == np.uint8
    sink = Sink()
    feed = CameraFeed(cam, sink, folder_fps=20.0).start()
    try:
        assert wait_for(lambda: any(m["detections"] for _, m in sink.messages), 20.0)
    finally:
        feed.stop()
    det = next(d for _, m in sink.messages for d in m["detections"])
    assert np.hypot(det["centroid_uv"][0] - 319.5, det["centroid_uv"][1] - 239.5) < 3.0
    assert SimCamera(lambda: None, lambda: [near])() is None  # nothing to render before the first fix
