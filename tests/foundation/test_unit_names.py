"""Every public name of the foundation (skyfix/*.py) carries its unit, or its type says it.

Walks the AST of each module: public dataclass/class fields, parameters of public
functions and methods, and public properties. A name whose annotation is a float or an
array (or that has no annotation) must end in a unit suffix (``_m``, ``_deg``, ``_s``,
``_mps``, ``_px``, ...), or be annotated with one of :mod:`skyfix.units`' aliases
(``Pixels``, ``PixelArray``, ...), or be listed in ``DIMENSIONLESS`` with the reason it
has no unit. Integers, strings and other types are not checked.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from skyfix import units

FOUNDATION = Path(units.__file__).resolve().parent
UNIT_SUFFIX = re.compile(
    r"_(m|m2|km|deg|rad|s|ms|us|mps|px|hz|c|enu|ned|ecef)$")
"""Units, and for vectors the frame whose axes they are in (``_enu`` vectors are in metres
unless a unit precedes the frame: ``offset_enu_m``; ``bearing_unit_enu`` is a unit vector)."""
NUMERIC = re.compile(r"\b(float|ndarray|ArrayLike)\b")

_COEFF = "lens distortion coefficient: dimensionless by definition (OpenCV / Brown-Conrady)"
_ROT = "rotation matrix: dimensionless"
DIMENSIONLESS: dict[str, str] = {
    "camera.py::Camera.K": "the intrinsic matrix K, standard name; px entries and a 1 (docstring)",
    "camera.py::Camera.scaled.factor": "image resize ratio",
    "camera.py::Camera.project.xyz": "scale-free: any length unit, the projection divides it out",
    **{f"distortion.py::BrownConrady.{k}": _COEFF for k in ("k1", "k2", "p1", "p2", "k3")},
    **{f"distortion.py::Fisheye.{k}": _COEFF for k in ("k1", "k2", "k3", "k4")},
    **{f"distortion.py::Barrel.{k}": _COEFF for k in ("a", "b", "c", "d")},
    "distortion.py::BrownConrady.opencv_coefficients": _COEFF,
    "distortion.py::Fisheye.opencv_coefficients": _COEFF,
    "distortion.py::Barrel.radial_factor.r": "radius normalised by the half image size",
    "rotation.py::euler_zyx_from_r_ned_from_frd.r": _ROT,
    **{f"mission.py::MissionItem.param{i}": "MAVLink's param1..4 as on the wire: the unit is the MAV_CMD's "
       "(waypoint: hold s, radius m; change speed: m/s)" for i in range(1, 5)},
}


def _unit_aliases() -> set[str]:
    return set(units.UNIT_ALIASES)


def _needs_unit(annotation: ast.expr | None) -> bool:
    """True for float/array annotations (and missing ones) that name no unit alias."""
    if annotation is None:
        return True
    text = ast.unparse(annotation)
    if any(re.search(rf"\b{alias}\b", text) for alias in _unit_aliases()):
        return False
    return bool(NUMERIC.search(text))


def _is_property(fn: ast.FunctionDef) -> bool:
    return any(isinstance(d, ast.Name) and d.id == "property" for d in fn.decorator_list)


def _function_names(fn: ast.FunctionDef, qual: str) -> list[tuple[str, int, ast.expr | None]]:
    if _is_property(fn):
        return [(qual, fn.lineno, fn.returns)]
    args = fn.args.posonlyargs + fn.args.args + fn.args.kwonlyargs
    return [(f"{qual}.{a.arg}", a.lineno, a.annotation) for a in args if a.arg not in ("self", "cls")]


def public_names(tree: ast.Module) -> list[tuple[str, int, ast.expr | None]]:
    """(qualified name, line, annotation) of each public field, parameter and property."""
    out = []
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and not node.name.startswith("_"):
            out += _function_names(node, node.name)
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for st in node.body:
                if isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name):
                    if not st.target.id.startswith("_"):
                        out.append((f"{node.name}.{st.target.id}", st.lineno, st.annotation))
                elif isinstance(st, ast.FunctionDef) and not st.name.startswith("_"):
                    out += _function_names(st, f"{node.name}.{st.name}")
    return out


def offenders(path: Path) -> list[str]:
    """Public float/array names of one module with neither a unit suffix nor a unit type."""
    bad = []
    for qual, line, annotation in public_names(ast.parse(path.read_text(), str(path))):
        key = f"{path.name}::{qual}"
        if key in DIMENSIONLESS or UNIT_SUFFIX.search(qual) or not _needs_unit(annotation):
            continue
        bad.append(f"{key} (line {line})")
    return bad


@pytest.mark.parametrize("path", sorted(FOUNDATION.glob("*.py")), ids=lambda p: p.name)
def test_public_numbers_of_the_foundation_say_their_unit(path):
    assert offenders(path) == [], "add a unit suffix, a skyfix.units type, or a DIMENSIONLESS entry with its reason"


def test_the_walk_finds_an_offender(tmp_path):
    """The check can fail: a new unit-less float field and parameter are reported."""
    module = tmp_path / "probe.py"
    module.write_text("class Probe:\n    speed: float\n    range_m: float\n    fx: 'Pixels'\n"
                      "def f(gain: float, n: int, width_px: float, uv: 'PixelArray'): ...\n")
    assert offenders(module) == ["probe.py::Probe.speed (line 2)", "probe.py::f.gain (line 5)"]


def test_allow_list_is_not_stale():
    names = {f"{p.name}::{q}" for p in FOUNDATION.glob("*.py") for q, _, _ in public_names(ast.parse(p.read_text()))}
    assert sorted(set(DIMENSIONLESS) - names) == []
