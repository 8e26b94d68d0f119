"""skyfix: keep drones localised and turn their imagery into maps.

Subpackages: ``skyfix.thermal``, ``skyfix.crps``, ``skyfix.tags``, ``skyfix.mapping``,
``skyfix.fusion``, ``skyfix.drivers``, ``skyfix.datasets``. The foundation lives here:
``skyfix.geo`` (WGS84 and local ENU frames), ``skyfix.camera`` (intrinsics, distortion,
poses, ground intersection), ``skyfix.types`` (measurements) and ``skyfix.errors``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("skyfix")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"
