"""Rendered drone surveys over known 2.5-D terrain: hills, buildings and trees.

A :class:`SurveyScene` is a height field (metres above the take-off point, ENU up of its
:class:`~skyfix.geo.LocalFrame`) with a top-down colour texture on the same grid
(row 0 along the north edge). Photos are rendered by exact ray casting: each pixel's
ray is marched down through the height field in small vertical steps until it passes
below the surface, then the crossing is refined by bisection, so roofs, walls and tree
crowns occlude what is behind them as they do for a real camera. The true orthophoto is
the texture itself and the true DSM the height field.

:func:`write_survey` flies a nadir lawn-mower grid at constant height and writes JPEGs
with the metadata a DJI drone writes: EXIF camera and GPS (AMSL, with a correlated GPS
error, not the truth) and XMP ``drone-dji`` relative altitude (barometric, above
take-off, with its own noise) and, optionally, the factory-calibrated focal length.
"""

from __future__ import annotations

import datetime
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import piexif

from skyfix.camera import Camera
from skyfix.errors import InputError
from skyfix.geo import LocalFrame

__all__ = ["SurveyPhoto", "SurveyScene", "make_scene", "render_view", "write_survey"]

#: DJI FC6310 (Phantom 4 Pro): 13.2 mm wide 3:2 sensor, 8.8 mm lens, EXIF 35 mm equivalent 24.
SENSOR_WIDTH_MM = 13.2
FOCAL_MM = 8.8
FOCAL_35MM = 24


