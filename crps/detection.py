"""What a drone detector returns, and the protocol a user's own detector implements.

A :class:`Detection` is pixel-space only; :func:`skyfix.crps.observe` turns it into
a range and bearing with the camera, the helper pose and the target's size.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from skyfix import validate
from skyfix.errors import InputError

__all__ = ["BoxDetector", "Detection", "Detector", "Roi", "to_gray"]

#: Region of interest (u0, v0, u1, v1) in pixels, end-exclusive.
Roi = tuple[int, int, int, int]
Kind = Literal["silhouette", "marker", "box", "model"]


@dataclass(frozen=True)
class Detection:
    """One detected target in one image (raw pixel coordinates, OpenCV convention).

    ``centroid_uv`` (2,) the target centre; ``centroid_cov_px2`` (2, 2) its covariance;
    ``bbox_px`` (u0, v0, u1, v1) end-exclusive; ``score`` detector confidence (higher is
    better; for silhouettes the signal-to-noise ratio of the integrated contrast).
    Size, by ``kind``:

    * ``"silhouette"``: ``moments_px2`` (2, 2) second moments of the silhouette with the
      blur removed, and ``moments_sigma_rel`` the 1-sigma relative error of the RMS
      along the major axis (``sqrt`` of the largest eigenvalue);
    * ``"marker"``: ``size_px`` the on-axis-equivalent apparent side, focal / PnP range of
      a unit-sized marker, with ``size_sigma_px``; ``marker_id`` the decoded identity;
    * ``"box"``: ``size_px`` the raw box width in pixels, ``size_sigma_px`` its 1-sigma;
    * ``"model"``: a silhouette refined by :class:`~skyfix.crps.fit.SilhouetteFit`:
      ``size_px`` the on-axis apparent span (focal x span / range), ``size_sigma_px`` its 1-sigma
      from the pixels' noise, ``size_model_sigma_rel`` the relative 1-sigma of the model error,
      which stays fixed while the target keeps its attitude (a tracker does not average it).
    """

    centroid_uv: np.ndarray
    centroid_cov_px2: np.ndarray
    bbox_px: tuple[int, int, int, int]
    score: float
    kind: Kind = "silhouette"
    moments_px2: np.ndarray | None = None
    moments_sigma_rel: float = 0.0
    size_px: float = float("nan")
    size_sigma_px: float = 0.0
    marker_id: int | None = None
    time_s: float = 0.0
    size_model_sigma_rel: float = 0.0

    def __post_init__(self) -> None:
        c = validate.finite_array("Detection.centroid_uv", self.centroid_uv).reshape(-1)
        if c.shape != (2,):
            raise InputError(f"Detection.centroid_uv must be (2,), got {c.shape}")
        object.__setattr__(self, "centroid_uv", c)
        object.__setattr__(self, "centroid_cov_px2",
                           validate.covariance("Detection.centroid_cov_px2", self.centroid_cov_px2, 2))
        if self.kind not in ("silhouette", "marker", "box", "model"):
            raise InputError(f"Detection.kind must be 'silhouette', 'marker', 'box' or 'model', got {self.kind!r}")
        if self.kind == "silhouette":
            if self.moments_px2 is None:
                raise InputError("a silhouette Detection needs moments_px2")
            object.__setattr__(self, "moments_px2", validate.covariance("Detection.moments_px2", self.moments_px2, 2))
        elif not (np.isfinite(self.size_px) and self.size_px > 0):
            raise InputError(f"a {self.kind} Detection needs size_px > 0, got {self.size_px}")
        object.__setattr__(self, "time_s", validate.finite_scalar("Detection.time_s", self.time_s))
        if validate.finite_scalar("Detection.size_model_sigma_rel", self.size_model_sigma_rel) < 0:
            raise InputError(f"Detection.size_model_sigma_rel must be >= 0, got {self.size_model_sigma_rel}")

    @property
    def major_rms_px(self) -> float:
        """RMS extent of the silhouette along its major axis, pixels (NaN for other kinds)."""
        if self.moments_px2 is None:
            return float("nan")
        return float(np.sqrt(max(np.linalg.eigvalsh(self.moments_px2)[-1], 0.0)))

    @property
    def extent_px(self) -> float:
        """A rough apparent size in pixels for gating and ROIs (4 x major RMS or size_px)."""
        return 4.0 * self.major_rms_px if self.kind == "silhouette" else float(self.size_px)


@runtime_checkable
class Detector(Protocol):
    """Anything that finds targets in an image: ``detector(image, roi=None) -> list[Detection]``.

    ``image`` is ``(H, W)`` or ``(H, W, 3)``; ``roi`` restricts the search (pixels,
    end-exclusive); returned coordinates are always full-image pixels.
    """

    def __call__(self, image: np.ndarray, roi: Roi | None = None) -> list[Detection]: ...


def to_gray(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Grey float32 ``(H, W)`` in about [0, 1] from uint8/uint16/float, grey or BGR."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        import cv2

        code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        img = cv2.cvtColor(img if img.dtype != np.float64 else img.astype(np.float32), code)
    if img.ndim != 2 or img.shape[0] < 8 or img.shape[1] < 8:
        raise InputError(f"{name} must be (H, W) or (H, W, 3) with H, W >= 8, got shape {np.shape(image)}")
    if img.dtype == np.uint8:
        return img.astype(np.float32) * np.float32(1.0 / 255.0)
    if img.dtype == np.uint16:
        return img.astype(np.float32) * np.float32(1.0 / 65535.0)
    if not np.issubdtype(img.dtype, np.floating):
        raise InputError(f"{name} must be uint8, uint16 or float, got dtype {img.dtype}")
    out = img.astype(np.float32, copy=False)
    if not np.isfinite(out).all():
        raise InputError(f"{name} contains NaN or infinite pixels")
    return out


class BoxDetector:
    """Adapt a user model returning boxes with scores to the :class:`Detector` protocol.

    ``model(image) -> (boxes (N, 4) u0, v0, u1, v1 pixels, scores (N,))``. Boxes scoring
    below ``min_score`` are dropped. With ``refine`` (e.g. a
    :class:`~skyfix.crps.silhouette.SilhouetteDetector`) each box is re-measured by that
    detector inside the box, which gives sub-pixel moments instead of a box width;
    otherwise the box width is the size with ``box_sigma_px`` uncertainty per edge.
    """

    def __init__(self, model: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], *,
                 min_score: float = 0.5, refine: Detector | None = None, box_sigma_px: float = 1.0) -> None:
        if not callable(model):
            raise InputError(f"BoxDetector model must be callable, got {type(model).__name__}")
        self.model = model
        self.min_score = validate.finite_scalar("min_score", min_score)
        self.refine = refine
        self.box_sigma_px = validate.positive_scalar("box_sigma_px", box_sigma_px)

    def __call__(self, image: np.ndarray, roi: Roi | None = None) -> list[Detection]:
        h, w = np.shape(image)[:2]
        u0, v0, u1, v1 = roi if roi is not None else (0, 0, w, h)
        boxes, scores = self.model(np.asarray(image)[v0:v1, u0:u1])
        boxes = validate.finite_array("boxes", boxes).reshape(-1, 4) + np.array([u0, v0, u0, v0])
        scores = validate.finite_array("scores", scores).reshape(-1)
        if scores.shape[0] != boxes.shape[0]:
            raise InputError(f"the box model returned {boxes.shape[0]} boxes but {scores.shape[0]} scores")
        out: list[Detection] = []
        for box, score in zip(boxes, scores, strict=True):
            if score < self.min_score or box[2] <= box[0] or box[3] <= box[1]:
                continue
            ibox = (int(np.floor(box[0])), int(np.floor(box[1])), int(np.ceil(box[2])), int(np.ceil(box[3])))
            if self.refine is not None:
                found = self.refine(image, roi=_grow(ibox, 1.0, w, h))
                if found:
                    best = max(found, key=lambda d: d.score)
                    out.append(Detection(best.centroid_uv, best.centroid_cov_px2, best.bbox_px, float(score),
                                         best.kind, best.moments_px2, best.moments_sigma_rel,
                                         best.size_px, best.size_sigma_px, best.marker_id, best.time_s))
                continue
            centre = np.array([(box[0] + box[2]) / 2.0 - 0.5, (box[1] + box[3]) / 2.0 - 0.5])
            var = self.box_sigma_px ** 2 / 2.0
            out.append(Detection(centre, np.eye(2) * var, ibox, float(score), "box",
                                 size_px=float(box[2] - box[0]), size_sigma_px=self.box_sigma_px * np.sqrt(2.0)))
        return out


def _grow(box: tuple[int, int, int, int], fraction: float, width: int, height: int) -> Roi:
    """``box`` grown by ``fraction`` of its larger side plus 12 px on each side, clipped to the image."""
    u0, v0, u1, v1 = box
    mu = mv = int(np.ceil(fraction * max(u1 - u0, v1 - v0))) + 12
    return max(u0 - mu, 0), max(v0 - mv, 0), min(u1 + mu, width), min(v1 + mv, height)
