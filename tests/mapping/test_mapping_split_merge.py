"""Split, align and merge of submodels (skyfix.mapping.submodels, .align, .merge) on synthetic inputs:
the parts, a known misalignment recovered, and rasters/clouds merged block by block without a seam."""

from __future__ import annotations

import numpy as np
import pytest

from skyfix.errors import ConfigurationError, InputError
from skyfix.mapping.align import align_submodels, apply
from skyfix.mapping.grid import Grid
from skyfix.mapping.merge import Part, merge_points, merge_rasters, read_ply_header
from skyfix.mapping.submodels import load_split, part_count, save_split, split_photos


def _grid_survey(lines: int = 10, per_line: int = 10, line_m: float = 14.0, photo_m: float = 8.0):
    names = [f"IMG_{i:04d}.jpg" for i in range(lines * per_line)]
    en = np.array([(line * line_m, k * photo_m) for line in range(lines) for k in range(per_line)], float)
    return names, en


def test_split_is_balanced_contiguous_with_an_overlap_band_and_order_free():
    names, en = _grid_survey()
    subs = split_photos(names, en, 25, overlap_m=15.0)
    assert len(subs) == 4 == part_count(100, 25)
    cores = [set(s.core) for s in subs]
    assert sorted(len(c) for c in cores) == [25, 25, 25, 25]
    assert set().union(*cores) == set(names) and sum(map(len, cores)) == 100  # each photo in one core
    pos = dict(zip(names, en, strict=True))
    for s in subs:
        core = np.array([pos[n] for n in s.core])
        for n in s.shared:  # shared: another part's photo within the band of this core
            assert n not in s.core
            assert np.min(np.linalg.norm(core - pos[n], axis=1)) <= 15.0
        outside = set(names) - set(s.core) - set(s.shared)
        for n in outside:
            assert np.min(np.linalg.norm(core - pos[n], axis=1)) > 15.0
        # contiguous: a part's core is a block of the grid (its bounding box holds no other core)
        lo, hi = core.min(axis=0), core.max(axis=0)
        inside = [n for n in names if np.all(pos[n] >= lo) and np.all(pos[n] <= hi)]
        assert set(inside) == set(s.core)
        assert len(s.shared) > 0
    rng = np.random.default_rng(3)
    order = rng.permutation(100)
    again = split_photos([names[i] for i in order], en[order], 25, overlap_m=15.0)
    assert [s.to_dict() for s in again] == [s.to_dict() for s in subs]
    assert len(split_photos(names, en, 33, 10.0)) == 3
    assert sorted(len(s.core) for s in split_photos(names, en, 33, 10.0)) == [33, 33, 34]


def test_split_refuses_bad_options_and_round_trips(tmp_path):
    names, en = _grid_survey(2, 3)
    with pytest.raises(InputError, match="at least 3"):
        split_photos(names, en, 2, 10.0)
    with pytest.raises(InputError, match="split-overlap"):
        split_photos(names, en, 3, -1.0)
    with pytest.raises(InputError, match="unique"):
        split_photos(names[:-1] + names[:1], en, 3, 1.0)
    with pytest.raises(InputError, match="finite"):
        split_photos(names, en[:-1], 3, 1.0)
    subs = split_photos(names, en, 3, 10.0)
    save_split(tmp_path / "split.json", subs, 3, 10.0)
    loaded, target, overlap = load_split(tmp_path / "split.json")
    assert (target, overlap) == (3, 10.0) and [s.to_dict() for s in loaded] == [s.to_dict() for s in subs]
    assert load_split(tmp_path / "none.json") is None


