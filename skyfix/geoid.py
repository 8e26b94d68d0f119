"""EGM96 geoid heights: converting altitudes above mean sea level to WGS84 ellipsoid heights.

Autopilots, EXIF and most DEMs give altitudes above mean sea level (the geoid, ``amsl``);
GNSS fixes and skyfix's frames use heights above the WGS84 ellipsoid. The two differ by
the geoid undulation N (−107 m to +86 m over the Earth): ``h_ellipsoid = h_amsl + N``.

N comes from the EGM96 15' grid applied by PROJ (pyproj's ``vgridshift``), the model
ArduPilot, PX4 and most GNSS receivers use for their AMSL output. The grid is data, not
code: it is found in ``$SKYFIX_GEOID_GRID`` (a file path), PROJ's data directories
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
from skyfix.errors import NotAvailableError

#: Grid file names of EGM96 on a 15' grid: PROJ's current CDN name and the classic one.
EGM96_GRID_NAMES = ("us_nga_egm96_15.tif", "egm96_15.gtx")
_SYSTEM_DIRS = ("/usr/share/proj", "/usr/local/share/proj")


def _candidate_dirs() -> list[Path]:
    dirs = [os.environ.get("PROJ_DATA", ""), os.environ.get("PROJ_LIB", "")]
    dirs += [pyproj.datadir.get_data_dir(), pyproj.datadir.get_user_data_dir()]
    dirs += list(_SYSTEM_DIRS)
    out: list[Path] = []
    for entry in dirs:
        out += [Path(p) for p in entry.split(os.pathsep) if p]
    return out


def find_egm96_grid() -> Path:
    """Path of an EGM96 15' grid file; NotAvailableError (with the fix) when there is none.

    Example:
        >>> find_egm96_grid().suffix in (".gtx", ".tif")
        True
    """
    override = os.environ.get("SKYFIX_GEOID_GRID")
    if override:
        path = Path(override)
        if not path.is_file():
            raise NotAvailableError(f"SKYFIX_GEOID_GRID={override}: no such file")
        return path
    for folder in _candidate_dirs():
        for name in EGM96_GRID_NAMES:
            if (folder / name).is_file():
                return folder / name
    raise NotAvailableError(
        "EGM96 geoid grid not found (looked for " + " or ".join(EGM96_GRID_NAMES)
        + " in PROJ_DATA, pyproj's data folders and /usr/share/proj): install Debian's "
        "'proj-data' package (apt-get install proj-data) or point SKYFIX_GEOID_GRID at the file")


@functools.lru_cache(maxsize=1)
def _undulation_transformer() -> pyproj.Transformer:
    grid = find_egm96_grid()
    # vgridshift with multiplier +1 maps h=0 to h=N: the grid value itself.
    return pyproj.Transformer.from_pipeline(f"+proj=vgridshift +grids={grid} +multiplier=1")


def geoid_undulation_m(lat_deg, lon_deg) -> np.ndarray:
    """EGM96 geoid height N (m above the WGS84 ellipsoid) at WGS84 (lat_deg, lon_deg).

    Vectorised over broadcastable inputs. Example:

    >>> round(float(geoid_undulation_m(0.0, 0.0)), 2)
    17.16
    """
    lat, lon = np.broadcast_arrays(validate.latitude("lat_deg", lat_deg),
                                   validate.longitude("lon_deg", lon_deg))
    _, _, n_m = _undulation_transformer().transform(lon, lat, np.zeros(lat.shape))
    n_m = np.asarray(n_m, dtype=float)
    if not np.all(np.isfinite(n_m)):
        raise NotAvailableError("EGM96 grid gave no value at some of the positions given")
    return n_m


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
