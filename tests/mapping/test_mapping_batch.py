"""Batch correction of real photos: EXIF carried over, bad photos skipped, backends agree."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import piexif
import pytest

from skyfix.camera_io import load_camera, save_camera
from skyfix.errors import DataError, InputError
from skyfix.mapping.batch import CorrectionSpec, correct_photos, list_photos
from skyfix.mapping.correct import Undistortion
from skyfix.mapping.exif import read_metadata
from skyfix.mapping.lens import barrel_camera, parse_barrel

DATA = Path(__file__).parent / "data"
BARREL = parse_barrel("0.1 -0.32 0")


@pytest.fixture()
def photo_dir(tmp_path: Path) -> Path:
    src = tmp_path / "in"
    src.mkdir()
    for p in sorted(DATA.glob("*.jpg")):
        shutil.copy(p, src / p.name)
    good = (DATA / "IMG_0459.jpg").read_bytes()
    (src / "truncated.jpg").write_bytes(good[: len(good) // 2])
    (src / "not_a_photo.jpg").write_bytes(b"hello, I am text")
    img = cv2.imread(str(DATA / "IMG_0460.jpg"))
    cv2.imwrite(str(src / "no_exif.jpg"), img)
    return src


def test_metadata_of_real_photo():
    meta = read_metadata((DATA / "IMG_0459.jpg").read_bytes(), "IMG_0459")
    assert meta.make == "Canon" and meta.orientation == 1
    assert meta.gps_lat_deg == pytest.approx(41.0, abs=0.1) and meta.gps_lon_deg == pytest.approx(-83.3, abs=0.1)
    # FocalPlaneXResolution 4000000 / 732 px per inch: a 1200 px wide image on a 5.58 mm
    # sensor, 9.6 % off the 1/2.3-inch type's 6.17 mm (the tag was divided by 3 for a
    # 4000 -> 1200 px downscale), so the sensor table gives the focal length: 4.3 mm x 1200 / 6.17 mm.
    assert meta.focal_plane_px_per_mm == pytest.approx(4000000 / 732 / 25.4, rel=1e-9)
    assert meta.focal_length_px(1200, 900) == pytest.approx(4.3 * 1200 / 6.17, rel=1e-9)


def test_missing_and_corrupt_inputs_raise_data_errors(tmp_path):
    with pytest.raises(DataError, match="no EXIF"):
        read_metadata(cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))[1].tobytes(), "blank")
    with pytest.raises(DataError, match="not a JPEG"):
        read_metadata(b"GIF89a....", "gif")
    with pytest.raises(InputError, match="does not exist"):
        list_photos(tmp_path / "nowhere")


def test_batch_corrects_good_photos_and_reports_bad_ones(photo_dir, tmp_path):
    out = tmp_path / "out"
    report = correct_photos(list_photos(photo_dir), out, CorrectionSpec(barrel=BARREL), workers=2, progress=False)
    assert sorted(Path(r.output).name for r in report.written) == ["IMG_0459.jpg", "IMG_0460.jpg"]
    reasons = {Path(r.source).name: r.error for r in report.skipped}
    assert set(reasons) == {"truncated.jpg", "not_a_photo.jpg", "no_exif.jpg"}
    assert "truncated" in reasons["truncated.jpg"] and "no EXIF" in reasons["no_exif.jpg"]

    before = piexif.load(str(photo_dir / "IMG_0459.jpg"))
    after = piexif.load(str(out / "IMG_0459.jpg"))
    assert after["GPS"] == before["GPS"]
    assert after["0th"][piexif.ImageIFD.Make] == before["0th"][piexif.ImageIFD.Make]
    assert after["0th"][piexif.ImageIFD.Orientation] == before["0th"][piexif.ImageIFD.Orientation]
    f_before = before["Exif"][piexif.ExifIFD.FocalLength]
    f_after = after["Exif"][piexif.ExifIFD.FocalLength]
    assert f_after[0] / f_after[1] == pytest.approx(f_before[0] / f_before[1] / BARREL.d, rel=1e-4)
    cam = report.written[0].output_camera
    raw_f = read_metadata((photo_dir / "IMG_0459.jpg").read_bytes()).focal_length_px(1200, 900)
    assert cam["fx_px"] == pytest.approx(raw_f / BARREL.d)
    # Pixels: the written JPEG is the remapped photo encoded at the input's quality (90)
    # and chroma subsampling (4:2:0): no further from the remapped pixels than OpenCV's
    # own q90 encoding of them (2.1 grey levels mean on this photo), 2 % slack.
    import simplejpeg

    from skyfix.mapping.exif import jpeg_quality

    raw = cv2.imread(str(photo_dir / "IMG_0459.jpg"))
    expected = Undistortion.for_barrel(BARREL, 1200, 900).apply(raw).astype(np.int16)
    written = (out / "IMG_0459.jpg").read_bytes()
    assert jpeg_quality(written) == 90 and simplejpeg.decode_jpeg_header(written)[3] == "420"
    by_opencv = cv2.imdecode(cv2.imencode(".jpg", expected.astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 90])[1],
                             cv2.IMREAD_COLOR)
    error_opencv = np.abs(by_opencv.astype(np.int16) - expected).mean()
    assert np.abs(cv2.imread(str(out / "IMG_0459.jpg")).astype(np.int16) - expected).mean() < 1.02 * error_opencv


def test_missing_exif_allowed_on_request(photo_dir, tmp_path):
    spec = CorrectionSpec(barrel=BARREL, require_exif=False)
    report = correct_photos([photo_dir / "no_exif.jpg"], tmp_path / "o", spec, workers=1, progress=False)
    assert len(report.written) == 1 and report.written[0].output_camera["fx_px"] is None


def test_calibration_spec_rescales_to_photo_size(tmp_path):
    cam = barrel_camera(BARREL, 600, 450, 460.0)
    from skyfix.mapping.lens import barrel_to_opencv

    fitted = barrel_to_opencv(BARREL, 600, 450, 460.0).camera
    save_camera(tmp_path / "cal.json", fitted)
    spec = CorrectionSpec(camera=load_camera(tmp_path / "cal.json"))
    tables = spec.undistortion(1200, 900)
    assert tables.output.fx == pytest.approx(2 * fitted.fx)
    with pytest.raises(DataError, match="aspect"):
        spec.undistortion(1200, 1000)
    assert cam.width == 600


def _cuda() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return torch.cuda.is_available()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not _cuda(), reason="no CUDA device on this machine"))])
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_torch_backend_matches_opencv(photo_dir, tmp_path, device, dtype):
    pytest.importorskip("kornia")
    from skyfix.mapping.remap_torch import TorchRemapper

    raw = cv2.imread(str(photo_dir / "IMG_0459.jpg"))
    tables = Undistortion.for_barrel(BARREL, 1200, 900)
    a = tables.apply(raw).astype(int)
    b = TorchRemapper(tables, device=device, dtype=dtype)(raw[None])[0].astype(int)
    # Float vs OpenCV's 1/32-px fixed-point tables: rounding-level differences only.
    assert np.mean(np.abs(a - b)) < 0.2 and np.max(np.abs(a - b)) <= 3
    if dtype == "float32":
        report = correct_photos(list_photos(photo_dir), tmp_path / "t", CorrectionSpec(barrel=BARREL),
                                backend="torch", device=device, batch_size=2, progress=False)
        assert len(report.written) == 2 and len(report.skipped) == 3
        # The overlapped pipeline (decode and encode on threads, remap on the device) writes what
        # the OpenCV backend writes: same pixels up to the remap's rounding, after the same JPEG
        # encoder at the same quality, and the same corrected camera in the EXIF.
        ref = correct_photos(list_photos(photo_dir), tmp_path / "o", CorrectionSpec(barrel=BARREL), workers=2,
                             progress=False)
        assert [r.output_camera for r in report.results] == [r.output_camera for r in ref.results]
        for r in report.written:
            name = Path(r.output).name
            t_img, o_img = (cv2.imread(str(tmp_path / d / name)).astype(int) for d in ("t", "o"))
            assert np.mean(np.abs(t_img - o_img)) < 0.2


def test_jpeg_quality_estimate_and_default_keeps_input_quality(tmp_path):
    from skyfix.mapping.exif import jpeg_quality

    img = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
    for q in (20, 75, 90, 98):
        assert jpeg_quality(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, q])[1].tobytes()) == q
    assert jpeg_quality(b"\xff\xd8") is None
    report = correct_photos([DATA / "IMG_0459.jpg"], tmp_path, CorrectionSpec(barrel=BARREL), workers=1,
                            progress=False)
    assert jpeg_quality((tmp_path / "IMG_0459.jpg").read_bytes()) == jpeg_quality((DATA / "IMG_0459.jpg").read_bytes())
    assert len(report.written) == 1
    with pytest.raises(InputError, match="jpeg_quality"):
        CorrectionSpec(barrel=BARREL, jpeg_quality=101)


@pytest.mark.parametrize("with_size_tags", [True, False])
def test_exif_transfer_in_place_and_by_redump_agree(with_size_tags):
    # The in-place patch (size tags present) and piexif's re-dump (PixelXDimension missing,
    # so it must be added) give the same tags: focal 4.3 mm x 1.25, the 35 mm equivalent
    # 24 mm x 1.25 x (old diagonal 1000 / new diagonal 500) = 60, the new size, no thumbnail.
    from skyfix.mapping.exif import transfer_metadata

    exif_ifd = {piexif.ExifIFD.FocalLength: (43, 10), piexif.ExifIFD.FocalLengthIn35mmFilm: 24}
    if with_size_tags:
        exif_ifd.update({piexif.ExifIFD.PixelXDimension: 800, piexif.ExifIFD.PixelYDimension: 600})
    zeroth = {piexif.ImageIFD.Make: b"Canon", piexif.ImageIFD.ImageWidth: 800, piexif.ImageIFD.ImageLength: 600}
    gps = {piexif.GPSIFD.GPSAltitude: (2821, 10)}
    import io

    buffer = io.BytesIO()
    piexif.insert(piexif.dump({"0th": zeroth, "Exif": exif_ifd, "GPS": gps}),
                  cv2.imencode(".jpg", np.zeros((600, 800), np.uint8))[1].tobytes(), buffer)
    raw = buffer.getvalue()
    out = transfer_metadata(raw, cv2.imencode(".jpg", np.zeros((300, 400), np.uint8))[1].tobytes(),
                            focal_scale=1.25, width=400, height=300)
    tags = piexif.load(out)
    num, den = tags["Exif"][piexif.ExifIFD.FocalLength]
    assert num / den == 4.3 * 1.25
    assert tags["Exif"][piexif.ExifIFD.FocalLengthIn35mmFilm] == 60
    assert (tags["Exif"][piexif.ExifIFD.PixelXDimension], tags["Exif"][piexif.ExifIFD.PixelYDimension]) == (400, 300)
    assert tags["GPS"] == gps and tags["0th"][piexif.ImageIFD.Make] == b"Canon" and not tags["1st"]
    assert cv2.imdecode(np.frombuffer(out, np.uint8), cv2.IMREAD_GRAYSCALE).shape == (300, 400)
