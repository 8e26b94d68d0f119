import numpy as np
import pytest

from skyfix.errors import InputError
from skyfix.tags.codec import TagGeometry, TileCodec, spiral_order
from skyfix.tags.palette import choose_palette, palette_delta_e, srgb_to_lab


def test_known_value_base4():
    # The source's example: tiles 3, 2, 0, 1 read clockwise from the lower right = 3201 in base 4.
    codec = TileCodec(colors=4, tiles=4)
    assert codec.decode([3, 2, 0, 1])[0] == 3 * 64 + 2 * 16 + 0 * 4 + 1
    assert codec.encode(225).tolist() == [[3, 2, 0, 1]]


@pytest.mark.parametrize("colors,tiles", [(2, 4), (6, 4), (3, 9), (2, 16)])
def test_round_trip_every_value(colors, tiles):
    codec = TileCodec(colors=colors, tiles=tiles)
    values = np.arange(min(codec.capacity, 5000))
    assert np.array_equal(codec.decode(codec.encode(values)), values)


def test_bad_values_raise():
    codec = TileCodec(6, 4)
    with pytest.raises(InputError, match="values must be in"):
        codec.encode(6 ** 4)
    with pytest.raises(InputError, match="digits"):
        codec.decode([[0, 1, 6, 0]])
    with pytest.raises(InputError, match="tiles"):
        TileCodec(6, 5)


def test_reading_order_is_clockwise_from_lower_right():
    # (col, row) with row 0 south: LR, LL, UL, UR.
    assert spiral_order(2).tolist() == [[1, 0], [0, 0], [0, 1], [1, 1]]
    cells = spiral_order(3)
    assert cells[0].tolist() == [2, 0] and cells[-1].tolist() == [1, 1]
    assert len({tuple(c) for c in cells.tolist()}) == 9


def test_displaced_tile_is_lower_right_and_outwards():
    g = TagGeometry(4, 0.05, 0.02, 0.025)
    xy = g.tile_centres_m()
    assert xy[0, 0] == pytest.approx(0.035 + 0.025) and xy[0, 1] == pytest.approx(-0.035 - 0.025)
    assert g.size_m == pytest.approx(0.05 * 2 + 0.02 + 0.025)


def test_palette_far_apart_and_far_from_paper():
    pal = choose_palette(6)
    de = palette_delta_e(pal)
    assert de[~np.eye(6, dtype=bool)].min() > 60.0     # CIE76 > 60: unmistakable colours
    white = srgb_to_lab(np.ones(3))
    assert np.linalg.norm(srgb_to_lab(pal) - white, axis=1).min() > 60.0
    assert np.array_equal(pal, choose_palette(6))     # deterministic


def test_lab_known_values():
    assert srgb_to_lab(np.ones(3)) == pytest.approx([100.0, 0.0, 0.0], abs=1e-3)
    assert srgb_to_lab(np.zeros(3)) == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
    assert srgb_to_lab([1.0, 0.0, 0.0]) == pytest.approx([53.24, 80.09, 67.20], abs=0.05)
