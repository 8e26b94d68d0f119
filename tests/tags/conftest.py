"""Shared fixtures for the tags tests: one small field, its texture and a camera."""

import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.datasets.tag_scene import field_texture
from skyfix.tags.field import TagField


@pytest.fixture(scope="session")
def tag_field() -> TagField:
    # A fixed move budget (not a time limit) so every machine tests the same field.
    return TagField.generate(12, 12, tile_m=0.05, gap_m=0.02, spacing_m=0.25, time_limit_s=60.0,
                             max_iterations=25_000, seed=3)


@pytest.fixture(scope="session")
def tag_texture(tag_field):
    return field_texture(tag_field)


@pytest.fixture(scope="session")
def camera() -> Camera:
    return Camera.from_fov(640, 480, 60.0)


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(7)
