"""Geoid heights (EGM96, EGM2008): altitudes above mean sea level <-> WGS84 ellipsoid heights.

Autopilots, EXIF and most DEMs give altitudes above mean sea level (the geoid, ``amsl``);
GNSS fixes and skyfix's frames use heights above the WGS84 ellipsoid. The two differ by
the geoid undulation N (−107 m to +86 m over the Earth): ``h_ellipsoid = h_amsl + N``.

N comes from the EGM96 15' grid applied by PROJ (pyproj's ``vgridshift``), the model
ArduPilot, PX4 and most GNSS receivers use for their AMSL output, or EGM2008's 2.5' grid
where it is installed (``model="egm2008"``). :class:`skyfix.geo.Height` carries a height
with its datum and converts through these functions. A grid is data, not
code: it is found in ``$SKYFIX_GEOID_GRID`` (EGM96 only, a file path), PROJ's data directories
(``$PROJ_DATA``, pyproj's own) or ``/usr/share/proj`` (Debian/Ubuntu package
``proj-data``). Nothing is downloaded at run time; when no grid is found a
:class:`~skyfix.errors.NotAvailableError` says how to install one.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import pyproj

from skyfix import validate
from skyfix.errors import InputError, NotAvailableError

#: Geoid model -> grid file names on PROJ's CDN and the classic ones (EGM96 15', EGM2008 2.5').
GEOID_GRIDS = {"egm96": ("us_nga_egm96_15.tif", "egm96_15.gtx"),
               "egm2008": ("us_nga_egm08_25.tif", "egm08_25.gtx")}
_SYSTEM_DIRS = ("/usr/share/proj", "/usr/local/share/proj")
_CELL_DEG = 1e-3  # cache cell of undulation_near_m: ~100 m, over which the geoid moves by < 1 cm


def _candidate_dirs() -> list[Path]:
    dirs = [os.environ.get("PROJ_DATA", ""), os.environ.get("PROJ_LIB", "")]
    dirs += [pyproj.datadir.get_data_dir(), pyproj.datadir.get_user_data_dir()]
    dirs += list(_SYSTEM_DIRS)
    out: list[Path] = []
    for entry in dirs:
        out += [Path(p) for p in entry.split(os.pathsep) if p]
    return out


def find_geoid_grid(model: str = "egm96") -> Path:
    """Path of the grid file of geoid ``model`` (``"egm96"`` or ``"egm2008"``);
    NotAvailableError (with the fix) when none is installed. ``$SKYFIX_GEOID_GRID`` overrides
    the EGM96 grid.

    Example:
        >>> find_geoid_grid("egm96").suffix in (".gtx", ".tif")
        True
    """
    if model not in GEOID_GRIDS:
        raise InputError(f"unknown geoid model {model!r}; expected one of {list(GEOID_GRIDS)}")
    override = os.environ.get("SKYFIX_GEOID_GRID")
    if override and model == "egm96":
        path = Path(override)
        if not path.is_file():
            raise NotAvailableError(f"SKYFIX_GEOID_GRID={override}: no such file")
        return path
    names = GEOID_GRIDS[model]
    for folder in _candidate_dirs():
        for name in names:
            if (folder / name).is_file():
                return folder / name
    how = "install Debian's 'proj-data' package (apt-get install proj-data), " if model == "egm96" else ""
    raise NotAvailableError(
        f"{model.upper()} geoid grid not found (looked for " + " or ".join(names)
        + f" in PROJ_DATA, pyproj's data folders and /usr/share/proj): {how}fetch it with PROJ's "
        f"'projsync --file {names[0]}' (https://cdn.proj.org/{names[0]}) or put it in one of those folders")


@functools.lru_cache(maxsize=len(GEOID_GRIDS))
def _undulation_transformer(model: str) -> pyproj.Transformer:
    grid = find_geoid_grid(model)
    # vgridshift with multiplier +1 maps h=0 to h=N: the grid value itself.
    return pyproj.Transformer.from_pipeline(f"+proj=vgridshift +grids={grid} +multiplier=1")


def geoid_undulation_m(lat_deg, lon_deg, model: str = "egm96") -> np.ndarray:
    """Geoid height N (m above the WGS84 ellipsoid) of ``model`` at WGS84 (lat_deg, lon_deg).

    Vectorised over broadcastable inputs. Example:

    >>> round(float(geoid_undulation_m(0.0, 0.0)), 2)
    17.16
    """
    lat, lon = np.broadcast_arrays(validate.latitude("lat_deg", lat_deg),
                                   validate.longitude("lon_deg", lon_deg))
    _, _, n_m = _undulation_transformer(model).transform(lon, lat, np.zeros(lat.shape))
    n_m = np.asarray(n_m, dtype=float)
    if not np.all(np.isfinite(n_m)):
        raise NotAvailableError(f"{model.upper()} grid gave no value at some of the positions given")
    return n_m


@functools.lru_cache(maxsize=4096)
def _cell_undulation_m(lat_cell: int, lon_cell: int, model: str) -> float:
    return float(geoid_undulation_m(lat_cell * _CELL_DEG, lon_cell * _CELL_DEG, model))


def undulation_near_m(lat_deg: float, lon_deg: float, model: str = "egm96") -> float:
    """N (m) at the centre of the 0.001 deg cell holding (lat_deg, lon_deg), cached: for
    telemetry at 10 Hz, where the ~100 m cell moves N by less than a centimetre.

    Example:
        >>> abs(undulation_near_m(47.00004, 8.00004) - float(geoid_undulation_m(47.00004, 8.00004))) < 0.01
        True
    """
    lat = float(validate.latitude("lat_deg", lat_deg))
    lon = float(validate.longitude("lon_deg", lon_deg))
    return _cell_undulation_m(round(lat / _CELL_DEG), round(lon / _CELL_DEG), model)


def amsl_to_ellipsoidal_m(lat_deg, lon_deg, alt_amsl_m) -> np.ndarray:
    """Height above mean sea level (EGM96) -> height above the WGS84 ellipsoid, metres.

    Example:
        >>> round(float(amsl_to_ellipsoidal_m(47.0, 8.0, 500.0)), 2)  # the geoid is 48.39 m up there
        548.39
    """
    alt = validate.finite_array("alt_amsl_m", alt_amsl_m)
    return alt + geoid_undulation_m(lat_deg, lon_deg)


def ellipsoidal_to_amsl_m(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """Height above the WGS84 ellipsoid -> height above mean sea level (EGM96), metres.

    Example:
        >>> round(float(ellipsoidal_to_amsl_m(47.0, 8.0, 548.39)), 2)
        500.0
    """
    alt = validate.finite_array("alt_m", alt_m)
    return alt - geoid_undulation_m(lat_deg, lon_deg)
