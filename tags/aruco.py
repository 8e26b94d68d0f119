"""AprilTag / ArUco boards through ``cv2.aruco`` (OpenCV >= 4.7 API, checked on 5.0).

A board is a grid of square markers on the floor, in the same field frame as the tile
tags (x east, y north, metres; marker (col, row) centred at ``origin_xy_m + (col, row) *
spacing_m``, row 0 south; id = ``first_id + row * cols + col``). Every marker is printed
as seen from above with its top edge to the north, so OpenCV's corner order (top-left,
top-right, bottom-right, bottom-left of the printed marker) is NW, NE, SE, SW.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import msgspec
import numpy as np
from msgspec import Meta

from skyfix import validate
from skyfix.camera import Camera
from skyfix.errors import DataError, EstimationError, InputError
from skyfix.jsonfile import convert, json_schema
from skyfix.tags.blur import motion_blur_px
from skyfix.tags.image import as_rgb_u8
from skyfix.tags.locate import BLUR_FLAG_PX, ideal_pixels
from skyfix.tags.pose import DOWN_MOUNT, AttitudePrior, TagFix, make_fix, solve_pose
from skyfix.tags.raster import fill_rects
from skyfix.tags.reference import consistent_tags

FORMAT = "skyfix.tags.ArucoField"
#: Dictionaries by name: AprilTag 36h11 and the usual ArUco ones.
DICTIONARIES = {name[5:].lower(): getattr(cv2.aruco, name) for name in dir(cv2.aruco)
                if name.startswith("DICT_") and name[5:] == name[5:].upper()}


def dictionary(name: str):
    """``cv2.aruco.Dictionary`` by name, e.g. ``"apriltag_36h11"``, ``"4x4_50"``."""
    key = str(name).lower()
    if key not in DICTIONARIES:
        raise InputError(f"unknown marker dictionary {name!r}; expected one of {sorted(DICTIONARIES)}")
    return cv2.aruco.getPredefinedDictionary(DICTIONARIES[key])


@dataclass(frozen=True)
class ArucoField:
    """A rows x cols grid of markers of side ``marker_m`` (black border included)."""

    dictionary_name: str = "apriltag_36h11"
    rows: int = 10
    cols: int = 10
    marker_m: float = 0.1
    spacing_m: float = 0.25
    first_id: int = 0
    origin_xy_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        d = dictionary(self.dictionary_name)
        for name in ("rows", "cols"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise InputError(f"{name} must be a positive integer, got {v!r}")
        n_ids = d.bytesList.shape[0]
        if self.first_id < 0 or self.first_id + self.rows * self.cols > n_ids:
            raise InputError(f"{self.rows * self.cols} markers from id {self.first_id} do not fit the "
                             f"{n_ids} ids of {self.dictionary_name}")
        object.__setattr__(self, "marker_m", validate.positive_scalar("marker_m", self.marker_m))
        object.__setattr__(self, "spacing_m", validate.positive_scalar("spacing_m", self.spacing_m))
        if self.spacing_m < 1.2 * self.marker_m:
            raise InputError(f"spacing_m={self.spacing_m} must leave a white quiet zone: >= 1.2 x marker_m")
        o = validate.finite_array("origin_xy_m", self.origin_xy_m).reshape(2)
        object.__setattr__(self, "origin_xy_m", (float(o[0]), float(o[1])))

    @property
    def ids(self) -> np.ndarray:
        return self.first_id + np.arange(self.rows * self.cols)

    def corners_m(self, ids) -> np.ndarray:
        """Corners ``(N, 4, 2)`` (NW, NE, SE, SW; field x east, y north) of marker ``ids``."""
        idx = np.asarray(ids, dtype=int).ravel() - self.first_id
        row, col = np.divmod(idx, self.cols)
        c = np.stack((self.origin_xy_m[0] + col * self.spacing_m,
                      self.origin_xy_m[1] + row * self.spacing_m), axis=1)
        h = self.marker_m / 2.0
        return c[:, None, :] + np.array([[-h, h], [h, h], [h, -h], [-h, -h]])[None]

    def bounds_m(self, margin_m: float = 0.0) -> tuple[float, float, float, float]:
        c = self.corners_m(self.ids).reshape(-1, 2)
        return (float(c[:, 0].min() - margin_m), float(c[:, 1].min() - margin_m),
                float(c[:, 0].max() + margin_m), float(c[:, 1].max() + margin_m))

    def rasterise(self, metres_per_px: float, margin_m: float = 0.1) -> tuple[np.ndarray, tuple[float, float]]:
        """The board as sRGB float32 ``(H, W, 3)`` (row 0 north) and its centre (x, y), metres."""
        mpp = validate.positive_scalar("metres_per_px", metres_per_px)
        x0, y0, x1, y1 = self.bounds_m(margin_m)
        w, h = math.ceil((x1 - x0) / mpp), math.ceil((y1 - y0) / mpp)
        if max(w, h) > 30000:
            raise InputError(f"rendering at {mpp} m/px needs {w} x {h} px; at most 30000 per side")
        image = np.ones((h, w, 3), np.float32)
        d = dictionary(self.dictionary_name)
        cells = d.markerSize + 2
        cell_m = self.marker_m / cells
        rects = []
        for mid, corner in zip(self.ids, self.corners_m(self.ids), strict=True):
            bits = cv2.aruco.generateImageMarker(d, int(mid), cells, borderBits=1)
            rr, cc = np.nonzero(bits < 128)
            left, top = corner[0]
            xa = left + cc * cell_m
            yt = top - rr * cell_m
            rects.append(np.stack(((xa - x0) / mpp, (y1 - yt) / mpp,
                                   (xa + cell_m - x0) / mpp, (y1 - yt + cell_m) / mpp), axis=1))
        rects = np.concatenate(rects)
        fill_rects(image, rects, np.zeros((len(rects), 3)))
        return image, (x0 + w * mpp / 2.0, y1 - h * mpp / 2.0)

    def write_png(self, path: str | Path, dpi: float = 150.0) -> Path:
        """Print-ready PNG at ``dpi``."""
        image, _ = self.rasterise(0.0254 / validate.positive_scalar("dpi", dpi), margin_m=0.02)
        out = Path(path)
        if not cv2.imwrite(str(out), np.round(image * 255).astype(np.uint8)):
            raise DataError(f"could not write PNG {out}")
        return out

    def to_dict(self) -> dict:
        return {"format": FORMAT, "version": 1, "dictionary": self.dictionary_name, "rows": self.rows,
                "cols": self.cols, "marker_m": self.marker_m, "spacing_m": self.spacing_m,
                "first_id": self.first_id, "origin_xy_m": list(self.origin_xy_m)}

    @classmethod
    def from_dict(cls, d: dict, source: str = "marker board") -> ArucoField:
        """Board from its saved form (:class:`ArucoFieldFile`); DataError naming ``source`` and the key."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise DataError(f"{source}: not a skyfix marker board (expected format {FORMAT!r})")
        f = convert(d, ArucoFieldFile, source)
        try:
            return cls(f.dictionary, f.rows, f.cols, f.marker_m, f.spacing_m, f.first_id, f.origin_xy_m)
        except InputError as exc:
            raise DataError(f"{source}: {exc}") from exc

    def save(self, path: str | Path) -> Path:
        out = Path(path)
        out.write_text(json.dumps(self.to_dict(), indent=1))
        return out


