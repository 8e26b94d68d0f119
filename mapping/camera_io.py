"""Cameras with their lens model as JSON (the ``cal.json`` that ``skyfix lens`` reads and writes).

Format: ``{"width", "height", "fx_px", "fy_px", "cx_px", "cy_px", "model", "coefficients"}``
with ``model`` one of ``pinhole``, ``brown_conrady`` (k1 k2 p1 p2 k3), ``fisheye``
(k1 k2 k3 k4) or ``barrel`` (ImageMagick a b c d); extra keys (rms_px...) are kept aside.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

from skyfix.camera import Camera
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import DataError, InputError
from skyfix.jsonfile import read_json

__all__ = ["camera_from_dict", "camera_to_dict", "load_camera", "save_camera"]

_MODELS = {"brown_conrady": BrownConrady, "fisheye": Fisheye, "barrel": Barrel}


def camera_to_dict(camera: Camera, **extra) -> dict:
    """JSON-ready dict of ``camera``; ``extra`` items (e.g. ``rms_px``) are added as they are."""
    dist = camera.distortion
    model = next((name for name, cls in _MODELS.items() if isinstance(dist, cls)), None)
    if dist is not None and model is None:
        raise InputError(f"cannot serialise distortion model {type(dist).__name__}")
    return {"width": camera.width, "height": camera.height, "fx_px": camera.fx, "fy_px": camera.fy,
            "cx_px": camera.cx, "cy_px": camera.cy, "model": model or "pinhole",
            "coefficients": asdict(dist) if dist is not None else {}, **extra}


def camera_from_dict(data: dict, source: str = "camera") -> Camera:
    """Inverse of :func:`camera_to_dict`; DataError naming ``source`` on a malformed dict."""
    try:
        model = data.get("model", "pinhole")
        dist = None
        if model != "pinhole":
            if model not in _MODELS:
                raise DataError(f"{source}: unknown lens model {model!r}; expected one of "
                                f"{['pinhole', *_MODELS]}")
            dist = _MODELS[model](**data.get("coefficients", {}))
        return Camera(int(data["width"]), int(data["height"]), data["fx_px"], data["fy_px"],
                      data["cx_px"], data["cy_px"], dist)
    except (KeyError, TypeError, AttributeError) as exc:
        raise DataError(f"{source}: not a skyfix camera file (missing or malformed {exc})") from exc


def save_camera(path: str | os.PathLike, camera: Camera, **extra) -> None:
    """Write ``camera`` (and ``extra`` fields) to a JSON file."""
    Path(path).write_text(json.dumps(camera_to_dict(camera, **extra), indent=2) + "\n")


def load_camera(path: str | os.PathLike) -> Camera:
    """Read a camera JSON file written by :func:`save_camera` or ``skyfix lens calibrate``."""
    p = Path(path)
    data = read_json(p, "calibration file", missing=InputError)
    if not isinstance(data, dict):
        raise DataError(f"{p}: expected a JSON object describing a camera")
    return camera_from_dict(data, str(p))
