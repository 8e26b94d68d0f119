"""``skyfix serve --camera sim``: frames from the simulator's renderer instead of a real camera.

The drone's camera (a stabilised gimbal) is turned towards the nearest peer it hears and
the frame is rendered by :func:`skyfix.datasets.drone_view.render_drone_view` with that peer
(a 0.5 m quad) at the position it broadcasts, against the procedural sky. The frames take
the same road as a real camera's (bounded queue, detector, log), so the service's camera
path can be exercised on the simulator. The rendered peer is where the peer *says* it is:
frames for plumbing and load, not for measuring anyone's position.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from skyfix.errors import GeometryError

#: (lat_deg, lon_deg, ellipsoidal alt_m) of this drone, or None before the first fix
OwnPosition = Callable[[], tuple[float, float, float] | None]
#: (lat_deg, lon_deg, ellipsoidal alt_m) of each peer heard
PeerPositions = Callable[[], list[tuple[float, float, float]]]


class SimCamera:
    """A frame source (call it): uint8 ``(H, W)`` sky frames with the nearest peer, or None when there is
    nothing to point at. ``width``/``hfov_deg`` the rendered camera."""

    def __init__(self, own: OwnPosition, peers: PeerPositions, *, width: int = 1280, height: int = 720,
                 hfov_deg: float = 60.0, seed: int = 0) -> None:
        from skyfix.camera import Camera
        from skyfix.crps.model import DroneModel

        self.own, self.peers = own, peers
        self.camera = Camera.from_fov(width, height, hfov_deg)
        self.model = DroneModel(arms=4, span_m=0.5)
        self._rng = np.random.default_rng(seed)

    def __call__(self) -> np.ndarray | None:
        from skyfix.camera import CameraPose
        from skyfix.datasets.drone_view import TargetPose, render_drone_view
        from skyfix.geo import inverse

        me = self.own()
        peers = self.peers()
        if me is None or not peers:
            return None
        lat, lon, alt = me
        pts = np.asarray(peers, dtype=float)
        bearings_deg, dists_m = inverse(lat, lon, pts[:, 0], pts[:, 1])
        k = int(np.argmin(dists_m))
        bearing_deg, dist_m = float(bearings_deg[k]), float(dists_m[k])
        elevation_deg = math.degrees(math.atan2(peers[k][2] - alt, max(dist_m, 1e-3)))
        pose = CameraPose(lat, lon, alt, yaw_deg=bearing_deg, gimbal_pitch_deg=elevation_deg, stabilized=True)
        try:
            view = render_drone_view(self.camera, pose, TargetPose(*peers[k], yaw_deg=30.0), self.model,
                                     supersample=4, blur_sigma_px=0.7, noise_sigma=0.01, rng=self._rng)
        except GeometryError:  # the peer is at the camera (same position broadcast): nothing to render
            return None
        return np.clip(view.image * 255.0, 0, 255).astype(np.uint8)