class ArucoFieldFile(msgspec.Struct, kw_only=True):
    """A marker board as :meth:`ArucoField.save` writes it (x east, y north, metres; row 0 south).

    Example:
        >>> board = convert({"format": FORMAT, "dictionary": "4x4_50", "rows": 2, "cols": 3, "marker_m": 0.2,
        ...                  "spacing_m": 0.3}, ArucoFieldFile, "board.json")
        >>> board.first_id, board.origin_xy_m
        (0, (0.0, 0.0))
    """

    format: Literal["skyfix.tags.ArucoField"]
    version: Literal[1] = 1
    dictionary: Annotated[str, Meta(extra_json_schema={"enum": sorted(DICTIONARIES)})]
    rows: Annotated[int, Meta(ge=1)]
    cols: Annotated[int, Meta(ge=1)]
    marker_m: Annotated[float, Meta(gt=0, description="marker side, black border included")]
    spacing_m: Annotated[float, Meta(gt=0, description="marker centre to centre, >= 1.2 marker_m")]
    first_id: Annotated[int, Meta(ge=0)] = 0
    origin_xy_m: tuple[float, float] = (0.0, 0.0)


def aruco_field_json_schema() -> dict:
    """JSON Schema of the marker board file (:class:`ArucoFieldFile`), published in docs/schemas/."""
    return json_schema(ArucoFieldFile) | {"title": "skyfix marker board"}


