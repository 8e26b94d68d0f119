"""A fiducial marker carried by the target: identity and a precise apparent size.

Uses OpenCV's ArUco detector directly for now; this is the single place to switch to
``skyfix.tags`` once it provides marker decoding. The marker's pose comes from
IPPE for squares (``cv2.solvePnP`` with ``SOLVEPNP_IPPE_SQUARE``) on a marker of unit
side, so the detection is scale-free: ``size_px = focal / range_of_unit_marker`` and
:func:`skyfix.crps.observe` multiplies by the real side given as
``target_size_m``. The returned centroid is the projection of the marker centre.
"""

from __future__ import annotations

import math

import numpy as np

from skyfix.camera import Camera
from skyfix.crps.detection import Detection, Roi, to_gray
from skyfix.errors import InputError

__all__ = ["MarkerDetector"]

_UNIT_SQUARE = np.array([[-0.5, 0.5, 0.0], [0.5, 0.5, 0.0], [0.5, -0.5, 0.0], [-0.5, -0.5, 0.0]], np.float64)


class MarkerDetector:
    """Detect ArUco markers (``dictionary`` a ``cv2.aruco.DICT_*`` name); a :class:`Detector`.

    ``ids`` restricts to the markers of known targets; ``corner_sigma_px`` is the 1-sigma
    corner noise used for the size and centroid uncertainty.
    """

    def __init__(self, camera: Camera, dictionary: str = "DICT_4X4_50", ids: set[int] | None = None,
                 corner_sigma_px: float = 0.15) -> None:
        import cv2

        if not hasattr(cv2.aruco, dictionary):
            raise InputError(f"dictionary must name a cv2.aruco dictionary such as 'DICT_4X4_50', got {dictionary!r}")
        if camera.distortion is not None:
            raise InputError("MarkerDetector needs an undistorted camera; undistort the image first")
        self.camera = camera
        self.ids = set(ids) if ids is not None else None
        self.corner_sigma_px = float(corner_sigma_px)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)),
                                                 params)

    def __call__(self, image: np.ndarray, roi: Roi | None = None, *, time_s: float = 0.0) -> list[Detection]:
        import cv2

        gray = to_gray(image)
        h, w = gray.shape
        u0, v0, u1, v1 = (0, 0, w, h) if roi is None else roi
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w), min(v1, h)
        img8 = np.clip(gray[v0:v1, u0:u1] * 255.0 + 0.5, 0, 255).astype(np.uint8)
        corners, ids, _ = self._detector.detectMarkers(img8)
        if ids is None:
            return []
        out: list[Detection] = []
        focal = math.sqrt(self.camera.fx * self.camera.fy)
        for quad, marker_id in zip(corners, ids.ravel(), strict=True):
            if self.ids is not None and int(marker_id) not in self.ids:
                continue
            pts = quad.reshape(4, 2).astype(np.float64) + np.array([u0, v0])
            ok, rvec, tvec = cv2.solvePnP(_UNIT_SQUARE, pts, self.camera.K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            if not ok or tvec[2, 0] <= 0:
                continue
            range_unit = float(np.linalg.norm(tvec))
            size_px = focal / range_unit
            centre = self.camera.project(tvec.reshape(1, 3))[0]
            side_px = float(np.mean(np.linalg.norm(pts - np.roll(pts, 1, axis=0), axis=1)))
            # Range from 4 corners: relative error ~ corner noise / side / sqrt(2 * 4 / 2).
            size_sigma = size_px * self.corner_sigma_px / side_px
            cen_var = self.corner_sigma_px ** 2 / 4.0
            box = (int(pts[:, 0].min()), int(pts[:, 1].min()), int(math.ceil(pts[:, 0].max())) + 1,
                   int(math.ceil(pts[:, 1].max())) + 1)
            out.append(Detection(centre, np.eye(2) * cen_var, box, side_px, "marker", size_px=size_px,
                                 size_sigma_px=size_sigma, marker_id=int(marker_id), time_s=time_s))
        return out
