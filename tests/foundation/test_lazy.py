"""Lazy package exports load on first use and fail clearly for unknown names."""

import subprocess
import sys

import pytest

import skyfix.fusion


def test_lazy_exports_resolve_and_cache():
    engine_cls = skyfix.fusion.FusionEngine
    from skyfix.fusion.engine import FusionEngine

    assert engine_cls is FusionEngine
    assert "FusionEngine" in vars(skyfix.fusion)  # cached on the module after the first look-up
    assert "FusionEngine" in dir(skyfix.fusion) and "FusionEngine" in skyfix.fusion.__all__
    with pytest.raises(AttributeError, match="skyfix.fusion' has no attribute 'Nope'"):
        skyfix.fusion.Nope  # noqa: B018


def test_importing_the_packages_loads_no_heavy_library():
    code = ("import sys, skyfix.fusion, skyfix.drivers, skyfix.mapping, skyfix.crps, skyfix.thermal, "
            "skyfix.tags, skyfix.datasets; "
            "print(sorted(m for m in ('gtsam', 'cv2', 'pymavlink', 'pycolmap', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_building_the_whole_command_line_loads_no_heavy_library():
    # every test and user command starts here: a heavy import would cost each of them ~1.5 s
    code = ("import sys; from skyfix.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('gtsam', 'cv2', 'pymavlink', 'pycolmap', 'scipy', 'torch', 'pyproj') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("package, name", [
    ("skyfix.thermal", "geolocate"), ("skyfix.fusion", "replay"), ("skyfix.mapping", "calibrate")])
def test_an_export_named_like_its_module_stays_the_export(package, name):
    # importing the submodule first binds it to the package attribute of the same name; the
    # export must still be the function (14 thermal tests failed on import order alone)
    code = (f"import importlib, types; importlib.import_module('{package}.{name}'); "
            f"from {package} import {name} as x; print(isinstance(x, types.FunctionType))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "True"
