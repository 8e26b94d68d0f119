"""Which hotspot of which frame is which fire: the sightings a joint estimate is built on.

Every hotspot is first geolocated on its own (its frame's logged pose, the ground or DEM);
the single-frame points are clustered (complete linkage: no two points of one fire
farther apart than ``gate_m``), so a constant GNSS or boresight error that a
frame-by-frame tracker would see as a moving fire does not split it. Clusters seen in
fewer than ``min_sightings`` frames are dropped (reflections, one-frame glints); a frame
with two hotspots in one cluster keeps the one nearer the cluster's centre.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage

from skyfix import validate
from skyfix.camera import Camera
from skyfix.errors import EstimationError, InputError, SkyfixError
from skyfix.geo import LocalFrame
from skyfix.thermal.detect import Hotspot
from skyfix.thermal.ground import DemGround, FlatGround, as_ground, ground_points
from skyfix.thermal.poselog import PoseLog
from skyfix.thermal.tracker import ground_area_m2

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Sightings:
    """Sightings ``(N,)`` sorted by camera stamp ``time_s``: centroid ``uv_px`` ``(N, 2)``,
    ``fire_index`` into the ``(F,)`` per-fire arrays: ``fire_ids``, ``initial_en_m``
    ``(F, 2)`` (cluster centre, ENU m in ``frame``), ``area_m2`` and ``peak`` (latest).
    ``pool`` ``(P, 5)``: every geolocated hotspot of the flight (stamp s, u px, v px,
    ground area m^2, peak), assigned or not, for re-association."""

    frame: LocalFrame
    time_s: np.ndarray
    uv_px: np.ndarray
    fire_index: np.ndarray
    fire_ids: np.ndarray
    initial_en_m: np.ndarray
    area_m2: np.ndarray
    peak: np.ndarray
    pool: np.ndarray

    @property
    def n(self) -> int:
        """Number of sightings."""
        return int(self.time_s.size)

    @property
    def n_fires(self) -> int:
        """Number of fires."""
        return int(self.fire_ids.size)

    def frames(self) -> list[slice]:
        """Row slices of the sightings of each frame (equal stamps), in order."""
        cut = np.flatnonzero(np.diff(self.time_s) > 0) + 1
        edges = [0, *cut.tolist(), self.n]
        return [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]

    def merged(self, fire_en_m: np.ndarray, merge_m: float) -> Sightings:
        """Fires whose positions ``fire_en_m`` ``(F, 2)`` (ENU m in :attr:`frame`) are within
        ``merge_m`` of each other (single linkage) become one; its initial position is
        their sightings-weighted mean. Returns ``self`` when nothing merges."""
        if self.n_fires < 2:
            return self
        groups = fcluster(linkage(fire_en_m, "single"), merge_m, criterion="distance")
        if np.unique(groups).size == self.n_fires:
            return self
        ids, new_of_old = np.unique(groups, return_inverse=True)
        index = new_of_old[self.fire_index]
        counts = np.bincount(self.fire_index, minlength=self.n_fires).astype(float)
        init = np.array([np.average(fire_en_m[new_of_old == g], axis=0, weights=counts[new_of_old == g])
                         for g in range(ids.size)])
        last = [np.flatnonzero(index == g)[-1] for g in range(ids.size)]
        area = np.array([self.area_m2[self.fire_index[k]] for k in last])
        peak = np.array([self.peak[self.fire_index[k]] for k in last])
        return Sightings(self.frame, self.time_s, self.uv_px, index, np.arange(1, ids.size + 1), init, area, peak,
                         self.pool)

    def reassigned(self, pool_fire: np.ndarray, fire_en_m: np.ndarray, min_sightings: int = 3) -> Sightings:
        """Sightings from a new assignment ``pool_fire`` ``(P,)`` (fire index or -1) of the
        pool; fires with fewer than ``min_sightings`` are dropped, the others keep their
        position ``fire_en_m`` ``(F, 2)`` as the initial one."""
        pool_fire = np.asarray(pool_fire, int)
        counts = np.bincount(pool_fire[pool_fire >= 0], minlength=self.n_fires)
        keep_fire = np.flatnonzero(counts >= min_sightings)
        if keep_fire.size == 0:
            raise EstimationError(f"no fire seen in {min_sightings} or more frames")
        new_of_old = np.full(self.n_fires, -1)
        new_of_old[keep_fire] = np.arange(keep_fire.size)
        use = (pool_fire >= 0) & (new_of_old[np.maximum(pool_fire, 0)] >= 0)
        rows, index = self.pool[use], new_of_old[pool_fire[use]]
        return _build(self.frame, rows, index, fire_en_m[keep_fire], self.pool)


def _single_frame_points(camera: Camera, pose_log: PoseLog, detections, ground, frame: LocalFrame):
    rows = []
    for stamp, spots in detections:
        t = validate.finite_scalar("stamp", stamp)
        if not spots:
            continue
        try:
            pose = pose_log.pose_at(t)
            uv = np.array([[h.u_px, h.v_px] for h in spots])
            pts = ground_points(camera, pose, uv, ground, frame)
        except SkyfixError as exc:
            log.warning("frame at %.3f s dropped from the sightings: %s", t, exc)
            continue
        area = ground_area_m2(camera, pose.in_frame(frame)[0], pts, [h.area_px for h in spots])
        for h, p, a in zip(spots, pts, area, strict=True):
            rows.append((t, h.u_px, h.v_px, p[0], p[1], a, h.peak))
    return np.array(rows, float).reshape(-1, 7)


def associate(camera: Camera, pose_log: PoseLog, detections: list[tuple[float, list[Hotspot]]],
              ground: float | FlatGround | DemGround, *, frame: LocalFrame | None = None, gate_m: float = 15.0,
              min_sightings: int = 3) -> Sightings:
    """Sightings from ``detections`` (camera stamp s, hotspots of that frame) per frame.

    ``pose_log`` is read at the stamps as they are (no time offset); ``frame`` defaults
    to one at the first logged position, on the ground's median height.
    Raises :class:`EstimationError` when no fire is seen ``min_sightings`` times.
    """
    ground = as_ground(ground)
    if not isinstance(pose_log, PoseLog):
        raise InputError(f"pose_log must be a PoseLog, got {type(pose_log).__name__}")
    if frame is None:
        frame = LocalFrame(float(pose_log.lat_deg[0]), float(pose_log.lon_deg[0]), ground.alt_m)
    gate = validate.positive_scalar("gate_m", gate_m)
    rows = _single_frame_points(camera, pose_log, detections, ground, frame)
    if rows.shape[0] < min_sightings:
        raise EstimationError(f"{rows.shape[0]} geolocated hotspots: fewer than min_sightings={min_sightings}")
    labels = (fcluster(linkage(rows[:, 3:5], "complete"), gate, criterion="distance")
              if rows.shape[0] > 1 else np.ones(1, int))
    keep = np.zeros(rows.shape[0], bool)
    for lab in np.unique(labels):
        members = np.flatnonzero(labels == lab)
        centre = np.median(rows[members, 3:5], axis=0)
        dist = np.hypot(*(rows[members, 3:5] - centre).T)
        best: dict[float, tuple[float, int]] = {}
        for m, d in zip(members, dist, strict=True):
            if rows[m, 0] not in best or d < best[rows[m, 0]][0]:
                best[rows[m, 0]] = (d, m)
        if len(best) >= min_sightings:
            keep[[m for _, m in best.values()]] = True
    if not keep.any():
        raise EstimationError(f"no fire seen in {min_sightings} or more frames")
    order = np.argsort(rows[:, 0], kind="stable")
    rows, labels, keep = rows[order], labels[order], keep[order]
    ids, index = np.unique(labels[keep], return_inverse=True)
    init = np.array([np.median(rows[keep][index == i, 3:5], axis=0) for i in range(ids.size)])
    return _build(frame, rows[keep][:, [0, 1, 2, 5, 6]], index, init, rows[:, [0, 1, 2, 5, 6]])


def _build(frame: LocalFrame, rows: np.ndarray, index: np.ndarray, init: np.ndarray, pool: np.ndarray) -> Sightings:
    """Sightings from time-sorted ``rows`` (t, u, v, area, peak) and their fire ``index``."""
    order = np.argsort(rows[:, 0], kind="stable")
    rows, index = rows[order], index[order]
    n_fires = init.shape[0]
    last = [np.flatnonzero(index == i)[-1] for i in range(n_fires)]
    return Sightings(frame, rows[:, 0], rows[:, 1:3], index, np.arange(1, n_fires + 1), init,
                     rows[last, 3], rows[last, 4], pool)
