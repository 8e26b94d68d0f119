"""The foundation's public API carries runnable ``Example:`` sections, and pytest runs them.

A new public function or class in these modules without an example fails here; the
examples themselves run as doctests because pyproject's testpaths hold skyfix/ and its
addopts ``--doctest-modules`` (checked below, so dropping either fails too).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULES = ("geo", "camera", "distortion", "rotation", "types", "validate", "camera_io", "geoid")
# typing.Protocol classes describe what a caller passes in; they have nothing to run.
PROTOCOLS = {"distortion.py": {"Intrinsics", "Distortion"}}


def _public_without_example(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    return [node.name for node in tree.body
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not node.name.startswith("_")
            and node.name not in PROTOCOLS.get(path.name, set())
            and "Example:" not in (ast.get_docstring(node) or "")]


@pytest.mark.parametrize("module", MODULES)
def test_every_public_name_has_an_example(module):
    assert _public_without_example(ROOT / "skyfix" / f"{module}.py") == []


def test_the_check_sees_a_missing_example(tmp_path):
    src = tmp_path / "m.py"
    src.write_text('def f():\n    """Doc.\n\n    Example:\n        >>> 1\n        1\n    """\n\n\n'
                   'def g():\n    """No example."""\n\n\nclass _Private:\n    pass\n')
    assert _public_without_example(src) == ["g"]


def test_pytest_runs_the_foundation_doctests(pytestconfig):
    assert "skyfix" in pytestconfig.getini("testpaths")
    assert "--doctest-modules" in pytestconfig.getini("addopts")
