"""Multi-frame fire tracking: associate hotspots across frames and fuse their positions.

Each fire is a 2-D position (east, north) in a local ENU frame with a covariance. A
new frame's geolocated hotspots are matched to fires by Mahalanobis distance (gate on
the innovation covariance plus the fire's own extent, so a growing fire whose
centroid wanders still matches) with an optimal assignment; matched fires get a
Kalman update (information-weighted least squares with a small random-walk process
noise, because a burning front moves), unmatched hotspots start new fires. A fire
that stays undetected while inside the camera's view for ``miss_limit`` frames is
reported out; it is re-lit if it is seen again at the same place.

Pose errors are taken as independent between frames (see :class:`PoseUncertainty`);
with a constant GNSS bias the fused sigma would be optimistic by that bias.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from skyfix import validate
from skyfix.camera import Camera, CameraPose, world_to_pixel
from skyfix.errors import InputError, SkyfixError
from skyfix.geo import LocalFrame
from skyfix.thermal.detect import DEFAULT_KELVIN_PER_COUNT, Hotspot, detect_hotspots
from skyfix.thermal.geolocate import locate_in_frame
from skyfix.thermal.ground import DemGround, FlatGround, as_ground
from skyfix.thermal.pose import PoseUncertainty

log = logging.getLogger(__name__)

#: Chi-square (2 dof) gate at 99.9 %.
GATE_CHI2 = 13.8


@dataclass(frozen=True)
class Fire:
    """A tracked fire. ``lat_deg``/``lon_deg`` WGS84, ``alt_m`` ellipsoidal; ``cov_en_m2``
    the 2x2 horizontal covariance (east, north), m^2; ``sigma_m`` its RMS radial error
    sqrt(trace) (the 2-D "DRMS": 2 * sigma_m contains the true position with >= 95 %
    probability for a correct covariance); ``n_observations`` frames that saw it;
    ``first_seen_s``/``last_seen_s`` times; ``area_m2`` last hot area on the ground;
    ``peak`` last peak (deg C, or 8-bit level); ``burning`` False once reported out."""

    fire_id: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    cov_en_m2: np.ndarray
    n_observations: int
    first_seen_s: float
    last_seen_s: float
    area_m2: float
    peak: float
    burning: bool

    @property
    def sigma_m(self) -> float:
        """RMS horizontal error, metres: sqrt(trace of ``cov_en_m2``)."""
        return float(math.sqrt(self.cov_en_m2[0, 0] + self.cov_en_m2[1, 1]))

    @property
    def sigma_major_m(self) -> float:
        """1-sigma along the worst horizontal direction, metres."""
        return float(math.sqrt(np.linalg.eigvalsh(self.cov_en_m2).max()))


@dataclass
class _Track:
    fire_id: int
    en_m: np.ndarray
    cov_m2: np.ndarray
    up_m: float
    n_obs: int
    first_s: float
    last_s: float
    area_m2: float
    peak: float
    misses: int = 0
    burning: bool = True
    history: list = field(default_factory=list)


@dataclass(frozen=True)
class TrackerSettings:
    """Tuning of :class:`FireTracker` (units in the names)."""

    #: Random walk of a fire's centroid, m per sqrt(s): fronts move, flames flicker.
    drift_m_per_sqrt_s: float = 0.05
    #: Frames in view without a detection before a fire is reported out.
    miss_limit: int = 5
    #: Observations before a fire is reported (1 = report on first sight).
    min_observations: int = 2
    #: Detection threshold (deg C for radiometric, 8-bit level or None=auto for 8-bit).
    threshold: float | None = None
    palette: str = "white-hot"
    min_area_px: int = 4
    kelvin_per_count: float = DEFAULT_KELVIN_PER_COUNT


def ground_area_m2(camera: Camera, cam_enu_m: np.ndarray, pts_enu_m: np.ndarray, area_px: np.ndarray) -> np.ndarray:
    """Hot area on the ground ``(N,)`` m^2 of hotspots of ``area_px`` pixels whose ground
    points are ``pts_enu_m`` ``(N, 3)``: pixels x range^2 / (fx fy) / cos(incidence)."""
    ray = pts_enu_m - cam_enu_m
    rng2 = np.einsum("ij,ij->i", ray, ray)
    cos_inc = np.abs(ray[:, 2]) / np.sqrt(rng2)
    return np.asarray(area_px, float) * rng2 / (camera.fx * camera.fy) / cos_inc


class FireTracker:
    """Feed ``update(frame, pose, time_s)``; read ``fires``.

    ``camera``: the thermal camera. ``ground_alt_m``: ground ellipsoidal height (m), or a
    :class:`FlatGround`/:class:`DemGround`. ``uncertainty``: per-frame pose and pixel
    1-sigma errors. ``frame``: local ENU frame to track in (default: created near the
    first pose).

    Example:
        Three frames of the same fire (300 deg C, 4 x 4 px) from a hovering drone 100 m up
        make one fire seen three times:

        >>> frame = np.full((120, 160), 20.0, np.float32)
        >>> frame[40:44, 100:104] = 300.0
        >>> tracker = FireTracker(Camera.from_fov(160, 120, 50.0), FlatGround(400.0))
        >>> for t_s in (0.0, 1.0, 2.0):
        ...     ids = tracker.update(frame, CameraPose(47.0, 8.0, 500.0), t_s)
        >>> [(f.fire_id, f.n_observations, f.burning) for f in tracker.fires]
        [(1, 3, True)]
        >>> east_m, north_m, _ = LocalFrame(47.0, 8.0, 400.0).to_enu(tracker.fires[0].lat_deg, tracker.fires[0].lon_deg,
        ...                                                          400.0)
        >>> round(float(east_m), 1), round(float(north_m), 1)
        (12.8, 10.5)
    """

    def __init__(self, camera: Camera, ground_alt_m: float | FlatGround | DemGround, *,
                 uncertainty: PoseUncertainty | None = None, settings: TrackerSettings | None = None,
                 frame: LocalFrame | None = None) -> None:
        if not isinstance(camera, Camera):
            raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
        self.camera = camera
        self.ground = as_ground(ground_alt_m)
        self.uncertainty = uncertainty if uncertainty is not None else PoseUncertainty()
        self.settings = settings if settings is not None else TrackerSettings()
        self.frame = frame
        self._tracks: list[_Track] = []
        self._next_id = 1
        self.frames_used = 0
        self.frames_dropped = 0
        self.last_hotspots: list[Hotspot] = []

    def update(self, image: np.ndarray, pose: CameraPose, time_s: float) -> list[int]:
        """Process one frame; returns the ids of the fires observed in it.

        A bad frame or pose (wrong dtype, constant/blank frame, ray missing the ground)
        is logged and dropped: the tracker keeps going.
        """
        try:
            t = validate.finite_scalar("time_s", time_s)
            if not isinstance(pose, CameraPose):
                raise InputError(f"pose must be a CameraPose, got {type(pose).__name__}")
            s = self.settings
            spots = detect_hotspots(image, threshold=s.threshold, palette=s.palette,
                                    min_area_px=s.min_area_px, kelvin_per_count=s.kelvin_per_count)
            return self.update_hotspots(spots, pose, t)
        except SkyfixError as exc:
            self.frames_dropped += 1
            log.warning("thermal frame at t=%s dropped: %s", time_s, exc)
            return []

    def update_hotspots(self, hotspots: list[Hotspot], pose: CameraPose, time_s: float) -> list[int]:
        """Like :meth:`update` for hotspots already detected in a frame (raises on bad input)."""
        t = validate.finite_scalar("time_s", time_s)
        if self.frame is None:
            self.frame = LocalFrame(pose.lat_deg, pose.lon_deg, self.ground.alt_m)
        self.last_hotspots = list(hotspots)
        self.frames_used += 1
        if hotspots:
            uv = np.array([[h.u_px, h.v_px] for h in hotspots])
            pts, cov = locate_in_frame(self.camera, pose, uv, self.ground, self.frame, self.uncertainty)
            areas = self._ground_areas(pose, pts, hotspots)
        else:
            pts, cov, areas = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
        self._predict(t)
        matched = self._associate(pts[:, :2], cov[:, :2, :2])
        seen = []
        for j, trk in enumerate(self._tracks):
            i = matched.get(j)
            if i is None:
                continue
            self._correct(trk, pts[i], cov[i, :2, :2], t, areas[i], hotspots[i].peak)
            seen.append(trk.fire_id)
        used = set(matched.values())
        for i in range(len(hotspots)):
            if i not in used:
                trk = _Track(self._next_id, pts[i, :2].copy(), cov[i, :2, :2].copy(), float(pts[i, 2]),
                             1, t, t, float(areas[i]), hotspots[i].peak)
                trk.history.append((t, *pts[i, :2]))
                self._tracks.append(trk)
                self._next_id += 1
                seen.append(trk.fire_id)
        self._count_misses(pose, set(seen))
        return seen

    def _ground_areas(self, pose: CameraPose, pts: np.ndarray, hotspots: list[Hotspot]) -> np.ndarray:
        cam_enu, _ = pose.in_frame(self.frame)
        return ground_area_m2(self.camera, cam_enu, pts, np.array([h.area_px for h in hotspots], float))

    def _predict(self, t: float) -> None:
        q = self.settings.drift_m_per_sqrt_s ** 2
        for trk in self._tracks:
            dt = max(t - trk.last_s, 0.0)
            trk.cov_m2 = trk.cov_m2 + q * dt * np.eye(2) if dt > 0 else trk.cov_m2

    def _associate(self, z: np.ndarray, r: np.ndarray) -> dict[int, int]:
        """Optimal gated assignment {track index: hotspot index}."""
        if not self._tracks or z.shape[0] == 0:
            return {}
        cost = np.full((len(self._tracks), z.shape[0]), 1e9)
        for j, trk in enumerate(self._tracks):
            extent_m2 = trk.area_m2 / math.pi  # radius^2 of a disc of that area
            s = trk.cov_m2 + r + extent_m2 * np.eye(2)
            nu = z - trk.en_m
            d2 = np.einsum("ni,nij,nj->n", nu, np.linalg.inv(s), nu)
            cost[j] = np.where(d2 <= GATE_CHI2, d2, 1e9)
        rows, cols = linear_sum_assignment(cost)
        return {int(j): int(i) for j, i in zip(rows, cols, strict=True) if cost[j, i] < 1e9}

    def _correct(self, trk: _Track, p: np.ndarray, r: np.ndarray, t: float, area_m2: float,
                 peak: float) -> None:
        gain = trk.cov_m2 @ np.linalg.inv(trk.cov_m2 + r)
        trk.en_m = trk.en_m + gain @ (p[:2] - trk.en_m)
        trk.cov_m2 = (np.eye(2) - gain) @ trk.cov_m2
        trk.cov_m2 = 0.5 * (trk.cov_m2 + trk.cov_m2.T)
        trk.up_m = float(p[2])
        trk.n_obs += 1
        trk.last_s = t
        trk.area_m2 = float(area_m2)
        trk.peak = float(peak)
        trk.misses = 0
        trk.burning = True
        trk.history.append((t, *p[:2]))

    def _count_misses(self, pose: CameraPose, seen_ids: set[int]) -> None:
        """Count a miss for every burning fire inside the image that was not seen."""
        burning = [j for j, trk in enumerate(self._tracks) if trk.burning and trk.fire_id not in seen_ids]
        if not burning:
            return
        enu = np.array([[*self._tracks[j].en_m, self._tracks[j].up_m] for j in burning])
        uv = world_to_pixel(self.camera, pose, self.frame, enu)
        ok = np.isfinite(uv).all(axis=1)
        inside = np.zeros(len(burning), bool)
        inside[ok] = self.camera.in_image(uv[ok])
        for j, vis in zip(burning, inside, strict=True):
            if vis:
                trk = self._tracks[j]
                trk.misses += 1
                if trk.misses >= self.settings.miss_limit:
                    trk.burning = False

    @property
    def fires(self) -> list[Fire]:
        """Fires seen at least ``min_observations`` times (burning or out), by id."""
        return [self._report(trk) for trk in self._tracks if trk.n_obs >= self.settings.min_observations]

    def track_history(self, fire_id: int) -> np.ndarray:
        """``(K, 3)`` rows (time_s, east_m, north_m) of the single-frame fixes of one fire."""
        for trk in self._tracks:
            if trk.fire_id == fire_id:
                return np.array(trk.history)
        raise InputError(f"no fire with id {fire_id}")

    def _report(self, trk: _Track) -> Fire:
        lat, lon, alt = self.frame.to_geodetic(trk.en_m[0], trk.en_m[1], trk.up_m)
        r = self.frame.enu_rotation_at(float(lat), float(lon))[:2, :2]
        cov = r.T @ trk.cov_m2 @ r
        cov.setflags(write=False)
        return Fire(trk.fire_id, float(lat), float(lon), float(alt), cov, trk.n_obs, trk.first_s,
                    trk.last_s, trk.area_m2, trk.peak, trk.burning)
