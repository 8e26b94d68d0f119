"""Dependencies point one way: every import in the source tree is walked (the AST, so imports
inside functions count too) and checked against the layering of DESIGN.md.

core ``skyfix/`` <- perception (thermal, tags, mapping, crps's perception modules) <- fusion
<- crps's swarm system (node, messages, transport; also uses drivers); drivers use only the
core; datasets (the harness) may use everything below the applications; the applications
(crps's demo and service, the top) may use everything, the simulator included, and so may
each package's command-line front end (``cli.py``) use the harness.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"skyfix": "skyfix", "thermal": "thermal", "crps": "crps", "tags": "tags", "mapping": "mapping",
            "fusion": "fusion", "drivers": "drivers", "datasets": "datasets"}
PERCEPTION = {"thermal", "tags", "mapping", "crps.perception"}
#: layer -> the layers it may import (itself always allowed)
ALLOWED = {
    "skyfix": set(),
    "thermal": {"skyfix"}, "tags": {"skyfix"}, "mapping": {"skyfix"}, "crps.perception": {"skyfix"},
    "drivers": {"skyfix"},
    "fusion": {"skyfix", *PERCEPTION},
    "crps.system": {"skyfix", *PERCEPTION, "fusion", "drivers"},
    "datasets": set(PACKAGES) - {"crps"} | {"crps.perception", "crps.system"},
    "crps.app": set(PACKAGES) - {"crps"} | {"crps.perception", "crps.system"},
}
#: crps modules above fusion (the swarm system) and the applications on top; the rest is perception.
CRPS_SYSTEM = {"node", "transport", "messages", "swarm", "outputs", "camera_feed", "cli", "__init__",
               "help_protocol", "help_agent", "roles", "vantage", "help_loop", "rejoin"}
CRPS_APPS = {"demo", "service", "serve_cli", "sim_camera", "recovery", "recovery_faults", "recovery_report"}


def _layer_of_module(dotted: str) -> str | None:
    """Layer of an imported ``skyfix...`` module name (None: not skyfix)."""
    parts = dotted.split(".")
    if parts[0] != "skyfix":
        return None
    if len(parts) == 1 or parts[1] not in PACKAGES:
        return "skyfix"
    if parts[1] == "crps":
        if len(parts) == 2:
            return None  # the package's lazy exports; the imported name decides (perception exports only)
        return _crps_layer(parts[2])
    return parts[1]


def _crps_layer(module: str) -> str:
    if module in CRPS_APPS:
        return "crps.app"
    return "crps.system" if module in CRPS_SYSTEM else "crps.perception"


def _layer_of_file(path: Path) -> str:
    folder = path.relative_to(ROOT).parts[0]
    if folder == "crps":
        return _crps_layer(path.stem)
    return folder


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
            # "from skyfix import fusion" imports the subpackage named on the right
            if node.module in ("skyfix", "skyfix.crps"):
                found += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return found


def _source_files() -> list[Path]:
    return sorted(p for folder in PACKAGES for p in (ROOT / folder).rglob("*.py"))


def test_the_walk_sees_the_tree():
    files = _source_files()
    assert len(files) > 50
    assert any(p.parts[-2:] == ("crps", "node.py") for p in files)


@pytest.mark.parametrize("path", _source_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_upward_import(path: Path):
    layer = _layer_of_file(path)
    allowed = ALLOWED[layer] | {layer}
    if path.stem == "cli":  # a package's command-line front end may drive the simulator/renderers
        allowed |= {"datasets"}
    bad = [f"line {line}: {name} ({_layer_of_module(name)})" for line, name in _imports(path)
           if _layer_of_module(name) is not None and _layer_of_module(name) not in allowed]
    assert not bad, f"{path.relative_to(ROOT)} ({layer}) imports upward: {bad}"


def test_the_walk_catches_an_upward_import(tmp_path):
    """The checker itself fails on a core module importing fusion inside a function."""
    src = tmp_path / "mod.py"
    src.write_text("def f():\n    from skyfix.fusion.engine import FusionEngine\n    return FusionEngine\n")
    names = [name for _, name in _imports(src)]
    assert names == ["skyfix.fusion.engine"] and _layer_of_module(names[0]) not in ALLOWED["skyfix"]
    assert _layer_of_module("skyfix.crps.node") == "crps.system"
    assert _layer_of_module("skyfix.crps.fit") == "crps.perception"
    assert "crps.app" not in ALLOWED["datasets"] and "datasets" not in ALLOWED["crps.system"]
