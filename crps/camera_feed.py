"""Camera frames into the service: a folder of images or an OpenCV source, through a bounded queue.

A reader thread grabs frames as the source delivers them; a detector thread runs
:class:`skyfix.crps.SilhouetteDetector` on the newest one. The queue holds two frames:
when the detector is behind, the oldest frame is dropped (and counted), never the
MAVLink or peer traffic. Detections are logged on ``/camera/detections`` (pixel centroid,
box, score); turning them into relative observations of identified peers needs the
camera's pose and the help protocol (next issue).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from skyfix.errors import InputError

log = logging.getLogger(__name__)

FRAME_QUEUE = 2
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


class CameraFeed:
    """Frames from ``source`` (folder, device index, stream URL, or a callable returning a frame or None)
    to the detector; ``outputs`` receives the detections. ``folder_fps``: rate of a folder's or a
    callable's frames."""

    def __init__(self, source: str | Callable[[], np.ndarray | None], outputs, folder_fps: float = 10.0) -> None:
        import cv2

        self.outputs, self.folder_fps = outputs, folder_fps
        self.frames: queue.Queue = queue.Queue(FRAME_QUEUE)
        self.n_frames = self.n_dropped = self.n_detected = 0
        self._stop = threading.Event()
        self._render = source if callable(source) else None
        path = Path("") if callable(source) else Path(source)
        if self._render is not None:
            self._files = self._capture = None
        elif path.is_dir():
            self._files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self._files:
                raise InputError(f"--camera {source}: no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
            self._capture = None
        else:
            self._files = None
            self._capture = cv2.VideoCapture(int(source) if source.isdigit() else source)
            if not self._capture.isOpened():
                raise InputError(f"--camera {source!r}: not a folder and OpenCV cannot open it as a device or stream")
        self._threads = [threading.Thread(target=self._read, daemon=True, name="skyfix-camera-read"),
                         threading.Thread(target=self._detect, daemon=True, name="skyfix-camera-detect")]

    def start(self) -> CameraFeed:
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        if self._capture is not None:
            self._capture.release()

    def _offer(self, t_s: float, image) -> None:
        """Queue a frame, dropping the oldest when the detector is behind."""
        self.n_frames += 1
        while True:
            try:
                self.frames.put_nowait((t_s, image))
                return
            except queue.Full:
                try:
                    self.frames.get_nowait()
                    self.n_dropped += 1
                except queue.Empty:
                    pass

    def _read(self) -> None:
        import cv2

        i = 0
        while not self._stop.is_set():
            if self._render is not None:
                image = self._render()
                self._stop.wait(1.0 / self.folder_fps)
            elif self._files is not None:
                image = cv2.imread(str(self._files[i % len(self._files)]), cv2.IMREAD_UNCHANGED)
                i += 1
                self._stop.wait(1.0 / self.folder_fps)
            else:
                ok, image = self._capture.read()
                if not ok:
                    self._stop.wait(0.05)
                    continue
            if image is not None:
                self._offer(time.time(), image)

    def _detect(self) -> None:
        from skyfix.crps import SilhouetteDetector

        detector = SilhouetteDetector()
        while not self._stop.is_set():
            try:
                t_s, image = self.frames.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                detections = detector(image)
            except InputError as exc:  # an unusable frame is logged and skipped
                log.warning("camera frame skipped: %s", exc)
                continue
            self.n_detected += len(detections)
            self.outputs.json("/camera/detections", {
                "time_s": t_s, "frames": self.n_frames, "dropped": self.n_dropped,
                "detections": [{"centroid_uv": d.centroid_uv.tolist(), "bbox_px": list(d.bbox_px),
                                "score": float(d.score)} for d in detections]}, t_s)