def make_detector(board: ArucoField) -> cv2.aruco.ArucoDetector:
    """An ``ArucoDetector`` for the board's dictionary with sub-pixel corner refinement."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(dictionary(board.dictionary_name), params)


def corner_pixel_sigma(side_px: np.ndarray, blur_px: float) -> np.ndarray:
    """1-sigma of a refined marker corner, pixels: it fits ~side pixels of each edge, so the
    error grows as 1/sqrt(side); a blur streak adds a fraction of its length."""
    return 0.15 * np.sqrt(40.0 / np.maximum(side_px, 4.0)) + 0.1 * blur_px


def fix_from_corners(corners_px: np.ndarray, ids: np.ndarray, board: ArucoField, camera: Camera, *,
                     grey: np.ndarray | None = None, prior: AttitudePrior | None = None,
                     mount: np.ndarray = DOWN_MOUNT, min_tags: int = 1, time_s: float = 0.0,
                     source_id: str = "") -> TagFix:
    """Pose from marker corners ``(N, 4, 2)`` (raw pixels, OpenCV order) and their ``ids``."""
    corners_px = np.asarray(corners_px, float).reshape(-1, 4, 2)
    ids = np.asarray(ids, int).ravel()
    known = (ids >= board.first_id) & (ids < board.first_id + board.rows * board.cols)
    if known.sum() < min_tags:
        raise EstimationError(f"{len(ids)} markers detected, {int(known.sum())} on this board; need {min_tags}")
    ground = board.corners_m(ids[known])
    uv = ideal_pixels(camera, corners_px[known].reshape(-1, 2)).reshape(-1, 4, 2)
    keep = np.ones(len(uv), bool)
    if len(uv) >= 2:
        keep = consistent_tags(ground, uv, board.spacing_m, board.marker_m, min_support=min(2, len(uv)))
    if keep.sum() < min_tags:
        raise EstimationError(f"{int(known.sum())} markers, {int(keep.sum())} consistent with the board")
    side = np.linalg.norm(np.diff(uv[keep], axis=1, append=uv[keep][:, :1]), axis=2).mean(axis=1)
    blur = motion_blur_px(grey) if grey is not None else 0.0
    sol = solve_pose(ground[keep].reshape(-1, 2), uv[keep].reshape(-1, 2), camera.K, prior=prior,
                     mount=mount, sigma_px=np.repeat(corner_pixel_sigma(side, blur), 4))
    if sol.rms_px > 3.0:
        raise EstimationError(f"marker corners fit the pose with {sol.rms_px:.1f} px RMS; expected < 3 px")
    return make_fix(sol, int(keep.sum()), len(ids) - int(keep.sum()), blur, BLUR_FLAG_PX, time_s, source_id)


def locate_aruco(image, board: ArucoField, camera: Camera, *, prior: AttitudePrior | None = None,
                 mount: np.ndarray = DOWN_MOUNT, detector: cv2.aruco.ArucoDetector | None = None,
                 min_tags: int = 1, time_s: float = 0.0, source_id: str = "") -> TagFix:
    """Detect the board's markers in an RGB frame and return the vehicle's :class:`TagFix`.

    Uses every marker corner in one planar PnP (IPPE, both solutions scored, the IMU's
    roll/pitch picks between them; see :func:`~skyfix.tags.pose.solve_pose`).
    """
    if not isinstance(board, ArucoField):
        raise InputError(f"board must be an ArucoField, got {type(board).__name__}")
    rgb = as_rgb_u8(image)
    if rgb.shape[:2] != (camera.height, camera.width):
        raise InputError(f"image is {rgb.shape[1]}x{rgb.shape[0]} but the camera is {camera.width}x{camera.height}")
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    det = detector if detector is not None else make_detector(board)
    corners, ids, _ = det.detectMarkers(grey)
    if ids is None or len(ids) == 0:
        raise EstimationError("no markers of the board's dictionary found in the image")
    return fix_from_corners(np.concatenate([c.reshape(1, 4, 2) for c in corners]), ids.ravel(), board, camera,
                            grey=grey, prior=prior, mount=mount, min_tags=min_tags, time_s=time_s,
                            source_id=source_id)
