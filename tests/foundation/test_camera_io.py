"""Camera JSON (skyfix.camera_io): the written form round-trips exactly, older forms read."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.camera_io import camera_from_dict, camera_to_dict, load_camera, save_camera
from skyfix.distortion import Barrel, BrownConrady, Fisheye
from skyfix.errors import DataError, InputError

# Values with long binary expansions, so a lossy float format would show.
LENSES = {
    "pinhole": None,
    "brown_conrady": BrownConrady(k1=-0.123456789012345, k2=0.0314159265358979, p1=1.1e-4, p2=-2.7e-5,
                                  k3=-0.00271828182845904),
    "fisheye": Fisheye(k1=0.0123456789, k2=-0.00987654321, k3=1.0 / 3.0e3, k4=-2.0 / 7.0e4),
    "barrel": Barrel(0.1 / 3.0, -0.32, 0.0),
}


def _camera(distortion=None) -> Camera:
    return Camera(4000, 3000, 2900.123456789, 2901.987654321, 1999.5 + 1.0 / 3.0, 1499.5 - 2.0 / 7.0, distortion)


def _write(tmp_path, data, name="cam.json"):
    path = tmp_path / name
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("model", sorted(LENSES))
def test_round_trip_is_exact_for_every_lens_model(tmp_path, model):
    cam = _camera(LENSES[model])
    save_camera(tmp_path / "cal.json", cam, rms_px=0.4321)
    raw = json.loads((tmp_path / "cal.json").read_text())
    assert raw["model"] == model and raw["rms_px"] == 0.4321
    assert set(raw) == {"width", "height", "fx_px", "fy_px", "cx_px", "cy_px", "model", "coefficients", "rms_px"}
    back = load_camera(tmp_path / "cal.json")
    assert back == cam  # dataclass equality: every float bit for bit, same distortion class and coefficients
    assert type(back.distortion) is type(cam.distortion)
    # The same through the dict functions (no file).
    assert camera_from_dict(camera_to_dict(cam)) == cam


def test_written_form_names_units():
    d = camera_to_dict(Camera(640, 512, 500.0, 501.0, 319.5, 255.5, BrownConrady(k1=-0.2)))
    assert d == {"width": 640, "height": 512, "fx_px": 500.0, "fy_px": 501.0, "cx_px": 319.5, "cy_px": 255.5,
                 "model": "brown_conrady",
                 "coefficients": {"k1": -0.2, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0}}


def test_legacy_fx_keys_read(tmp_path):
    # What skyfix thermal simulate and the tags/crps CLIs used to take.
    path = _write(tmp_path, {"width": 640, "height": 512, "fx": 686.2, "fy": 687.0, "cx": 319.5, "cy": 255.5})
    assert load_camera(path) == Camera(640, 512, 686.2, 687.0, 319.5, 255.5)


def test_legacy_fx_keys_take_the_image_size_when_the_file_has_none(tmp_path):
    path = _write(tmp_path, {"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0})
    assert load_camera(path, image_size=(640, 480)) == Camera(640, 480, 600.0, 600.0, 320.0, 240.0)
    with pytest.raises(DataError, match=r"cam\.json.*lacks width and height"):
        load_camera(path)


def test_hfov_form(tmp_path):
    # 90 deg across 640 px: f = 320 / tan(45 deg) = 320 px; centre (319.5, 255.5); square pixels.
    cam = load_camera(_write(tmp_path, {"width": 640, "height": 512, "hfov_deg": 90.0}))
    assert cam.fx == pytest.approx(320.0, rel=1e-15) and cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (319.5, 255.5)
    both = load_camera(_write(tmp_path, {"width": 640, "height": 512, "hfov_deg": 90.0, "vfov_deg": 60.0}))
    assert both.fy == pytest.approx(256.0 / math.tan(math.radians(30.0)), rel=1e-15)
    assert both.vfov_deg == pytest.approx(60.0, abs=1e-12)


def test_hfov_form_with_a_lens_model(tmp_path):
    cam = load_camera(_write(tmp_path, {"width": 640, "height": 480, "hfov_deg": 60.0, "model": "fisheye",
                                        "coefficients": {"k1": 0.01}}))
    assert cam.distortion == Fisheye(k1=0.01)


def test_rescaled_to_the_image_size(tmp_path):
    cam = Camera(4000, 3000, 2900.0, 2910.0, 2010.0, 1490.0, BrownConrady(k1=-0.1))
    save_camera(tmp_path / "cal.json", cam)
    small = load_camera(tmp_path / "cal.json", image_size=(1000, 750))
    assert (small.width, small.height) == (1000, 750)
    # Pixel edges stay aligned: (c + 0.5) scales by 1/4.
    assert small.fx == 725.0 and small.fy == 727.5
    assert small.cx == pytest.approx((2010.0 + 0.5) / 4 - 0.5, abs=1e-12)
    assert small.cy == pytest.approx((1490.0 + 0.5) / 4 - 0.5, abs=1e-12)
    # The same ray through the same physical point of the sensor on both images.
    uv_big = np.array([[100.0, 2900.0], [3999.0, 0.0], [2010.0, 1490.0]])
    np.testing.assert_allclose(small.pixel_to_ray((uv_big + 0.5) / 4 - 0.5), cam.pixel_to_ray(uv_big), atol=1e-12)
    # A size the file already has comes back untouched.
    assert load_camera(tmp_path / "cal.json", image_size=(4000, 3000)) == cam


def test_aspect_ratio_mismatch_names_the_file_and_both_sizes(tmp_path):
    save_camera(tmp_path / "cal.json", Camera(640, 512, 600.0, 600.0, 319.5, 255.5))
    with pytest.raises(DataError, match=r"cal\.json.*640x512.*640x480"):
        load_camera(tmp_path / "cal.json", image_size=(640, 480))


def test_missing_keys_name_the_file_and_what_is_expected(tmp_path):
    path = _write(tmp_path, {"width": 640, "height": 512, "fx_px": 600.0, "fy_px": 600.0, "cx_px": 319.5},
                  name="half.json")
    with pytest.raises(DataError, match=r"half\.json.*lacks \['cy_px'\]"):
        load_camera(path)
    path = _write(tmp_path, {"width": 640, "height": 512}, name="empty.json")
    with pytest.raises(DataError, match=r"empty\.json.*fx_px, fy_px, cx_px, cy_px.*hfov_deg.*found none"):
        load_camera(path)
    with pytest.raises(DataError, match=r"one\.json.*gives width but not height"):
        load_camera(_write(tmp_path, {"width": 640, "hfov_deg": 50.0}, name="one.json"))


def test_unknown_model_names_the_file_and_the_models(tmp_path):
    data = camera_to_dict(_camera()) | {"model": "kannala"}
    with pytest.raises(DataError, match=r"odd\.json.*unknown lens model 'kannala'.*brown_conrady"):
        load_camera(_write(tmp_path, data, name="odd.json"))


def test_malformed_content_is_a_data_error_naming_the_file(tmp_path):
    base = camera_to_dict(_camera())
    cases = {
        "two_forms.json": base | {"fx": 1.0},
        "zero_f.json": base | {"fx_px": 0.0},
        "text_f.json": base | {"fy_px": "600"},
        "frac_w.json": base | {"width": 640.5},
        "bad_coef.json": base | {"model": "brown_conrady", "coefficients": {"k9": 1.0}},
        "barrel_abc.json": base | {"model": "barrel", "coefficients": {"a": 0.1}},
        "pinhole_coef.json": base | {"coefficients": {"k1": -0.2}},
        "list.json": [1, 2, 3],
        "fov.json": {"width": 640, "height": 480, "hfov_deg": 180.0},
    }
    for name, data in cases.items():
        with pytest.raises(DataError, match=name.replace(".", r"\.")):
            load_camera(_write(tmp_path, data, name=name))


def test_missing_file_is_an_input_error_and_bad_json_a_data_error(tmp_path):
    with pytest.raises(InputError, match="nope.json"):
        load_camera(tmp_path / "nope.json")
    (tmp_path / "bad.json").write_text("{width: 1")
    with pytest.raises(DataError, match=r"bad\.json"):
        load_camera(tmp_path / "bad.json")


def test_writer_refuses_extras_that_clash_or_are_not_json(tmp_path):
    with pytest.raises(InputError, match="fx_px"):
        camera_to_dict(_camera(), fx_px=1.0)
    with pytest.raises(InputError, match="extra"):
        save_camera(tmp_path / "c.json", _camera(), rms_px=float("nan"))
    with pytest.raises(InputError, match="image_size"):
        camera_from_dict(camera_to_dict(_camera()), image_size=(640,))
