"""A run interrupted after matching resumes without redoing extraction or matching;
photos without any GPS reconstruct unreferenced."""

from __future__ import annotations

import shutil
from pathlib import Path

import piexif
import pytest

from skyfix.mapping import sfm
from skyfix.mapping.pipeline import PipelineConfig, run_pipeline

DATA = Path(__file__).parents[1] / "data" / "seneca"
FAST = {"max_image_size_px": 1200, "max_features": 4000, "threads": 2}


def _spy_on_extract_and_match(monkeypatch) -> list[str]:
    """The names of sfm.extract / sfm.match as they get called (they still run)."""
    calls = []
    for name in ("extract", "match"):
        original = getattr(sfm, name)

        def spy(*args, _original=original, _name=name, **kwargs):
            calls.append(_name)
            return _original(*args, **kwargs)

        monkeypatch.setattr(sfm, name, spy)
    return calls


def test_interrupt_after_matching_then_resume(tmp_path, monkeypatch):
    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted(DATA.glob("*.jpg"))[1:5]:
        shutil.copy(p, photos / p.name)
    out = tmp_path / "project"

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt  # Ctrl-C while mapping

    monkeypatch.setattr(sfm, "reconstruct", interrupted)
    with pytest.raises(KeyboardInterrupt):  # 4 photos > 2: GPS-neighbour (spatial) matching
        run_pipeline(PipelineConfig(photos, out, exhaustive_max_photos=2, **FAST))
    monkeypatch.undo()
    assert (out / "work" / "stages" / "matches.json").exists()
    assert not (out / "work" / "stages" / "mapping.json").exists()

    calls = _spy_on_extract_and_match(monkeypatch)
    report = run_pipeline(PipelineConfig(photos, out, exhaustive_max_photos=2, **FAST))
    assert calls == []
    assert report.matching == "spatial"  # recorded by the interrupted run, not redone
    assert {"features", "matches"} <= set(report.resumed_stages)
    assert "mapping" not in report.resumed_stages
    assert len(report.registered) >= 3 and report.georeferenced


def test_no_gps_reconstructs_unreferenced(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted(DATA.glob("*.jpg"))[1:5]:
        exif = piexif.load(str(p))
        exif["GPS"], exif["thumbnail"] = {}, None
        piexif.insert(piexif.dump(exif), p.read_bytes(), str(photos / p.name))
    report = run_pipeline(PipelineConfig(photos, tmp_path / "project", **FAST))
    assert len(report.registered) >= 3
    assert not report.georeferenced
    assert any("not georeferenced" in w for w in report.warnings)
    assert (tmp_path / "project" / "points.ply").exists()
    assert not (tmp_path / "project" / "orthophoto.tif").exists()


def test_non_overlapping_photos_explained(tmp_path):
    from skyfix.errors import DataError

    photos = tmp_path / "photos"
    photos.mkdir()
    ends = sorted(DATA.glob("*.jpg"))
    for p in (ends[0], ends[-1]):  # 151 m apart along the line
        shutil.copy(p, photos / p.name)
    # At most 60 m above ground the footprint diagonal is 60 * 1500 / 836 = 108 m < 151 m.
    with pytest.raises(DataError, match="reconstructed nothing"):
        run_pipeline(PipelineConfig(photos, tmp_path / "project", max_agl_m=60.0, **FAST))
    import json

    saved = json.loads((tmp_path / "project" / "report.json").read_text())
    assert saved["isolated_by_gps"] == [ends[0].name, ends[-1].name]
    assert any("cannot overlap" in w for w in saved["warnings"])
    assert "reconstructed nothing" in saved["error"]


def test_barrel_correction_stage_feeds_mapping(tmp_path):
    from skyfix.distortion import Barrel

    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted(DATA.glob("*.jpg"))[1:5]:
        shutil.copy(p, photos / p.name)
    out = tmp_path / "project"
    report = run_pipeline(PipelineConfig(photos, out, barrel=Barrel(0.0, -0.01, 0.0), **FAST))
    corrected = sorted(p.name for p in (out / "work" / "corrected").glob("*.jpg"))
    assert corrected == sorted(p.name for p in photos.glob("*.jpg"))
    assert len(report.registered) >= 3 and report.georeferenced and report.georef_rms_m <= 5.0


def test_changed_option_reruns_the_stages_it_affects(tmp_path, monkeypatch):
    # Issue 20: a second run with --resolution-cm 30 kept the old orthophoto. Each stage
    # records the options it depends on; a changed one re-runs that stage and the later ones.
    import rasterio

    photos = tmp_path / "photos"
    photos.mkdir()
    for p in sorted(DATA.glob("*.jpg"))[1:5]:
        shutil.copy(p, photos / p.name)
    out = tmp_path / "project"
    first = run_pipeline(PipelineConfig(photos, out, **FAST))
    # Without --resolution-cm the orthophoto's pixel is the photos' GSD: flying height
    # 62.5 +- 7 m over the 836 px focal length (see test_mapping_pipeline.py).
    assert first.resolution_cm == pytest.approx(first.gsd_cm)
    assert 55.5 / 836.30 < first.gsd_cm / 100.0 < 69.5 / 836.30

    calls = _spy_on_extract_and_match(monkeypatch)
    coarse = run_pipeline(PipelineConfig(photos, out, resolution_cm=30.0, **FAST))
    assert calls == []
    assert {"features", "matches", "mapping", "georef", "dsm"} <= set(coarse.resumed_stages)
    assert "ortho" not in coarse.resumed_stages and coarse.resolution_cm == pytest.approx(30.0)
    with rasterio.open(out / "orthophoto.tif") as ds:
        assert ds.res[0] == pytest.approx(0.30)

    # A matching option: the database's matches are replaced, the features kept.
    again = run_pipeline(PipelineConfig(photos, out, resolution_cm=30.0, exhaustive_max_photos=2, **FAST))
    assert calls == ["match"] and again.matching == "spatial"
    assert "features" in again.resumed_stages and "matches" not in again.resumed_stages
    assert len(again.registered) >= 3 and again.georeferenced
