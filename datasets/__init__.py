"""skyfix.datasets: the synthetic-image harness, the simulator and loaders for real data."""

from skyfix.datasets.render import GroundTexture, Rendered, render_ground

__all__ = ["GroundTexture", "Rendered", "render_ground"]
