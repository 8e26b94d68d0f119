"""Code shape: no module over 500 lines and no function over 80, outside benchmarks/ and tests/.

Small modules with one job and short functions are the house style (../shared/STYLE.md);
this walks every ``.py`` file of the working tree with :mod:`ast` so a new offender fails
here, not in review. ``ALLOWED`` is the visible debt: each entry says why it is still
long. A split entry should be deleted (a stale one is reported as a warning, not a
failure, so the engineer splitting it is not blocked by this file).
"""

from __future__ import annotations

import ast
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80
_SKIP_DIRS = {"benchmarks", "tests", "build", "dist", "__pycache__", "node_modules", "venv"}

# "path" (module lines) or "path::Qual.name" (function lines) -> why it may stay long.
ALLOWED: dict[str, str] = {}


def source_files(root: Path = ROOT) -> list[Path]:
    """Every ``.py`` file under ``root`` outside benchmarks/, tests/, hidden and build folders."""
    out = []
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).parts[:-1]
        if any(p in _SKIP_DIRS or p.startswith(".") or p.endswith(".egg-info") for p in parts):
            continue
        out.append(path)
    return out


def _functions(tree: ast.AST, prefix: str = ""):
    """(qualified name, line count) of every function and method, nested ones included."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            name = f"{prefix}.{node.name}" if prefix else node.name
            if not isinstance(node, ast.ClassDef):
                yield name, node.end_lineno - node.lineno + 1
            yield from _functions(node, name)
        else:
            yield from _functions(node, prefix)


def offenders(source: str, rel_path: str) -> dict[str, int]:
    """{entry: lines} for a module over ``MAX_MODULE_LINES`` or a function over ``MAX_FUNCTION_LINES``."""
    found = {}
    n_lines = len(source.splitlines())
    if n_lines > MAX_MODULE_LINES:
        found[rel_path] = n_lines
    for name, n in _functions(ast.parse(source, rel_path)):
        if n > MAX_FUNCTION_LINES:
            found[f"{rel_path}::{name}"] = n
    return found


def test_offenders_finds_long_modules_and_nested_functions():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    src = f"class A:\n    def short(self):\n        pass\n\n    def long(self):\n    {body.replace(chr(10), chr(10) + '    ')}\n"
    src += "\n" * (MAX_MODULE_LINES - len(src.splitlines()) + 1)
    assert offenders(src, "m.py") == {"m.py": MAX_MODULE_LINES + 1, "m.py::A.long": MAX_FUNCTION_LINES + 1}
    assert offenders("def f():\n    def g():\n        pass\n", "m.py") == {}


def test_no_long_modules_or_functions():
    files = source_files()
    assert len(files) > 100, f"expected the whole tree, found {len(files)} files under {ROOT}"
    found = {}
    for path in files:
        found.update(offenders(path.read_text(encoding="utf-8"), path.relative_to(ROOT).as_posix()))
    new = {k: v for k, v in found.items() if k not in ALLOWED}
    stale = sorted(set(ALLOWED) - set(found))
    if stale:
        warnings.warn(f"code shape: no longer too long, delete from ALLOWED: {stale}", stacklevel=1)
    assert not new, ("too long (split by responsibility, or add to ALLOWED with the reason): "
                     + ", ".join(f"{k} ({v} lines)" for k, v in sorted(new.items())))


def test_allow_list_says_why():
    for entry, why in ALLOWED.items():  # empty since issue 22: a new entry must say why
        assert why.strip() and not entry.startswith("fusion/"), entry  # fusion was split: keep it so
