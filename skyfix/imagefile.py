"""Reading an image file a user named, with one clear error when it is not a whole image.

OpenCV decodes a truncated JPEG or PNG without complaint (the missing rows come out grey
or black, libjpeg prints a warning on the terminal), so a cut-off download or a card
pulled mid-write would be measured as if it were a real frame. :func:`read_image` checks
the file's end marker first and raises :class:`~skyfix.errors.DataError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skyfix.errors import DataError, InputError

_JPEG_START, _JPEG_END = b"\xff\xd8", b"\xff\xd9"
_PNG_START, _PNG_END = b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82"


def check_complete(path: str | Path, data: bytes) -> None:
    """Raise :class:`DataError` naming ``path`` when ``data`` (the file's bytes) is a JPEG
    without its end-of-image marker or a PNG without its IEND chunk; other formats pass."""
    if data.startswith(_JPEG_START) and not data.rstrip(b"\x00").endswith(_JPEG_END):
        raise DataError(f"{path}: truncated JPEG (no end-of-image marker)")
    if data.startswith(_PNG_START) and _PNG_END not in data[-64:]:
        raise DataError(f"{path}: truncated PNG (no IEND chunk)")


def read_image(path: str | Path, flags: int | None = None, *, what: str = "image") -> np.ndarray:
    """The image at ``path`` decoded by OpenCV (``flags``: a ``cv2.IMREAD_*``; default
    unchanged depth and channels; colour comes out BGR as OpenCV gives it).

    Raises :class:`InputError` when the path does not exist or is a folder and
    :class:`DataError` when the file is empty, truncated or not an image, each naming
    ``what`` and the path once."""
    import cv2

    p = Path(path)
    if not p.exists():
        raise InputError(f"{what} {p} does not exist")
    if p.is_dir():
        raise InputError(f"{what} {p} is a folder, not an image file")
    data = p.read_bytes()
    if not data:
        raise DataError(f"{what} {p} is empty")
    check_complete(p, data)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED if flags is None else flags)
    if img is None:
        raise DataError(f"{what} {p} is not an image OpenCV can read")
    return img
