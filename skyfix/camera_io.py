"""Camera JSON: the one file format in which skyfix reads and writes a camera and its lens.

Written form (what :func:`save_camera` produces)::

    {"width": 4000, "height": 3000,          # image size, pixels (integers)
     "fx_px": 2900.0, "fy_px": 2900.0,       # focal lengths, pixels
     "cx_px": 1999.5, "cy_px": 1499.5,       # principal point, OpenCV pixels (centre of the
                                             #   top-left pixel is (0, 0))
     "model": "brown_conrady",               # pinhole | brown_conrady | fisheye | barrel
     "coefficients": {"k1": -0.1, "k2": 0.02, "p1": 0.0, "p2": 0.0, "k3": 0.0}}

``coefficients`` per ``model`` (see :mod:`skyfix.distortion`): ``brown_conrady`` k1 k2 p1
p2 k3 (OpenCV, dimensionless), ``fisheye`` k1 k2 k3 k4 (OpenCV Kannala-Brandt), ``barrel``
a b c d (ImageMagick ``-distort barrel``), ``pinhole`` none (``{}`` or absent). Missing
Brown-Conrady and fisheye coefficients are 0; barrel needs a, b, c (``d`` defaults to
1 - a - b - c). ``model`` absent means pinhole.
Any other key (``rms_px``, ``note``...) is kept in the file and ignored by the reader.

Also read, for files written by older skyfix versions and by hand:

- ``fx``, ``fy``, ``cx``, ``cy`` (pixels) instead of the ``_px`` names;
- ``"hfov_deg"`` [and ``"vfov_deg"``] instead of focal lengths: the field of view spans
  the full image width (height), the principal point is the image centre, and pixels are
  square when ``vfov_deg`` is absent (see :meth:`skyfix.camera.Camera.from_fov`).

A file gives its intrinsics in exactly one of these three ways. ``width``/``height`` may be
left out when the reader is told the image size (``image_size``); when the file gives a size
and the image has another one with the same aspect ratio, the camera is rescaled to the
image (:meth:`~skyfix.camera.Camera.scaled`).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, fields
from pathlib import Path
from typing import Annotated, Any

import msgspec
from msgspec import Meta

from skyfix import validate
from skyfix.camera import Camera
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import DataError, InputError
from skyfix.jsonfile import convert, json_schema, read_json

__all__ = ["CAMERA_KEYS", "LENS_MODELS", "CameraFile", "camera_from_dict", "camera_json_schema", "camera_to_dict",
           "load_camera", "save_camera"]

LENS_MODELS = {"brown_conrady": BrownConrady, "fisheye": Fisheye, "barrel": Barrel}
"""Lens model name in the file -> distortion class (``pinhole`` means no distortion)."""

CAMERA_KEYS = ("width", "height", "fx_px", "fy_px", "cx_px", "cy_px", "model", "coefficients")
"""Keys :func:`camera_to_dict` writes; ``extra`` fields may not reuse them."""

_FORMS = {  # the three ways a file may give the intrinsics -> keys each one needs
    "fx_px, fy_px, cx_px, cy_px": ("fx_px", "fy_px", "cx_px", "cy_px"),
    "fx, fy, cx, cy": ("fx", "fy", "cx", "cy"),
    "hfov_deg [, vfov_deg]": ("hfov_deg",),
}
_EXPECTED = ("a JSON object with width, height (pixels) and one of: "
             + "; ".join(_FORMS) + " (see skyfix.camera_io)")

_Pixels = Annotated[float, Meta(gt=0, multiple_of=1, description="pixels, a positive integer (640.0 reads as 640)")]
_FocalPx = Annotated[float, Meta(gt=0, description="focal length, pixels")]
_CentrePx = Annotated[float, Meta(description="principal point, OpenCV pixels (top-left pixel centre is 0)")]
_Fov = Annotated[float, Meta(gt=0, lt=180, description="field of view across the full image, degrees")]
_Model = Annotated[str, Meta(extra_json_schema={"enum": ["pinhole", *LENS_MODELS], "default": "pinhole"})]


class CameraFile(msgspec.Struct, kw_only=True):
    """skyfix camera JSON as read: a camera's image size, intrinsics and lens (see skyfix.camera_io).

    Exactly one of the three intrinsics forms is given (checked by :func:`camera_from_dict`);
    other keys are ignored.

    Example:
        >>> file = convert({"width": 640, "height": 480, "hfov_deg": 60, "note": "x"}, CameraFile, "cam.json")
        >>> file.width, file.hfov_deg, file.model
        (640.0, 60.0, 'pinhole')
    """

    width: _Pixels | None = None
    height: _Pixels | None = None
    fx_px: _FocalPx | None = None
    fy_px: _FocalPx | None = None
    cx_px: _CentrePx | None = None
    cy_px: _CentrePx | None = None
    fx: _FocalPx | None = None
    fy: _FocalPx | None = None
    cx: _CentrePx | None = None
    cy: _CentrePx | None = None
    hfov_deg: _Fov | None = None
    vfov_deg: _Fov | None = None
    model: _Model = "pinhole"
    coefficients: dict[str, Any] | None = None  # typed per model by the lens class (schema: allOf)


def camera_json_schema() -> dict:
    """JSON Schema of the camera file: :class:`CameraFile` plus each lens model's coefficients.

    Example:
        >>> schema = camera_json_schema()
        >>> sorted(schema["$defs"]), schema["$defs"]["Barrel"]["required"]
        (['Barrel', 'BrownConrady', 'CameraFile', 'Fisheye'], ['a', 'b', 'c'])
    """
    schema = json_schema(CameraFile, *LENS_MODELS.values())
    rules = []
    for name, cls in LENS_MODELS.items():
        lens = schema["$defs"][cls.__name__]
        lens["description"] = f"coefficients of the {name} lens model (skyfix.distortion.{cls.__name__})"
        lens["additionalProperties"] = False
        rules.append({"if": {"properties": {"model": {"const": name}}, "required": ["model"]},
                      "then": {"properties": {"coefficients": {"$ref": f"#/$defs/{cls.__name__}"}}}})
    schema["allOf"] = rules
    schema["oneOf"] = [{"required": list(keys)} for keys in _FORMS.values()]  # one intrinsics form
    schema["title"] = "skyfix camera JSON"
    return schema


def camera_to_dict(camera: Camera, **extra: Any) -> dict:
    """JSON-ready dict of ``camera`` in the written form; ``extra`` items (e.g. ``rms_px``)
    are added as they are. InputError for an unknown distortion class or an ``extra`` key
    that would overwrite a camera key.

    Example:
        >>> cam = Camera(4000, 3000, 2900.0, 2900.0, 1999.5, 1499.5, BrownConrady(k1=-0.1))
        >>> d = camera_to_dict(cam, rms_px=0.4)
        >>> d["model"], d["coefficients"]["k1"], d["rms_px"], camera_from_dict(d) == cam
        ('brown_conrady', -0.1, 0.4, True)
    """
    if not isinstance(camera, Camera):
        raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
    clash = sorted(set(extra) & set(CAMERA_KEYS))
    if clash:
        raise InputError(f"extra field(s) {clash} would overwrite the camera's own keys {list(CAMERA_KEYS)}")
    dist = camera.distortion
    model = next((name for name, cls in LENS_MODELS.items() if type(dist) is cls), None)
    if dist is not None and model is None:
        raise InputError(f"cannot write distortion model {type(dist).__name__} to camera JSON; "
                         f"supported: {list(LENS_MODELS)}")
    return {"width": camera.width, "height": camera.height, "fx_px": camera.fx, "fy_px": camera.fy,
            "cx_px": camera.cx, "cy_px": camera.cy, "model": model or "pinhole",
            "coefficients": asdict(dist) if dist is not None else {}, **extra}


def camera_from_dict(data: Any, source: str = "camera", *,
                     image_size: tuple[int, int] | None = None) -> Camera:
    """Camera described by ``data`` (any form in the module docstring).

    ``source`` names the file (or object) in error messages. ``image_size`` is the
    ``(width, height)`` in pixels of the images the camera will be used on: it supplies a
    missing width/height, and a camera stored at another size with the same aspect ratio is
    rescaled to it. DataError naming ``source`` on a malformed description or an aspect
    ratio mismatch; InputError on a malformed ``image_size``.

    Example:
        >>> cam = camera_from_dict({"width": 4000, "height": 3000, "hfov_deg": 84.0}, image_size=(1000, 750))
        >>> cam.width, round(cam.fx, 2), cam.cx
        (1000, 555.31, 499.5)
        >>> camera_from_dict({"width": 4000, "height": 3000}, "cam.json")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        skyfix.errors.DataError: cam.json: expected a JSON object with width, height (pixels) and one of: ...
    """
    size = None if image_size is None else _image_size(image_size)
    if not isinstance(data, dict):
        raise DataError(f"{source}: expected {_EXPECTED}; got JSON {type(data).__name__}")
    file = convert(data, CameraFile, source)
    width, height = _file_size(file, source, size)
    distortion = _distortion(file, source)
    forms = [name for name, keys in _FORMS.items() if any(getattr(file, k) is not None for k in keys)]
    if len(forms) != 1:
        found = "none of them" if not forms else f"{len(forms)} of them ({'; '.join(forms)})"
        raise DataError(f"{source}: expected {_EXPECTED}; found {found}")
    keys = _FORMS[forms[0]]
    missing = [k for k in keys if getattr(file, k) is None]
    if missing:
        raise DataError(f"{source}: lacks {missing}; with {forms[0]} all of them are needed ({_EXPECTED})")
    try:
        if keys[0] == "hfov_deg":
            camera = Camera.from_fov(width, height, file.hfov_deg, file.vfov_deg, distortion)
        else:
            camera = Camera(width, height, *(getattr(file, k) for k in keys), distortion)
    except InputError as exc:  # a value Camera refuses (e.g. a NaN from Python's json): the file is at fault
        raise DataError(f"{source}: {exc}") from exc
    if size is None or size == (camera.width, camera.height):
        return camera
    return _rescaled(camera, size, source)


def save_camera(path: str | os.PathLike, camera: Camera, **extra: Any) -> None:
    """Write ``camera`` (and ``extra`` JSON-able fields) to the JSON file ``path``.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as folder:  # read back at half the size
        ...     save_camera(Path(folder) / "camera.json", Camera.from_fov(640, 480, 90.0), rms_px=0.3)
        ...     round(load_camera(Path(folder) / "camera.json", image_size=(320, 240)).fx, 6)
        160.0
    """
    data = camera_to_dict(camera, **extra)
    try:
        text = json.dumps(data, indent=2, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InputError(f"camera file {path}: extra fields must be finite JSON values: {exc}") from exc
    Path(path).write_text(text + "\n")


def load_camera(path: str | os.PathLike, *, image_size: tuple[int, int] | None = None) -> Camera:
    """Read the camera JSON file ``path`` (format in the module docstring).

    ``image_size`` ``(width, height)`` pixels: see :func:`camera_from_dict`. InputError
    when the file does not exist, DataError when it is not a camera description.

    Example:
        >>> load_camera("no-such-camera.json")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        skyfix.errors.InputError: ...no-such-camera.json...
    """
    p = Path(path)
    return camera_from_dict(read_json(p, "camera file", missing=InputError), f"camera file {p}",
                            image_size=image_size)


def _image_size(image_size: Any) -> tuple[int, int]:
    try:
        w, h = image_size
        return validate.integer_in("image width", w, 1), validate.integer_in("image height", h, 1)
    except (TypeError, ValueError):
        raise InputError(f"image_size must be (width, height) in pixels, positive integers; "
                         f"got {image_size!r}") from None


def _file_size(file: CameraFile, source: str, size: tuple[int, int] | None) -> tuple[int, int]:
    given = [k for k in ("width", "height") if getattr(file, k) is not None]
    if not given:
        if size is None:
            raise DataError(f"{source}: lacks width and height and no image size was given; expected {_EXPECTED}")
        return size
    if len(given) == 1:
        raise DataError(f"{source}: gives {given[0]} but not {'height' if given[0] == 'width' else 'width'}; "
                        "give both or neither")
    return int(file.width), int(file.height)


def _distortion(file: CameraFile, source: str):
    model, coefficients = file.model, file.coefficients or {}
    if model not in ("pinhole", *LENS_MODELS):
        raise DataError(f"{source}: unknown lens model {model!r}; expected one of {['pinhole', *LENS_MODELS]}")
    if model == "pinhole":
        if any(v != 0 for v in coefficients.values()):
            raise DataError(f"{source}: coefficients {coefficients} given for a pinhole camera; "
                            f"name the lens model (\"model\": one of {list(LENS_MODELS)})")
        return None
    cls = LENS_MODELS[model]
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(coefficients) - set(names))
    if unknown:  # msgspec ignores unknown keys of a dataclass: a typo (k9) must not pass as 0
        raise DataError(f"{source}: model {model} has coefficients {names}, not {unknown}")
    return convert(coefficients, cls, f"{source} coefficients of model {model}")


def _rescaled(camera: Camera, size: tuple[int, int], source: str) -> Camera:
    """``camera`` for images of ``size``: one scale factor, the image height must follow it."""
    width, height = size
    factor = width / camera.width
    if round(camera.height * factor) != height:
        raise DataError(f"{source}: camera is {camera.width}x{camera.height} px but the image is "
                        f"{width}x{height} px; a different aspect ratio cannot be rescaled "
                        "(calibrate this image size or give a camera for it)")
    return camera.scaled(factor)
