"""A field of tile tags laid on the floor: grid, values, save/load, print rendering.

Field frame: x east, y north, z up, metres; the floor is z = 0. Tag (col, row) has its
centre at ``origin_xy_m + (col, row) * spacing_m``; row 0 is the southern row.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import msgspec
import numpy as np
from msgspec import Meta

from skyfix import validate
from skyfix.errors import DataError, InputError
from skyfix.jsonfile import convert, json_schema, read_json
from skyfix.tags.codec import TagGeometry, TileCodec
from skyfix.tags.placement import PlacementReport, optimise_placement
from skyfix.tags.raster import fill_rects

FORMAT = "skyfix.tags.TagField"
PAPER_RGB = np.ones(3)
MAX_PRINT_SIDE_PX = 30000


@dataclass(frozen=True, eq=False)
class TagField:
    """Tile tags on a grid: ``values`` ``(rows, cols)`` int, row 0 south, each value once."""

    codec: TileCodec
    geometry: TagGeometry
    spacing_m: float
    values: np.ndarray
    origin_xy_m: tuple[float, float] = (0.0, 0.0)
    placement: PlacementReport | None = None
    _index: dict = field(default_factory=dict, init=False, repr=False)
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.codec.tiles != self.geometry.tiles:
            raise InputError(f"codec has {self.codec.tiles} tiles but geometry {self.geometry.tiles}")
        v = np.asarray(self.values)
        if v.ndim != 2 or v.size == 0 or not np.issubdtype(v.dtype, np.integer):
            raise InputError(f"values must be a non-empty (rows, cols) integer array, got {v.dtype} {v.shape}")
        self.codec.encode(v.ravel())  # range check
        if np.unique(v).size != v.size:
            raise InputError("values must be distinct: every tag value may be used once")
        v = v.astype(np.int64).copy()
        v.setflags(write=False)
        object.__setattr__(self, "values", v)
        spacing = validate.positive_scalar("spacing_m", self.spacing_m)
        if spacing < 1.5 * self.geometry.size_m:
            raise InputError(f"spacing_m={spacing} must be >= 1.5 x the tag size "
                             f"({self.geometry.size_m:.4f} m) so tags stay separable")
        object.__setattr__(self, "spacing_m", spacing)
        o = validate.finite_array("origin_xy_m", self.origin_xy_m).reshape(2)
        object.__setattr__(self, "origin_xy_m", (float(o[0]), float(o[1])))
        self._index.update({int(val): i for i, val in enumerate(v.ravel())})
        digits = self.codec.encode(v.ravel())
        row, col = np.divmod(np.arange(v.size), v.shape[1])
        centres = np.stack((self.origin_xy_m[0] + col * spacing, self.origin_xy_m[1] + row * spacing), axis=1)
        tiles = centres[:, None, :] + self.geometry.tile_centres_m()[None, :, :]
        for name, arr in (("tile_digits", digits), ("centres", centres), ("tiles", tiles)):
            arr.setflags(write=False)
            self._cache[name] = arr

    @classmethod
    def generate(cls, rows: int, cols: int, *, colors: int = 6, tiles: int = 4,
                 tile_m: float = 0.05, gap_m: float = 0.01, offset_m: float | None = None,
                 spacing_m: float = 0.4, origin_xy_m: tuple[float, float] = (0.0, 0.0),
                 time_limit_s: float = 5.0, max_iterations: int = 400_000, seed: int = 0,
                 on_progress=None) -> TagField:
        """Optimise a placement (:func:`~skyfix.tags.placement.optimise_placement`) and
        build the field; ``placement`` holds the objective against random placement.

        The optimiser stops at ``time_limit_s`` or ``max_iterations`` moves, whichever
        comes first: bound the moves (and give time to spare) for a field that is the
        same on every machine for a given ``seed``. ``on_progress(fraction)``: see
        :func:`~skyfix.tags.placement.optimise_placement`."""
        codec = TileCodec(colors=colors, tiles=tiles)
        geometry = TagGeometry(tiles, tile_m, gap_m, 0.5 * tile_m if offset_m is None else offset_m)
        values, report = optimise_placement(codec, rows, cols, time_limit_s=time_limit_s,
                                            max_iterations=max_iterations, seed=seed, on_progress=on_progress)
        return cls(codec, geometry, spacing_m, values, origin_xy_m, report)

    @property
    def rows(self) -> int:
        return int(self.values.shape[0])

    @property
    def cols(self) -> int:
        return int(self.values.shape[1])

    def tile_digits(self) -> np.ndarray:
        """Colour index of every tile ``(rows * cols, tiles)``, reading order (read-only)."""
        return self._cache["tile_digits"]

    def index_of(self, values) -> np.ndarray:
        """Flat grid index ``(N,)`` (row-major) of each value, -1 where not in the field."""
        return np.array([self._index.get(int(v), -1) for v in np.ravel(values).tolist()], dtype=int)

    def centres_m(self, index=None) -> np.ndarray:
        """Tag centres ``(N, 2)`` (x east, y north) for flat grid indices (all by default)."""
        c = self._cache["centres"]
        return c.copy() if index is None else c[np.asarray(index, dtype=int).ravel()]

    def tile_points_m(self, index=None) -> np.ndarray:
        """Tile centres ``(N, tiles, 2)`` in the field frame, reading order."""
        t = self._cache["tiles"]
        return t.copy() if index is None else t[np.asarray(index, dtype=int).ravel()]

    def bounds_m(self, margin_m: float = 0.0) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the printed area, metres."""
        half = self.geometry.size_m / 2.0 + margin_m + self.geometry.offset_m / 2.0
        c = self.centres_m()
        return (float(c[:, 0].min() - half), float(c[:, 1].min() - half),
                float(c[:, 0].max() + half), float(c[:, 1].max() + half))

    # ----- rendering -------------------------------------------------------------------
    def _tile_rects_m(self) -> tuple[np.ndarray, np.ndarray]:
        """All tiles as (x0, y0, x1, y1) metres ``(M, 4)`` and their sRGB colours ``(M, 3)``."""
        pts = self.tile_points_m().reshape(-1, 2)
        half = self.geometry.tile_m / 2.0
        rects = np.concatenate((pts - half, pts + half), axis=1)
        colours = self.codec.colours_rgb(self.values.ravel()).reshape(-1, 3)
        return rects, colours

    def rasterise(self, metres_per_px: float, margin_m: float = 0.1) -> tuple[np.ndarray, tuple[float, float]]:
        """The field as an sRGB float32 image ``(H, W, 3)`` (row 0 north) and the (x, y)
        field position of the image centre, metres. Tiles are anti-aliased exactly."""
        mpp = validate.positive_scalar("metres_per_px", metres_per_px)
        x0, y0, x1, y1 = self.bounds_m(margin_m)
        w, h = math.ceil((x1 - x0) / mpp), math.ceil((y1 - y0) / mpp)
        if max(w, h) > MAX_PRINT_SIDE_PX:
            raise InputError(f"rendering at {mpp} m/px needs {w} x {h} px; at most {MAX_PRINT_SIDE_PX} "
                             "per side: lower the resolution")
        image = np.empty((h, w, 3), np.float32)
        image[:] = PAPER_RGB
        rects, colours = self._tile_rects_m()
        px = np.stack(((rects[:, 0] - x0) / mpp, (y1 - rects[:, 3]) / mpp,
                       (rects[:, 2] - x0) / mpp, (y1 - rects[:, 1]) / mpp), axis=1)
        fill_rects(image, px, colours)
        centre = (x0 + w * mpp / 2.0, y1 - h * mpp / 2.0)
        return image, centre

    def write_png(self, path: str | Path, dpi: float = 150.0) -> Path:
        """Print-ready PNG at ``dpi`` (1:1 scale when printed at that DPI)."""
        import cv2

        dpi = validate.positive_scalar("dpi", dpi)
        image, _ = self.rasterise(0.0254 / dpi, margin_m=0.02)
        out = Path(path)
        bgr = cv2.cvtColor(np.round(image * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
        if not cv2.imwrite(str(out), bgr):
            raise DataError(f"could not write PNG {out}")
        return out

    def write_svg(self, path: str | Path) -> Path:
        """Vector sheet (SVG, millimetre units, 1:1) of the whole field."""
        x0, y0, x1, y1 = self.bounds_m(0.02)
        rects, colours = self._tile_rects_m()
        mm = 1000.0
        parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{(x1 - x0) * mm:.2f}mm" '
                 f'height="{(y1 - y0) * mm:.2f}mm" viewBox="0 0 {(x1 - x0) * mm:.3f} {(y1 - y0) * mm:.3f}">',
                 f'<rect width="100%" height="100%" fill="#{_hex(PAPER_RGB)}"/>']
        for (a, b, c, d), col in zip(rects, colours, strict=True):
            parts.append(f'<rect x="{(a - x0) * mm:.3f}" y="{(y1 - d) * mm:.3f}" width="{(c - a) * mm:.3f}" '
                         f'height="{(d - b) * mm:.3f}" fill="#{_hex(col)}"/>')
        parts.append("</svg>")
        out = Path(path)
        out.write_text("\n".join(parts))
        return out

    # ----- persistence -----------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"format": FORMAT, "version": 1, "colors": self.codec.colors, "tiles": self.codec.tiles,
                "palette_rgb": self.codec.palette_rgb.tolist(), "tile_m": self.geometry.tile_m,
                "gap_m": self.geometry.gap_m, "offset_m": self.geometry.offset_m,
                "spacing_m": self.spacing_m, "origin_xy_m": list(self.origin_xy_m),
                "values": self.values.tolist(),
                "placement": None if self.placement is None else asdict(self.placement)}

    @classmethod
    def from_dict(cls, d: dict, source: str = "tag field") -> TagField:
        """Field from its saved form (:class:`TagFieldFile`); DataError naming ``source`` and the key."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise DataError(f"{source}: not a skyfix tag field (expected format {FORMAT!r})")
        f = convert(d, TagFieldFile, source)
        try:
            codec = TileCodec(f.colors, f.tiles, np.asarray(f.palette_rgb, float))
            geometry = TagGeometry(f.tiles, f.tile_m, f.gap_m, f.offset_m)
            return cls(codec, geometry, f.spacing_m, np.asarray(f.values, dtype=np.int64), f.origin_xy_m, f.placement)
        except ValueError as exc:  # InputError, or ragged values rows
            raise DataError(f"{source}: {exc}") from exc

    def save(self, path: str | Path) -> Path:
        out = Path(path)
        out.write_text(json.dumps(self.to_dict(), indent=1))
        return out

    @classmethod
    def load(cls, path: str | Path) -> TagField:
        return cls.from_dict(read_json(path, "tag field file"), f"tag field file {path}")


_Rgb = Annotated[list[Annotated[float, Meta(ge=0, le=1)]], Meta(min_length=3, max_length=3)]


class TagFieldFile(msgspec.Struct, kw_only=True):
    """A tile-tag field as :meth:`TagField.save` writes it (x east, y north, metres; row 0 south).

    Example:
        >>> convert({"format": FORMAT, "colors": 6}, TagFieldFile, "f.json")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        skyfix.errors.DataError: f.json: object missing required field `tiles`
    """

    format: Literal["skyfix.tags.TagField"]
    version: Literal[1] = 1
    colors: Annotated[int, Meta(ge=2, description="number of tile colours")]
    tiles: Annotated[int, Meta(description="tiles per tag")]
    palette_rgb: Annotated[list[_Rgb], Meta(description="sRGB in [0, 1] per colour")]
    tile_m: Annotated[float, Meta(gt=0)]
    gap_m: Annotated[float, Meta(ge=0)]
    offset_m: Annotated[float, Meta(ge=0, description="displacement of the lower-right tile")]
    spacing_m: Annotated[float, Meta(gt=0, description="tag centre to centre")]
    origin_xy_m: tuple[float, float] = (0.0, 0.0)
    values: Annotated[list[list[Annotated[int, Meta(ge=0)]]], Meta(description="tag values, rows x cols, row 0 south")]
    placement: PlacementReport | None = None


def tag_field_json_schema() -> dict:
    """JSON Schema of the tag field file (:class:`TagFieldFile`), published in docs/schemas/."""
    return json_schema(TagFieldFile) | {"title": "skyfix tag field"}


def _hex(rgb: np.ndarray) -> str:
    return "".join(f"{int(round(float(c) * 255)):02x}" for c in rgb)