def _sim3(yaw_deg: float, tilt_deg: float, scale: float, shift):
    a, b = np.radians(yaw_deg), np.radians(tilt_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return np.hstack((scale * rz @ rx, np.asarray(shift, float)[:, None]))


def _georeference(centres: np.ndarray, gps: np.ndarray) -> np.ndarray:
    """A submodel fitted to its photos' GPS by least squares, as the pipeline's georef stage does."""
    import pycolmap

    return apply(np.asarray(pycolmap.estimate_sim3d(centres, gps).matrix()), centres)


def test_joint_alignment_ties_the_overlap_and_leaves_each_submodel_near_its_gps_fit():
    """Two submodels of a 6 x 6 grid share 12 photos. Each was reconstructed with its own shape error (a
    stretch along the lines, a dome across them) and then fitted to its own photos' GPS (0.3 m noise), so in the overlap they disagree
    by decimetres. Joint alignment brings the shared photos together to the models' own precision (1 cm
    noise here) without moving either away from the GPS (the whole stays as close to the truth as the
    fits were), while a shared photo placed 2 m wrong in one submodel is left out."""
    rng = np.random.default_rng(0)
    names, en = _grid_survey(6, 6)
    truth = np.column_stack((en, 40.0 + rng.normal(0, 0.3, len(en))))
    gps = truth + rng.normal(0, 0.3, truth.shape)

    def bent(p, stretch, dome):  # a shape error no similarity undoes: along-line stretch, a dome across
        q = p.copy()
        q[:, 1] *= 1.0 + stretch
        q[:, 2] += dome * (p[:, 0] - p[:, 0].mean()) ** 2
        return q

    c0 = _georeference(bent(truth[:24], 0.01, 0.002) + rng.normal(0, 0.01, (24, 3)), gps[:24])
    drift = np.array([0.3, -0.2, 0.25])  # the GPS of the later photos drifted (a random walk, as consumer GNSS)
    c1 = _georeference(bent(truth[12:], -0.01, -0.002) + rng.normal(0, 0.01, (24, 3)), gps[12:] + drift)
    c1[3] += [0.0, 0.0, 2.0]  # IMG_0015 badly placed in submodel 1
    centres = {0: dict(zip(names[:24], c0, strict=True)), 1: dict(zip(names[12:], c1, strict=True))}
    out = align_submodels(centres, (0.3, 0.3))
    assert out[0].shared == out[1].shared == 12
    assert out[0].left_out == out[1].left_out == ["IMG_0015.jpg"]
    good = np.arange(12) != 3
    assert np.sqrt(np.mean(np.sum((c0[12:] - c1[:12])[good] ** 2, axis=1))) > 0.4  # apart before
    a0, a1 = apply(out[0].matrix, c0[12:]), apply(out[1].matrix, c1[:12])
    after = np.sqrt(np.mean(np.sum((a0 - a1)[good] ** 2, axis=1)))
    # what no similarity can remove (the two shapes differ): the best fit of one onto the other alone
    best = np.sqrt(np.mean(np.sum((_georeference(c1[:12][good], c0[12:][good]) - c0[12:][good]) ** 2, axis=1)))
    assert after <= 1.2 * best + 0.01, (after, best)
    before = np.vstack((c0, c1[12:]))
    placed = np.vstack((apply(out[0].matrix, c0), apply(out[1].matrix, c1[12:])))
    rms = [float(np.sqrt(np.mean(np.sum((p - truth) ** 2, axis=1)))) for p in (before, placed)]
    assert rms[1] < rms[0] + 0.05, rms  # no further from the truth than the submodels' own GPS fits
    assert out[0].moved_rms_m < 0.3 and out[1].moved_rms_m < 0.3


def test_a_submodel_sharing_nothing_stays_on_its_own_georeference():
    names, en = _grid_survey(4, 5)
    pts = np.column_stack((en, np.full(len(en), 30.0)))
    gps = dict(zip(names, pts, strict=True))
    centres = {0: {n: gps[n] for n in names[:10]}, 1: {n: gps[n] + [0.5, -0.2, 0.3] for n in names[10:]}}
    out = align_submodels(centres)
    assert out[1].shared == 0 and np.isnan(out[1].rms_after_m)
    np.testing.assert_allclose(out[1].matrix, np.hstack((np.eye(3), np.zeros((3, 1)))), atol=1e-9)
    assert out[1].moved_rms_m < 1e-9


def _write(path, data, grid: Grid, nodata=None):
    import rasterio

    bands = data[None] if data.ndim == 2 else data
    with rasterio.open(path, "w", driver="GTiff", width=grid.width, height=grid.height, count=bands.shape[0],
                       dtype=bands.dtype, crs=f"EPSG:{grid.epsg}", transform=grid.affine(), nodata=nodata) as ds:
        ds.write(bands)


def test_rasters_merge_block_by_block_without_a_step_where_submodels_meet(tmp_path):
    """Two submodels of a sloping ground, overlapping 20 m; the second sits 0.5 m too high and 0.3 m east,
    which its alignment undoes. The merged DSM follows the ground across the boundary (no step), a hole in
    one is filled from the other, and the orthophoto has no shift there."""
    import rasterio

    res, epsg, origin = 0.25, 32632, np.array([500000.0, 4500000.0])
    rng = np.random.default_rng(1)
    texture = rng.integers(0, 255, (800, 800), dtype=np.uint8)  # 1 texel = 0.1 m, from the origin

    def ground(e, n):
        return 100.0 + 0.05 * e + 0.02 * n

    def ortho_at(e, n):  # the texture, smoothed to about an output pixel, at local metres
        import cv2

        tex = cv2.GaussianBlur(texture.astype(np.float32), (0, 0), 2.5)
        tex = (tex - tex.mean()) / tex.std() * 40 + 128
        return cv2.remap(tex, (e / 0.1).astype(np.float32), (n / 0.1).astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT).clip(0, 255).astype(np.uint8)

    parts = []
    for i, (west, shift) in enumerate(((0.0, np.zeros(3)), (30.0, np.array([0.3, 0.0, 0.5])))):
        grid = Grid(epsg, origin[0] + west, origin[1] + 40.0, res, 200, 160)  # 50 m x 40 m
        rows, cols = np.mgrid[0:grid.height, 0:grid.width]
        e, n = grid.centres_m(rows, cols)
        e, n = e - origin[0], n - origin[1]
        # this submodel sees the true point p at p + shift, so its cell at e shows the ground at e - shift
        z = ground(e - shift[0], n - shift[1]) + shift[2]
        if i == 1:
            z[40:60, 30:50] = np.nan  # a hole the other submodel covers
        _write(tmp_path / f"dsm{i}.tif", np.where(np.isfinite(z), z, -9999.0).astype(np.float32), grid, -9999.0)
        grey = ortho_at(e - shift[0], n - shift[1])
        rgba = np.stack((grey, grey, grey, np.full_like(grey, 255)))
        _write(tmp_path / f"ortho{i}.tif", rgba, grid)
        folder = tmp_path / f"s{i}"
        folder.mkdir()
        (tmp_path / f"dsm{i}.tif").rename(folder / "dsm.tif")
        (tmp_path / f"ortho{i}.tif").rename(folder / "orthophoto.tif")
        core = np.array([(west + 5.0 + 10 * k, 20.0) for k in range(4 if i == 0 else 4)])
        undo = np.hstack((np.eye(3), -shift[:, None]))
        parts.append(Part(i, folder, core, undo))
    blocks = []
    dsm_grid, ortho_grid, stats = merge_rasters(
        parts, origin, epsg, tmp_path / "dsm.tif", tmp_path / "ortho.tif", dsm_res_m=res, ortho_res_m=res,
        bounds_m=(origin[0], origin[1], origin[0] + 80.0, origin[1] + 40.0), z_ref_m=100.0, block_px=64,
        on_block=lambda: blocks.append(1))
    assert len(blocks) == 2 * (5 * 3)  # 320 x 160 cells in 64 px blocks, DSM then orthophoto
    with rasterio.open(tmp_path / "dsm.tif") as ds:
        z = ds.read(1, masked=True).filled(np.nan)
    rows, cols = np.mgrid[0:dsm_grid.height, 0:dsm_grid.width]
    e, n = dsm_grid.centres_m(rows, cols)
    err = z - ground(e - origin[0], n - origin[1])
    inner = np.isfinite(err)
    assert inner.mean() > 0.97
    # bilinear sampling of a plane is exact: any step would be the misalignment left over
    assert np.nanmax(np.abs(err)) < 1e-3
    assert np.isfinite(z[40:60, 150:170]).all()  # submodel 1's hole (its cols 30-50 = 37.5-42.5 m) filled
    seam = stats.to_dict()["0-1"]
    assert abs(seam["dsm_median_difference_m"]) < 1e-3 and seam["dsm_cells_compared"] > 1000
    # what remains: both orthophotos rounded to uint8 and one resampled bilinearly (0.02 px measured)
    assert seam["ortho_shift_px"] < 0.05
    # without the alignment the same seam shows 0.5 m of height and 1.2 px of shift
    raw = [Part(p.index, p.folder, p.core_en_m, np.hstack((np.eye(3), np.zeros((3, 1))))) for p in parts]
    _, _, stats_raw = merge_rasters(raw, origin, epsg, tmp_path / "dsm_raw.tif", tmp_path / "ortho_raw.tif",
                                    dsm_res_m=res, ortho_res_m=res, bounds_m=(origin[0], origin[1], origin[0] + 80.0,
                                                                             origin[1] + 40.0), z_ref_m=100.0)
    seam_raw = stats_raw.to_dict()["0-1"]
    assert seam_raw["dsm_median_difference_m"] == pytest.approx(-0.5 + 0.05 * 0.3, abs=0.01)
    assert seam_raw["ortho_shift_px"] == pytest.approx(0.3 / res, abs=0.05)


def test_points_merge_keeps_each_ground_once_and_streams(tmp_path):
    from skyfix.mapping.model_files import write_ply

    origin = np.array([500000.0, 4500000.0])
    parts = []
    for i, west in enumerate((0.0, 20.0)):
        folder = tmp_path / f"s{i}"
        folder.mkdir()
        e, n = np.meshgrid(np.arange(west, west + 40.0, 0.5), np.arange(0.0, 10.0, 0.5))
        xyz = np.column_stack((e.ravel() + origin[0], n.ravel() + origin[1], np.full(e.size, 50.0 + i)))
        write_ply(folder / "points.ply", xyz, np.full((len(xyz), 3), 10 * (i + 1), np.uint8))
        core = np.array([(west + 10.0, 5.0), (west + 20.0, 5.0)]) if i == 0 else np.array([(40.3, 5.0), (50.3, 5.0)])
        parts.append(Part(i, folder, core, np.hstack((np.eye(3), [[0.0], [0.0], [-1.0 * i]]))))
    count = merge_points(parts, origin, tmp_path / "merged.ply", chunk=97)
    n, offset = read_ply_header(tmp_path / "merged.ply")
    assert n == count
    from skyfix.mapping.model_files import PLY_DTYPE

    rec = np.fromfile(tmp_path / "merged.ply", PLY_DTYPE, offset=offset)
    east = rec["x"] - origin[0]
    # the boundary is halfway between the cores' nearest photos, 20 and 40.3 m: 30.15 m
    assert np.all((rec["r"] == 10) == (east < 30.15))
    assert len(rec) == 20 * 120  # 0-60 m at 0.5 m, 20 rows: every ground point once
    np.testing.assert_allclose(rec["z"], 50.0)  # the second part's +1 m undone by its alignment


def test_pipeline_stop_after_names_a_stage():
    from skyfix.mapping.pipeline import PipelineConfig

    with pytest.raises(ConfigurationError, match="stop_after"):
        PipelineConfig("a", "b", stop_after="nope")


@pytest.mark.parametrize("flags, named", [
    (["--split", "2"], "--split must be at least 3"),
    (["--scheduler", "tcp://127.0.0.1:9"], "only apply with --split"),
    (["--split", "10", "--workers", "0"], "--workers must be at least 1"),
    (["--split", "10", "--split-overlap", "-1"], "--split-overlap must be >= 0"),
    (["--split", "10", "--scheduler", "nothere"], "--scheduler must be an address"),
])
def test_map_split_flags_are_checked_up_front(flags, named, tmp_path, capsys):
    from skyfix.cli import main

    photos = tmp_path / "photos"
    photos.mkdir()
    rc = main(["map", str(photos), "-o", str(tmp_path / "out"), *flags])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and named in err[0] and "Traceback" not in err[0], err


def test_a_finished_submodel_is_reused_only_with_the_same_options(tmp_path):
    import json

    from skyfix.mapping.pipeline import PipelineConfig
    from skyfix.mapping.scale_out import _all_options, finished_result

    config = PipelineConfig(tmp_path / "photos", tmp_path)
    assert finished_result(config) is None
    (tmp_path / "work").mkdir(exist_ok=True)
    (tmp_path / "work" / "submodel_done.json").write_text(json.dumps({"registered": 7,
                                                                      "options": _all_options(config)}))
    assert finished_result(config)["registered"] == 7
    changed = PipelineConfig(tmp_path / "photos", tmp_path, resolution_cm=30.0)
    assert finished_result(changed) is None  # --resolution-cm changed: the ortho stage must run again
