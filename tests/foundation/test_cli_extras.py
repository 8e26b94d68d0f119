"""The base install (no extras) is what a companion computer that flies needs, and a command
that needs a missing extra says which one (issue 20, item 11).

A base install is simulated in a subprocess by refusing to import the packages that only
the extras bring (pyproject.toml: ``mapping``, ``thermal``, ``gpu``, ``bench``) and pytest
(gtsam's wheel lists it as a requirement; it must not be needed at run time).
"""

from __future__ import annotations

import subprocess
import sys

from skyfix.cli import main

_BLOCK = '''
import importlib, importlib.abc, pkgutil, sys
BLOCK = {"pycolmap", "piexif", "simplekml", "simplejpeg", "rasterio", "torch", "kornia", "pupil_apriltags",
         "filterpy", "pytest", "_pytest"}
class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in BLOCK:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Blocker())
'''

_WALK = _BLOCK + '''
fails = []
for pkg in ["skyfix", "skyfix.crps", "skyfix.fusion", "skyfix.drivers", "skyfix.datasets", "skyfix.datasets.sim",
            "skyfix.tags", "skyfix.thermal", "skyfix.mapping"]:
    for info in pkgutil.iter_modules(importlib.import_module(pkg).__path__, pkg + "."):
        if not info.name.endswith("__main__"):
            try:
                importlib.import_module(info.name)
            except ModuleNotFoundError as exc:
                fails.append(f"{info.name}:{exc.name}")
print(" ".join(sorted(fails)))
'''


def _python(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)


def test_base_install_imports_the_flying_stack():
    out = _python(_WALK)
    assert out.returncode == 0, out.stderr
    # Every module of the flying stack (core, drivers, fusion, crps, simulator, tags, thermal)
    # imports without the extras; only photo-pipeline modules may need the mapping extra.
    fails = out.stdout.split()
    assert "skyfix.datasets.survey_scene:piexif" in fails
    assert all(f.startswith(("skyfix.mapping.", "skyfix.datasets.survey_scene:")) for f in fails), fails


def test_base_install_lists_every_command_and_names_the_extra():
    code = _BLOCK + "from skyfix.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    out = _python(code, "--help")
    assert out.returncode == 0, out.stderr
    for command in ("demo", "thermal", "tags", "serve", "sim", "vehicle", "fusion", "map", "plan", "lens"):
        assert f"    {command} " in out.stdout
    out = _python(code, "-q", "map", "photos/", "-o", "project/")
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and "pip install 'skyfix[mapping]'" in lines[0], out.stderr


def test_a_missing_extra_is_one_line_naming_it(tmp_path):
    assert main(["-q", "thermal", "simulate", str(tmp_path / "f"), "--fires", "1", "--frames", "2",
                 "--size", "160x128"]) == 0
    (tmp_path / "dem.tif").write_bytes(b"II*\x00")
    f = tmp_path / "f"
    code = _BLOCK + "from skyfix.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    out = _python(code, "-q", "thermal", "locate", str(f / "frames"), "--poses", str(f / "poses.csv"),
                  "--camera", str(f / "camera.json"), "--dem", str(tmp_path / "dem.tif"), "-o",
                  str(tmp_path / "o.geojson"))
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert "rasterio is not installed" in lines[0] and "pip install 'skyfix[thermal]'" in lines[0]
