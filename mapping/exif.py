"""Photo metadata: read the camera and GPS tags, and carry them over to corrected JPEGs.

Corrected photos keep every APPn segment of the original (EXIF with GPS, camera and
orientation, XMP, ICC profile). The EXIF copy is updated for the corrected camera:
``FocalLength`` (and the 35 mm equivalent) scaled by the correction's focal scale,
``PixelXDimension``/``PixelYDimension`` set to the new size, the stale thumbnail dropped.
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from skyfix.errors import DataError

__all__ = ["FocalEstimate", "PhotoMetadata", "jpeg_quality", "read_metadata", "read_xmp", "transfer_metadata"]

_SOI = b"\xff\xd8"
_DIAGONAL_35MM_MM = math.hypot(36.0, 24.0)
#: FocalPlaneResolutionUnit -> millimetres per unit (EXIF: 2 inch, 3 cm, 4 mm, 5 um).
_UNIT_MM = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


def _ratio(value) -> float | None:
    if value is None:
        return None
    if isinstance(value, tuple) and len(value) == 2:
        return value[0] / value[1] if value[1] else None
    return float(value)


def _dms(values, ref: bytes, negative: bytes) -> float | None:
    if not values or len(values) != 3:
        return None
    parts = [_ratio(v) for v in values]
    if any(p is None for p in parts):
        return None
    deg = parts[0] + parts[1] / 60.0 + parts[2] / 3600.0
    return -deg if ref == negative else deg


#: XMP attributes (DJI ``drone-dji`` namespace) read from a photo, as ``name="value"`` or elements.
_XMP_KEYS = ("RelativeAltitude", "AbsoluteAltitude", "CalibratedFocalLength", "CalibratedOpticalCenterX")


def read_xmp(data: bytes) -> dict[str, float]:
    """Numeric DJI XMP values of a JPEG (``drone-dji:RelativeAltitude`` metres above take-off,
    ``CalibratedFocalLength`` pixels of the full-resolution image, ...); {} without XMP."""
    start = data.find(b"<x:xmpmeta")
    if start < 0:
        return {}
    end = data.find(b"</x:xmpmeta>", start)
    packet = data[start:end if end > 0 else start + 65536].decode("utf-8", "replace")
    out = {}
    for key in _XMP_KEYS:
        found = re.search(rf'drone-dji:{key}\s*=\s*"([^"]+)"|<drone-dji:{key}>([^<]+)<', packet)
        if found:
            try:
                value = float(found.group(1) or found.group(2))
            except ValueError:
                continue
            if math.isfinite(value):
                out[key] = value
    return out


#: The focal-plane resolution is trusted when the sensor width it implies for the image
#: (its width over the pixel density) is within this share of the sensor table's width.
#: Sensors of one type differ by about 2 %; a photo resized without updating the tag, or
#: with the tag scaled by another factor than the image, is off by far more (the Seneca
#: photos, 4000 px downscaled to 1200 with the density divided by 3: a 5.58 mm sensor for
#: the 6.17 mm 1/2.3-inch type, which made the focal length 11 % long).
_FOCAL_PLANE_TOLERANCE = 0.05


@dataclass(frozen=True)
class FocalEstimate:
    """Focal length in pixels and where it came from (``source``), most trusted first:
    ``xmp-calibrated`` (DJI factory calibration), ``focal-plane`` (EXIF sensor pixel density,
    unless the sensor width it implies disagrees with the table's by over 5 %),
    ``sensor-table`` (known sensor width), ``35mm-equivalent`` (an approximation: 4-5 %
    off on frames cropped from the sensor when the sensor's shape is not known)."""

    focal_px: float
    source: str


@dataclass(frozen=True)
class PhotoMetadata:
    """What skyfix reads from a photo's EXIF and XMP. Angles in degrees, lengths in millimetres.

    ``gps_alt_m`` is as recorded (usually above mean sea level). ``focal_plane_px_per_mm``
    is the sensor pixel density, from which the focal length in pixels follows. ``xmp``:
    numeric DJI XMP values (see :func:`read_xmp`).
    """

    source: str
    make: str | None
    model: str | None
    focal_length_mm: float | None
    focal_length_35mm: float | None
    focal_plane_px_per_mm: float | None
    orientation: int | None
    gps_lat_deg: float | None
    gps_lon_deg: float | None
    gps_alt_m: float | None
    xmp: dict = field(default_factory=dict)
    time_s: float | None = None  # DateTimeOriginal (+ sub-seconds) as POSIX seconds of the camera's clock

    def focal_length_px(self, width: int, height: int) -> float:
        """Focal length in pixels of a ``width x height`` image; DataError when EXIF lacks it."""
        return self.focal_estimate(width, height).focal_px

    def focal_estimate(self, width: int, height: int) -> FocalEstimate:
        """The best-founded focal length in pixels of a ``width x height`` image (see
        :class:`FocalEstimate`); DataError when neither EXIF nor XMP gives one."""
        from skyfix.mapping.sensors import sensor_width_mm

        calibrated, centre_x = self.xmp.get("CalibratedFocalLength"), self.xmp.get("CalibratedOpticalCenterX")
        if calibrated and calibrated > 0:
            # Calibrated on the full-resolution frame: scale by the width its optical centre implies.
            scale = width / (2.0 * centre_x) if centre_x and centre_x > 0 else 1.0
            return FocalEstimate(calibrated * scale, "xmp-calibrated")
        sensor_mm = sensor_width_mm(self.make, self.model)
        if self.focal_length_mm and self.focal_plane_px_per_mm and (
                sensor_mm is None or abs(max(width, height) / self.focal_plane_px_per_mm / sensor_mm - 1.0)
                <= _FOCAL_PLANE_TOLERANCE):
            return FocalEstimate(self.focal_length_mm * self.focal_plane_px_per_mm, "focal-plane")
        if self.focal_length_mm and sensor_mm:
            # A cropped frame (16:9 from a 4:3 or 3:2 sensor) keeps the sensor's full width.
            return FocalEstimate(self.focal_length_mm * max(width, height) / sensor_mm, "sensor-table")
        if self.focal_length_35mm:
            return FocalEstimate(self.focal_length_35mm * math.hypot(width, height) / _DIAGONAL_35MM_MM,
                                 "35mm-equivalent")
        raise DataError(f"{self.source}: EXIF has no FocalLength with FocalPlaneXResolution nor "
                        "FocalLengthIn35mmFilm; the focal length in pixels is unknown")


def _load(data: bytes, source: str) -> dict:
    import piexif

    if not data.startswith(_SOI):
        raise DataError(f"{source}: not a JPEG file (no SOI marker)")
    try:
        return piexif.load(data)
    except Exception as exc:  # piexif raises bare ValueError/struct.error on damaged EXIF
        raise DataError(f"{source}: corrupt JPEG or unreadable EXIF ({exc})") from exc


def read_metadata(data: bytes, source: str = "photo", require_exif: bool = True) -> PhotoMetadata:
    """Metadata of a JPEG given as bytes; ``source`` names it in errors.

    With ``require_exif`` a photo without an EXIF block raises :class:`DataError`.
    """
    import piexif

    exif = _load(data, source)
    zeroth, ex, gps = exif.get("0th", {}), exif.get("Exif", {}), exif.get("GPS", {})
    if require_exif and not (zeroth or ex or gps):
        raise DataError(f"{source}: no EXIF metadata (camera, focal length and GPS are needed)")

    def text(tag: int) -> str | None:
        raw = zeroth.get(tag)
        return raw.decode("ascii", "replace").strip("\x00 ") if isinstance(raw, bytes) else None

    res, unit = _ratio(ex.get(piexif.ExifIFD.FocalPlaneXResolution)), ex.get(piexif.ExifIFD.FocalPlaneResolutionUnit, 2)
    px_per_mm = res / _UNIT_MM[unit] if res and unit in _UNIT_MM else None
    alt = _ratio(gps.get(piexif.GPSIFD.GPSAltitude))
    if alt is not None and gps.get(piexif.GPSIFD.GPSAltitudeRef) == 1:
        alt = -alt
    f35 = ex.get(piexif.ExifIFD.FocalLengthIn35mmFilm)
    return PhotoMetadata(
        source=source, make=text(piexif.ImageIFD.Make), model=text(piexif.ImageIFD.Model),
        focal_length_mm=_ratio(ex.get(piexif.ExifIFD.FocalLength)),
        focal_length_35mm=float(f35) if f35 else None, focal_plane_px_per_mm=px_per_mm,
        orientation=zeroth.get(piexif.ImageIFD.Orientation),
        gps_lat_deg=_dms(gps.get(piexif.GPSIFD.GPSLatitude), gps.get(piexif.GPSIFD.GPSLatitudeRef), b"S"),
        gps_lon_deg=_dms(gps.get(piexif.GPSIFD.GPSLongitude), gps.get(piexif.GPSIFD.GPSLongitudeRef), b"W"),
        gps_alt_m=alt, xmp=read_xmp(data), time_s=_time_s(ex))


def _time_s(ex: dict) -> float | None:
    """DateTimeOriginal with SubSecTimeOriginal as seconds (the camera clock, taken as UTC)."""
    import datetime

    import piexif

    raw = ex.get(piexif.ExifIFD.DateTimeOriginal)
    if not isinstance(raw, bytes):
        return None
    try:
        stamp = datetime.datetime.strptime(raw.decode("ascii").strip("\x00 "), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    sub = ex.get(piexif.ExifIFD.SubSecTimeOriginal)
    fraction = 0.0
    if isinstance(sub, bytes) and sub.strip(b"\x00 ").isdigit():
        digits = sub.strip(b"\x00 ").decode()
        fraction = int(digits) / 10 ** len(digits)
    return stamp.replace(tzinfo=datetime.timezone.utc).timestamp() + fraction


def _segments(data: bytes, source: str) -> list[bytes]:
    """APPn segments (markers 0xE0..0xEF, whole, marker included) before the image data."""
    out, pos = [], 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker in (0xDA, 0xD9):  # start of scan / end of image
            break
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        if length < 2 or pos + 2 + length > len(data):
            raise DataError(f"{source}: truncated JPEG header segment at byte {pos}")
        if 0xE0 <= marker <= 0xEF:
            out.append(data[pos:pos + 2 + length])
        pos += 2 + length
    return out


def _rational(value: float) -> tuple[int, int]:
    frac = Fraction(value).limit_denominator(10000)
    return frac.numerator, frac.denominator


_TIFF_TYPE_BYTES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8}


def _ifd(tiff: bytearray, offset: int, order: str) -> tuple[dict[int, tuple[int, int, int]], int]:
    """A TIFF IFD at ``offset``: tag -> (type, count, value position), and the position of
    its next-IFD pointer."""
    n = int.from_bytes(tiff[offset:offset + 2], order)
    entries = {}
    for k in range(n):
        e = offset + 2 + 12 * k
        tag, kind = int.from_bytes(tiff[e:e + 2], order), int.from_bytes(tiff[e + 2:e + 4], order)
        count = int.from_bytes(tiff[e + 4:e + 8], order)
        inline = _TIFF_TYPE_BYTES.get(kind, 1) * count <= 4
        entries[tag] = (kind, count, e + 8 if inline else 6 + int.from_bytes(tiff[e + 8:e + 12], order))
    return entries, offset + 2 + 12 * n


def _patched_exif(payload: bytes, focal_scale: float, width: int, height: int) -> bytes | None:
    """``payload`` (the APP1 segment's "Exif" header and TIFF block) with the focal length,
    35 mm equivalent and image size rewritten in place and the thumbnail IFD unlinked; None when a tag it must change
    is missing or not a plain number. piexif's load + dump does the same in ~4 ms per
    photo (a deep copy of every tag), more than the JPEG encoding in ``skyfix lens``."""
    try:
        tiff = bytearray(payload)  # offsets below are from the TIFF header at byte 6
        order = {b"II": "little", b"MM": "big"}[bytes(tiff[6:8])]
        zeroth, next_ptr = _ifd(tiff, 6 + int.from_bytes(tiff[10:14], order), order)
        exif, _ = _ifd(tiff, 6 + int.from_bytes(tiff[zeroth[0x8769][2]:zeroth[0x8769][2] + 4], order), order)

        def put_int(entry, value: int) -> None:
            kind, count, pos = entry
            size = {3: 2, 4: 4}[kind]
            if count != 1 or value >= 1 << (8 * size):
                raise ValueError("not a single SHORT/LONG that holds the value")
            tiff[pos:pos + size] = int(value).to_bytes(size, order)

        def get_int(tag: int, ifd: dict) -> int | None:
            if tag not in ifd or ifd[tag][0] not in (3, 4):
                return None
            kind, _, pos = ifd[tag]
            return int.from_bytes(tiff[pos:pos + (2 if kind == 3 else 4)], order)

        old_w = get_int(0xA002, exif) or get_int(0x0100, zeroth) or width
        old_h = get_int(0xA003, exif) or get_int(0x0101, zeroth) or height
        put_int(exif[0xA002], width)
        put_int(exif[0xA003], height)
        for tag, value in ((0x0100, width), (0x0101, height)):
            if tag in zeroth:
                put_int(zeroth[tag], value)
        if 0x920A in exif:
            kind, _, pos = exif[0x920A]
            num, den = int.from_bytes(tiff[pos:pos + 4], order), int.from_bytes(tiff[pos + 4:pos + 8], order)
            if kind != 5 or not den:
                return None
            num, den = _rational(num / den * focal_scale)
            tiff[pos:pos + 8] = num.to_bytes(4, order) + den.to_bytes(4, order)
        f35 = get_int(0xA405, exif)
        if f35:
            put_int(exif[0xA405], max(1, round(f35 * focal_scale * math.hypot(old_w, old_h) / math.hypot(width, height))))
        tiff[next_ptr:next_ptr + 4] = bytes(4)  # the stale thumbnail's IFD is no longer linked
        return bytes(tiff)
    except (KeyError, ValueError, IndexError):
        return None


def _redumped_exif(payload: bytes, focal_scale: float, width: int, height: int) -> bytes:
    """The same update through piexif (tags added where missing)."""
    import piexif

    exif = piexif.load(payload)
    ex, zeroth = exif.setdefault("Exif", {}), exif.setdefault("0th", {})
    old_w = ex.get(piexif.ExifIFD.PixelXDimension) or zeroth.get(piexif.ImageIFD.ImageWidth) or width
    old_h = ex.get(piexif.ExifIFD.PixelYDimension) or zeroth.get(piexif.ImageIFD.ImageLength) or height
    focal = _ratio(ex.get(piexif.ExifIFD.FocalLength))
    if focal:
        ex[piexif.ExifIFD.FocalLength] = _rational(focal * focal_scale)
    f35 = ex.get(piexif.ExifIFD.FocalLengthIn35mmFilm)
    if f35:
        diag_ratio = math.hypot(old_w, old_h) / math.hypot(width, height)
        ex[piexif.ExifIFD.FocalLengthIn35mmFilm] = max(1, round(f35 * focal_scale * diag_ratio))
    ex[piexif.ExifIFD.PixelXDimension] = int(width)
    ex[piexif.ExifIFD.PixelYDimension] = int(height)
    for tag in (piexif.ImageIFD.ImageWidth, piexif.ImageIFD.ImageLength):
        zeroth.pop(tag, None)
    exif["1st"], exif["thumbnail"] = {}, None
    try:
        return piexif.dump(exif)
    except Exception:  # some maker notes do not survive a re-dump; keep the rest
        ex.pop(piexif.ExifIFD.MakerNote, None)
        return piexif.dump(exif)


def transfer_metadata(original: bytes, corrected: bytes, *, focal_scale: float, width: int, height: int,
                      source: str = "photo") -> bytes:
    """``corrected`` (a JPEG from any encoder) with ``original``'s APPn segments, EXIF updated.

    ``focal_scale`` multiplies FocalLength; FocalLengthIn35mmFilm is recomputed for the new
    focal length and image diagonal; the image size tags become ``width x height``.
    """
    if not corrected.startswith(_SOI):
        raise DataError("corrected image is not a JPEG stream")
    segments = _segments(original, source)
    body = corrected[2:]
    for seg in _segments(corrected, "corrected image"):  # drop the encoder's own JFIF header
        if body.startswith(seg):
            body = body[len(seg):]
    new_segments = []
    for seg in segments:
        if seg[1] == 0xE1 and seg[4:10] == b"Exif\x00\x00":
            payload = _patched_exif(seg[4:], focal_scale, width, height)
            if payload is None:  # a layout the in-place patch does not cover
                payload = _redumped_exif(seg[4:], focal_scale, width, height)
            seg = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
        new_segments.append(seg)
    return _SOI + b"".join(new_segments) + body


#: IJG (libjpeg) standard luminance quantisation table, natural order; quality q scales it.
_IJG_LUMA = (16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57, 69, 56,
             14, 17, 22, 29, 51, 87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92,
             49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99)


@functools.lru_cache(maxsize=1)
def _ijg_sums() -> np.ndarray:
    """Sum of the IJG luminance table scaled for each quality 1..100 (libjpeg's rounding)."""
    q = np.arange(1, 101)[:, None]
    scale = np.where(q < 50, 5000 / q, 200 - 2 * q)
    return np.clip((np.array(_IJG_LUMA)[None, :] * scale + 50) // 100, 1, 255).sum(axis=1)


def jpeg_quality(data: bytes) -> int | None:
    """Estimated IJG quality (1-100) of a JPEG from its luminance quantisation table, or None.

    Returns the quality whose scaled IJG table is closest to the stored one (exact for
    libjpeg-encoded files, an estimate for cameras with their own tables), as ImageMagick
    does to write a converted JPEG at its original quality. Table order (zig-zag vs
    natural) does not matter for the sum compared.
    """
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker == 0xDA or length < 2:
            break
        if marker == 0xDB:
            seg, i = data[pos + 4:pos + 2 + length], 0
            while i < len(seg):
                precision, table_id = seg[i] >> 4, seg[i] & 0x0F
                size = 128 if precision else 64
                raw = seg[i + 1:i + 1 + size]
                if len(raw) < size:
                    return None
                values = ([int.from_bytes(raw[k:k + 2], "big") for k in range(0, 128, 2)] if precision
                          else list(raw))
                if table_id == 0:
                    return int(1 + np.argmin(np.abs(_ijg_sums() - sum(values))))
                i += 1 + size
        pos += 2 + length
    return None
