"""Hotspot detection: centroids on known blobs, frame kinds, dead pixels, bad input."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from skyfix.errors import InputError
from skyfix.thermal import (
    RelativeTemperatureWarning,
    apply_palette,
    detect_hotspots,
    palette_to_intensity,
)

H, W = 512, 640


def blob_frame(u: float, v: float, *, peak_c: float = 300.0, sigma_px: float = 3.0, ambient_c: float = 20.0,
               noise_c: float = 0.05, seed: int = 0, shape: tuple[int, int] = (H, W)) -> np.ndarray:
    """Float deg C frame with a Gaussian hotspot centred at (u, v) (OpenCV pixel centres)."""
    rng = np.random.default_rng(seed)
    vv, uu = np.mgrid[0:shape[0], 0:shape[1]]
    img = ambient_c + (peak_c - ambient_c) * np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * sigma_px ** 2))
    return (img + rng.normal(0, noise_c, img.shape)).astype(np.float32)


def to_counts(celsius: np.ndarray, kelvin_per_count: float = 0.01) -> np.ndarray:
    return np.clip(np.rint((celsius + 273.15) / kelvin_per_count), 0, 65535).astype(np.uint16)


def to_u8(celsius: np.ndarray, lo: float = 0.0, hi: float = 400.0) -> np.ndarray:
    return np.clip((celsius - lo) / (hi - lo) * 255 + 0.5, 0, 255).astype(np.uint8)


@pytest.mark.parametrize(("u", "v"), [(300.3, 200.7), (17.25, 480.5), (600.0, 30.9)])
def test_float_centroid_is_subpixel_exact_on_symmetric_blob(u, v):
    img = blob_frame(u, v)
    spots = detect_hotspots(img)
    assert len(spots) == 1
    # Symmetric blob, excess weighting: only the 0.05 C noise moves the centroid (<< 0.01 px).
    assert spots[0].u_px == pytest.approx(u, abs=0.01)
    assert spots[0].v_px == pytest.approx(v, abs=0.01)
    assert spots[0].units == "celsius" and spots[0].radiometric
    assert spots[0].peak == pytest.approx(float(img.max()), abs=0.2)


def test_counts_and_float_agree_and_report_celsius():
    img = blob_frame(250.4, 300.6, peak_c=350.0)
    a = detect_hotspots(img)[0]
    b = detect_hotspots(to_counts(img))[0]
    # 0.01 K counts quantisation: centroid shift well below 0.01 px, same hot area.
    assert b.u_px == pytest.approx(a.u_px, abs=0.01) and b.v_px == pytest.approx(a.v_px, abs=0.01)
    assert b.peak == pytest.approx(a.peak, abs=0.02) and b.threshold == pytest.approx(100.0, abs=1e-6)
    assert abs(a.area_px - b.area_px) <= 1
    c = detect_hotspots(to_counts(img, 0.04), kelvin_per_count=0.04)[0]
    assert c.peak == pytest.approx(a.peak, abs=0.1)


def test_threshold_is_in_celsius_for_radiometric_frames():
    img = blob_frame(100.0, 100.0, peak_c=150.0)
    assert detect_hotspots(img, threshold=200.0) == []
    assert len(detect_hotspots(img, threshold=120.0)) == 1
    assert len(detect_hotspots(to_counts(img), threshold=120.0)) == 1


def test_eight_bit_white_and_black_hot_warn_and_find_the_blob():
    img = blob_frame(320.6, 250.2, peak_c=380.0, sigma_px=4.0)
    u8 = to_u8(img)
    with pytest.warns(RelativeTemperatureWarning):
        white = detect_hotspots(u8)
    with pytest.warns(RelativeTemperatureWarning):
        black = detect_hotspots(255 - u8, palette="black-hot")
    for spots in (white, black):
        assert len(spots) == 1 and spots[0].units == "level"
        # 8-bit quantisation of a symmetric blob: centroid within 0.05 px.
        assert spots[0].u_px == pytest.approx(320.6, abs=0.05)
        assert spots[0].v_px == pytest.approx(250.2, abs=0.05)


@pytest.mark.parametrize("palette", ["ironbow", "arctic"])
def test_palette_round_trip_and_detection(palette):
    levels = np.tile(np.arange(256, dtype=np.uint8), (4, 1))
    back = palette_to_intensity(apply_palette(levels, palette), palette)
    # 6-bit-per-channel inverse table: a level comes back within a few levels of itself.
    assert np.abs(back.astype(int) - levels.astype(int)).max() <= 4
    rgb = apply_palette(to_u8(blob_frame(200.5, 150.5, peak_c=380.0, sigma_px=4.0)), palette)
    with pytest.warns(RelativeTemperatureWarning):
        spots = detect_hotspots(rgb, palette=palette)
    assert len(spots) == 1
    assert spots[0].u_px == pytest.approx(200.5, abs=0.2) and spots[0].v_px == pytest.approx(150.5, abs=0.2)


def test_wrong_palette_or_bgr_is_refused():
    rgb = apply_palette(to_u8(blob_frame(200.5, 150.5)), "ironbow")
    with pytest.raises(InputError, match="palette"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RelativeTemperatureWarning)
        detect_hotspots(rgb[..., ::-1].copy(), palette="ironbow")


def test_dead_pixels_and_hot_pairs_never_become_fires():
    rng = np.random.default_rng(3)
    img = (25.0 + rng.normal(0, 0.1, (H, W))).astype(np.float32)
    idx = rng.choice(H * W, 200, replace=False)
    img.ravel()[idx] = 382.2  # stuck at the top of the counts range
    img[100, 100:102] = 382.2  # two adjacent stuck pixels
    img[300:302, 400] = 382.2
    assert detect_hotspots(img) == []
    assert detect_hotspots(to_counts(img)) == []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RelativeTemperatureWarning)
        assert detect_hotspots(to_u8(img)) == []


def test_stuck_pixel_touching_a_fire_does_not_pull_its_centroid():
    img = blob_frame(300.0, 200.0, peak_c=300.0, sigma_px=3.0)
    ref = detect_hotspots(img)[0]
    img[200, 305] = 382.2  # at the blob's edge, ~2x the local temperature
    hit = detect_hotspots(img)[0]
    # Unfiltered, that pixel would move the centroid by ~0.25 px; the 3x3 median removes it.
    assert hit.u_px == pytest.approx(ref.u_px, abs=0.02)
    assert hit.peak == pytest.approx(ref.peak, abs=0.01)


def test_noise_only_frames_have_no_hotspots():
    rng = np.random.default_rng(5)
    for _ in range(5):
        img = (30.0 + 5.0 * rng.standard_normal((H, W))).astype(np.float32)
        assert detect_hotspots(img) == []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RelativeTemperatureWarning)
            assert detect_hotspots(to_u8(img, 0, 150)) == []


def test_nan_pixels_are_no_data():
    img = blob_frame(300.0, 200.0)
    img[:, :50] = np.nan
    img[200, 301] = np.nan  # inside the fire
    spots = detect_hotspots(img)
    assert len(spots) == 1 and spots[0].u_px == pytest.approx(300.0, abs=0.1)


@pytest.mark.parametrize(("h", "w"), [(500, 630), (37, 41), (512, 644)])
def test_any_frame_size(h, w):
    big = blob_frame(w - 6.0, h - 7.5, sigma_px=2.0, shape=(h + 3, w + 5))
    for img in (big[:h, :w], np.ascontiguousarray(big[:h, :w])):  # a view (not contiguous) and a copy
        spots = detect_hotspots(img)
        assert len(spots) == 1
        assert spots[0].u_px == pytest.approx(w - 6.0, abs=0.01)
        assert spots[0].v_px == pytest.approx(h - 7.5, abs=0.01)


def test_two_fires_sorted_by_area():
    img = np.maximum(blob_frame(100.0, 100.0, sigma_px=2.0), blob_frame(400.0, 300.0, sigma_px=5.0, seed=1))
    spots = detect_hotspots(img)
    assert [round(s.u_px) for s in spots] == [400, 100]
    u0, v0, w, h = spots[0].bbox_px
    assert u0 <= 400 < u0 + w and v0 <= 300 < v0 + h


@pytest.mark.parametrize(("frame", "message"), [
    (np.zeros((H, W), np.int32), "dtype"),
    (np.zeros((H, W, 4), np.uint8), "shape"),
    (np.zeros((0, 0), np.uint16), "empty"),
    (np.zeros(10, np.float32), "shape"),
    (np.full((H, W), 30000, np.uint16), "constant"),
    (np.full((H, W), 7, np.uint8), "constant"),
    (np.full((H, W), np.nan, np.float32), "NaN"),
    (np.full((H, W), 500.0, np.float32), "constant"),
    ([[1.0, 2.0], [3.0, 4.0]], "numpy array"),
])
def test_bad_frames_raise_input_error(frame, message):
    with pytest.raises(InputError, match=message), warnings.catch_warnings():
        warnings.simplefilter("ignore", RelativeTemperatureWarning)
        detect_hotspots(frame)


def test_bad_options_raise_input_error():
    img = blob_frame(100.0, 100.0)
    with pytest.raises(InputError, match="min_area_px"):
        detect_hotspots(img, min_area_px=1)
    with pytest.raises(InputError, match="palette"):
        detect_hotspots(np.zeros((H, W, 3), np.uint8), palette="rainbow")
    with pytest.raises(InputError, match="white-hot"):
        detect_hotspots(to_u8(img), palette="ironbow")
    with pytest.raises(InputError, match="kelvin_per_count"):
        detect_hotspots(to_counts(img), kelvin_per_count=0.0)
    with pytest.raises(InputError, match="threshold"):
        detect_hotspots(img, threshold=float("nan"))


def test_caller_frame_is_not_modified():
    img = blob_frame(100.0, 100.0)
    img[5, 5] = np.nan
    before = img.copy()
    detect_hotspots(img)
    np.testing.assert_array_equal(img, before)


def _whole_frame_reference(celsius: np.ndarray, thr_c: float, min_area_px: int) -> list[tuple]:
    """The detector's definition computed the slow way, with scipy on the whole frame:
    8-connected components of pixels above the threshold, a 3x3 median (edge pixels
    replicated) within each component's box grown by one pixel, the excess-weighted centroid
    of the component's pixels still above the threshold, the peak bounded by twice the
    hottest neighbour's excess."""
    from scipy import ndimage

    labels, n = ndimage.label(celsius > thr_c, structure=np.ones((3, 3)))
    out = []
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        rows, cols = box
        if np.count_nonzero(labels[box] == k) < min_area_px:
            continue
        r0, r1 = max(rows.start - 1, 0), min(rows.stop + 1, celsius.shape[0])
        c0, c1 = max(cols.start - 1, 0), min(cols.stop + 1, celsius.shape[1])
        patch = np.where(np.isnan(celsius[r0:r1, c0:c1]), thr_c, celsius[r0:r1, c0:c1]).astype(np.float64)
        mine = labels[r0:r1, c0:c1] == k
        excess = np.where(mine, np.maximum(ndimage.median_filter(patch, 3, mode="nearest") - thr_c, 0.0), 0.0)
        if np.count_nonzero(excess) < min_area_px:
            continue
        vv, uu = np.mgrid[r0:r1, c0:c1]
        ring = ndimage.maximum_filter(np.pad(patch, 1, constant_values=-np.inf), footprint=[[1, 1, 1], [1, 0, 1], [1, 1, 1]])
        peak = np.minimum(patch, 2.0 * ring[1:-1, 1:-1] - thr_c)[mine].max()
        out.append((np.sum(uu * excess) / excess.sum(), np.sum(vv * excess) / excess.sum(),
                    np.count_nonzero(excess), peak))
    return sorted(out, key=lambda s: (-s[2], s[0]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_block_scan_finds_what_labelling_the_whole_frame_finds(seed):
    """The detector scans only 16x16 blocks with hot pixels and drops lone blocks of stray
    pixels; on frames full of dead pixels, hot pairs, NaN holes and fires of every size
    (frame sizes not multiples of 16, fires on the edges) it reports exactly the
    whole-frame definition: same fires, centroids to 1e-6 px (float32 sums), same areas."""
    rng = np.random.default_rng(seed)
    h, w = 250 + 7 * seed, 333 - 5 * seed
    img = (25.0 + 3.0 * rng.standard_normal((h, w))).astype(np.float32)
    vv, uu = np.mgrid[0:h, 0:w]
    for u, v, s in zip(rng.uniform(-2, w + 2, 14), rng.uniform(-2, h + 2, 14), rng.uniform(0.6, 5.0, 14), strict=True):
        img += (250.0 * np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * s * s))).astype(np.float32)
    for k, s in enumerate((0.7, 0.8, 0.9, 1.1)):  # small fires alone in a block (and dead pixels near them)
        img += (250.0 * np.exp(-((uu - 16 * (2 * k + 1) - 7.5) ** 2 + (vv - 16 * (k + 3) - 7.5) ** 2) / (2 * s * s))
                ).astype(np.float32)
    img[rng.random((h, w)) < 0.0006] = 500.0  # dead pixels: most blocks hold none, a few touch fires
    img[rng.random((h, w)) < 0.01] = np.nan
    for min_area in (2, 4, 9):
        ref = _whole_frame_reference(img.astype(np.float64), 100.0, min_area)
        got = sorted(detect_hotspots(img, threshold=100.0, min_area_px=min_area), key=lambda s: (-s.area_px, s.u_px))
        assert len(ref) >= 3 and len(got) == len(ref)
        for spot, (u, v, area, peak) in zip(got, ref, strict=True):
            assert spot.u_px == pytest.approx(u, abs=1e-6) and spot.v_px == pytest.approx(v, abs=1e-6)
            assert spot.area_px == area and spot.peak == pytest.approx(peak, rel=1e-6)