@dataclass(frozen=True, eq=False)
class SurveyScene:
    """``heights_m`` (H, W) float32 metres above ``frame``'s origin; ``texture`` (H, W, 3)
    uint8 BGR seen from above; texel ``metres_per_px``; texel (0, 0) centre at
    (``west_m``, ``north_m``) in ``frame`` ENU."""

    frame: LocalFrame
    heights_m: np.ndarray
    texture: np.ndarray
    metres_per_px: float
    west_m: float
    north_m: float
    _blurred: list = field(default_factory=list, init=False, repr=False)

    def to_texel(self, east_m: np.ndarray, north_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (col, row) of ENU (east, north) points."""
        return (np.asarray(east_m) - self.west_m) / self.metres_per_px, \
            (self.north_m - np.asarray(north_m)) / self.metres_per_px

    def height_at(self, east_m: np.ndarray, north_m: np.ndarray) -> np.ndarray:
        """Surface height (metres above the origin) at ENU points, bilinear; NaN outside."""
        return _sample(self.heights_m, *self.to_texel(east_m, north_m), np.nan)

    def colour_at(self, east_m: np.ndarray, north_m: np.ndarray, blur_px: float = 0.0) -> np.ndarray:
        """Texture colour (float32 BGR) at ENU points; ``blur_px`` pre-filters the texture
        (anti-aliasing when a photo pixel covers several texels)."""
        if blur_px > 0 and not any(b[0] == blur_px for b in self._blurred):
            # every photo's GSD differs a little, so keep the latest two: a copy per photo held 100 x 118 MB
            # (float32 BGR of a 190 x 130 m scene at 5 cm) and two test suites at once ran out of memory
            del self._blurred[:-1]
            self._blurred.append((blur_px, cv2.GaussianBlur(self.texture.astype(np.float32), (0, 0), blur_px)))
        src = next((b[1] for b in self._blurred if b[0] == blur_px), None) if blur_px > 0 else self.texture
        return _sample(np.asarray(src, np.float32), *self.to_texel(east_m, north_m), 0.0)


def _sample(src: np.ndarray, col: np.ndarray, row: np.ndarray, border: float) -> np.ndarray:
    """Bilinear samples of ``src`` at any number of points (cv2.remap wants maps under 32767 wide)."""
    col, row = np.asarray(col, np.float32), np.asarray(row, np.float32)
    n, width = col.size, 1024
    pad = (-n) % width
    maps = [np.pad(a.ravel(), (0, pad), constant_values=-1e6).reshape(-1, width) for a in (col, row)]
    out = cv2.remap(src, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=(border,) * 4)
    return out.reshape(-1, *src.shape[2:])[:n].reshape(*col.shape, *src.shape[2:])


def _noise(shape: tuple[int, int], cells: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise in [-1, 1]: ``cells`` random values across the long side, bicubic."""
    h, w = shape
    small = rng.uniform(-1.0, 1.0, (max(2, cells * h // max(h, w)) + 3, cells + 3)).astype(np.float32)
    big = cv2.resize(small, (w + w * 3 // cells, h + h * 3 // max(2, cells * h // max(h, w))),
                     interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def make_scene(size_m: tuple[float, float] = (110.0, 80.0), metres_per_px: float = 0.05, *, seed: int = 0,
               origin: tuple[float, float, float] = (47.3977, 8.5456, 430.0), buildings: int = 6,
               trees: int = 14) -> SurveyScene:
    """A textured scene centred on the take-off point ``origin`` (lat, lon deg, height m):
    gentle hills (+-1.5 m), flat-roofed buildings 4-9 m tall and round tree crowns 5-8 m tall."""
    if metres_per_px <= 0 or min(size_m) <= 10 * metres_per_px:
        raise InputError(f"scene {size_m} m at {metres_per_px} m/px is too small")
    rng = np.random.default_rng(seed)
    w, h = int(size_m[0] / metres_per_px), int(size_m[1] / metres_per_px)
    west, north = -size_m[0] / 2.0, size_m[1] / 2.0
    east_m = west + np.arange(w, dtype=np.float32) * metres_per_px
    north_m = north - np.arange(h, dtype=np.float32) * metres_per_px
    ee, nn = np.meshgrid(east_m, north_m)
    heights = 1.5 * _noise((h, w), 4, rng)
    heights -= heights[h // 2, w // 2]  # the take-off point (scene centre) is at height 0
    grass = np.stack([40 + 25 * _noise((h, w), 60, rng), 110 + 40 * _noise((h, w), 25, rng),
                      70 + 30 * _noise((h, w), 40, rng)], axis=2)
    fine = rng.normal(0.0, 1.0, (h, w)).astype(np.float32)
    fine = cv2.GaussianBlur(fine, (0, 0), 0.12 / metres_per_px) * 60.0
    texture = grass + fine[..., None] + 45.0 * _noise((h, w), 150, rng)[..., None]
    road = np.abs(nn - 0.3 * ee - 6.0) < 3.0
    texture[road] = 120 + 0.4 * texture[road] - 40
    for _ in range(buildings):
        cx, cy = rng.uniform(west + 10, -west - 10), rng.uniform(-north + 10, north - 10)
        half = rng.uniform(3.0, 7.0, 2)
        inside = (np.abs(ee - cx) < half[0]) & (np.abs(nn - cy) < half[1])
        heights[inside] = float(np.max(heights[inside], initial=0.0)) + rng.uniform(4.0, 9.0)
        tile = np.array(rng.uniform(60, 200, 3), np.float32)
        stripes = 25.0 * np.sign(np.sin((ee[inside] - cx) * 2 * math.pi / 0.9))
        texture[inside] = tile + stripes[:, None] + 0.6 * fine[inside][:, None] * 1.5
    for _ in range(trees):
        cx, cy = rng.uniform(west + 5, -west - 5), rng.uniform(-north + 5, north - 5)
        radius, top = rng.uniform(2.0, 3.5), rng.uniform(5.0, 8.0)
        r2 = ((ee - cx) ** 2 + (nn - cy) ** 2) / radius ** 2
        crown = r2 < 1.0
        base = float(np.median(heights[crown]))
        heights[crown] = np.maximum(heights[crown], base + top * np.sqrt(1.0 - r2[crown]))
        texture[crown] = np.array([30, 80, 35], np.float32) + 1.4 * fine[crown][:, None] \
            + 30.0 * np.sqrt(1.0 - r2[crown])[:, None]
    frame = LocalFrame(*origin)
    return SurveyScene(frame, heights.astype(np.float32), np.clip(texture, 0, 255).astype(np.uint8),
                       metres_per_px, float(west), float(north))


def render_view(scene: SurveyScene, camera: Camera, centre_enu_m: np.ndarray, r_enu_from_cam: np.ndarray, *,
                step_m: float = 0.2, background: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """BGR uint8 image and (H, W, 3) ENU surface point of each pixel (NaN off the scene).

    Rays are marched down in ``step_m`` vertical steps from the highest to the lowest
    surface height and the first crossing is refined by 12 bisections (millimetres).
    """
    vv, uu = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    rays = camera.pixel_to_ray(np.stack((uu.ravel(), vv.ravel()), axis=1)) @ np.asarray(r_enu_from_cam).T
    c = np.asarray(centre_enu_m, dtype=np.float64)
    down = rays[:, 2] < -1e-6
    top, bottom = float(np.nanmax(scene.heights_m)) + 0.01, float(np.nanmin(scene.heights_m)) - 0.01

    def below(z: np.ndarray) -> np.ndarray:
        t = (z - c[2]) / np.where(down, rays[:, 2], -1.0)
        h = scene.height_at(c[0] + t * rays[:, 0], c[1] + t * rays[:, 1]).ravel()
        return ~(z > h)  # NaN (off the scene) counts as a hit, and is masked below

    z_hi = np.full(len(rays), top)
    hit = np.zeros(len(rays), bool)
    z = top
    while z > bottom and not hit.all():
        z -= step_m
        now = ~hit & below(np.full(len(rays), z))
        z_hi[~hit & ~now] = z
        hit |= now
    z_lo = np.maximum(z_hi - step_m, bottom)
    for _ in range(12):
        mid = 0.5 * (z_hi + z_lo)
        b = below(mid)
        z_lo, z_hi = np.where(b, mid, z_lo), np.where(b, z_hi, mid)
    t = (z_lo - c[2]) / np.where(down, rays[:, 2], -1.0)
    pts = c + t[:, None] * rays
    valid = down & np.isfinite(scene.height_at(pts[:, 0], pts[:, 1]).ravel())
    pts[~valid] = np.nan
    gsd_m = float(np.nanmedian(c[2] - pts[:, 2])) / camera.fx
    colour = scene.colour_at(pts[:, 0], pts[:, 1], blur_px=0.5 * gsd_m / scene.metres_per_px).reshape(-1, 3)
    colour[~valid] = background
    image = np.clip(np.rint(colour), 0, 255).astype(np.uint8).reshape(camera.height, camera.width, 3)
    return image, pts.reshape(camera.height, camera.width, 3)


@dataclass(frozen=True)
class SurveyPhoto:
    """One written photo: true camera centre (ENU m), what its GPS said (ENU m), path."""

    path: str
    centre_enu_m: tuple[float, float, float]
    gps_enu_m: tuple[float, float, float]
    relative_altitude_m: float


def _xmp_packet(relative_alt_m: float, absolute_alt_m: float, calibrated_focal_px: float | None,
                width: int, height: int) -> bytes:
    calib = "" if calibrated_focal_px is None else (
        f' drone-dji:CalibratedFocalLength="{calibrated_focal_px:.6f}"'
        f' drone-dji:CalibratedOpticalCenterX="{width / 2:.6f}" drone-dji:CalibratedOpticalCenterY="{height / 2:.6f}"')
    xml = ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?><x:xmpmeta xmlns:x="adobe:ns:meta/">'
           '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description rdf:about="" '
           'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
           f'drone-dji:AbsoluteAltitude="{absolute_alt_m:+.2f}" drone-dji:RelativeAltitude="{relative_alt_m:+.2f}" '
           'drone-dji:GimbalPitchDegree="-90.00"' + calib + '/></rdf:RDF></x:xmpmeta><?xpacket end="w"?>')
    payload = b"http://ns.adobe.com/xap/1.0/\x00" + xml.encode("utf-8")
    return b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload


def _exif(frame: LocalFrame, gps_enu_m: np.ndarray, width: int, height: int, with_sensor_width: bool,
          time_s: float) -> bytes:
    lat, lon, alt = frame.to_geodetic_points(gps_enu_m[None, :])[0]

    def dms(value: float) -> tuple:
        value = abs(value)
        d = int(value)
        m = int((value - d) * 60)
        s = round((value - d - m / 60) * 3600 * 10000)
        return ((d, 1), (m, 1), (s, 10000))

    stamp = datetime.datetime(2026, 5, 1, 10, 0, 0) + datetime.timedelta(seconds=time_s)
    exif = {"0th": {piexif.ImageIFD.Make: b"DJI", piexif.ImageIFD.Model: b"FC6310"},
            "Exif": {piexif.ExifIFD.DateTimeOriginal: stamp.strftime("%Y:%m:%d %H:%M:%S").encode(),
                     piexif.ExifIFD.SubSecTimeOriginal: f"{stamp.microsecond // 1000:03d}".encode(),
                     piexif.ExifIFD.FocalLength: (int(FOCAL_MM * 100), 100),
                     piexif.ExifIFD.FocalLengthIn35mmFilm: FOCAL_35MM,
                     piexif.ExifIFD.PixelXDimension: width, piexif.ExifIFD.PixelYDimension: height},
            "GPS": {piexif.GPSIFD.GPSLatitudeRef: b"N" if lat >= 0 else b"S", piexif.GPSIFD.GPSLatitude: dms(lat),
                    piexif.GPSIFD.GPSLongitudeRef: b"E" if lon >= 0 else b"W", piexif.GPSIFD.GPSLongitude: dms(lon),
                    piexif.GPSIFD.GPSAltitudeRef: 0, piexif.GPSIFD.GPSAltitude: (round(alt * 1000), 1000)}}
    if with_sensor_width:
        exif["Exif"][piexif.ExifIFD.FocalPlaneXResolution] = (round(width / SENSOR_WIDTH_MM * 1000), 1000)
        exif["Exif"][piexif.ExifIFD.FocalPlaneResolutionUnit] = 4
    return piexif.dump(exif)


def survey_camera(width: int = 512, height: int = 288) -> Camera:
    """The FC6310-like camera of :func:`write_survey`: a 16:9 crop spanning the sensor's width."""
    f_px = FOCAL_MM * width / SENSOR_WIDTH_MM
    return Camera(width, height, f_px, f_px, (width - 1) / 2.0, (height - 1) / 2.0)


def write_survey(out_dir: str | Path, scene: SurveyScene, *, height_m: float = 30.0, lines: int = 3,
                 per_line: int = 5, line_spacing_m: float = 14.0, photo_spacing_m: float = 8.0,
                 camera: Camera | None = None, calibrated_focal: bool = True, focal_plane: bool = False,
                 gps_sigma_m: tuple[float, float] = (0.4, 0.2), speed_mps: float = 5.0, gps_lag_s: float = 0.0,
                 seed: int = 0) -> list[SurveyPhoto]:
    """Fly a nadir grid (lines along north, alternating direction) ``height_m`` above the
    take-off point and write ``IMG_nnnn.jpg`` with EXIF and DJI XMP into ``out_dir``.

    EXIF carries ``FocalLengthIn35mmFilm`` 24, which scaled by the 16:9 image diagonal is
    4.5 % short of the true focal length (the crop problem); ``calibrated_focal`` adds
    DJI's XMP CalibratedFocalLength, ``focal_plane`` the EXIF focal-plane resolution.
    GPS error: a random walk per axis (horizontal, vertical sigmas ``gps_sigma_m`` per
    photo, zero mean over the flight) as consumer GNSS drifts; the barometric relative
    altitude has 0.1 m noise. The drone flies at ``speed_mps`` (10 s per turn); EXIF time
    stamps have millisecond sub-seconds; ``gps_lag_s`` makes each tag the position that
    many seconds before the photo (a stale GPS fix), trailing along the line.
    """
    rng = np.random.default_rng(seed + 1)
    camera = camera or survey_camera()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n = lines * per_line
    walk = np.cumsum(rng.normal(0.0, 1.0, (n, 3)), axis=0) / np.sqrt(np.arange(1, n + 1))[:, None]
    walk -= walk.mean(axis=0)
    gps_err = walk * np.array([gps_sigma_m[0], gps_sigma_m[0], gps_sigma_m[1]])
    photos = []
    for i in range(n):
        line, k = divmod(i, per_line)
        along = (k - (per_line - 1) / 2.0) * photo_spacing_m * (1 if line % 2 == 0 else -1)
        centre = np.array([(line - (lines - 1) / 2.0) * line_spacing_m, along, height_m])
        velocity = np.array([0.0, speed_mps * (1 if line % 2 == 0 else -1), 0.0])
        time_s = line * (per_line * photo_spacing_m / speed_mps + 10.0) + k * photo_spacing_m / speed_mps
        yaw_rad = math.radians(rng.normal(0.0, 1.0))
        tilt = np.radians(rng.normal(0.0, 0.5, 2))
        # camera x = east, y = south, z = down, turned by small yaw and tilts (gimbal jitter)
        base = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
        rz = np.array([[math.cos(yaw_rad), -math.sin(yaw_rad), 0], [math.sin(yaw_rad), math.cos(yaw_rad), 0],
                       [0, 0, 1]])
        rx = cv2.Rodrigues(np.array([tilt[0], tilt[1], 0.0]))[0]
        r_enu_from_cam = rz @ base @ rx
        image, _ = render_view(scene, camera, centre, r_enu_from_cam)
        image = np.clip(image.astype(np.float32) + rng.normal(0, 2.0, image.shape), 0, 255).astype(np.uint8)
        gps = centre - gps_lag_s * velocity + gps_err[i]
        rel_alt = float(centre[2] + rng.normal(0.0, 0.1))
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        buf = io.BytesIO()
        piexif.insert(_exif(scene.frame, gps, camera.width, camera.height, focal_plane, time_s), jpeg.tobytes(), buf)
        data = buf.getvalue()
        xmp = _xmp_packet(rel_alt, scene.frame.alt0_m + gps[2],
                          camera.fx if calibrated_focal else None, camera.width, camera.height)
        path = out / f"IMG_{i:04d}.jpg"
        path.write_bytes(data[:2] + xmp + data[2:])
        photos.append(SurveyPhoto(str(path), tuple(map(float, centre)), tuple(map(float, gps)), rel_alt))
    return photos
