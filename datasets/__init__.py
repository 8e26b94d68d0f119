"""skyfix.datasets: the synthetic-image harness, the simulator and loaders for real data."""

from __future__ import annotations

from skyfix.lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__, {"GroundTexture": "render", "Rendered": "render", "render_ground": "render"})
