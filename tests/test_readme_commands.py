"""The README's and every module README's commands run as written (issue 20).

- Fenced ``sh``/``bash`` blocks are run by bash in a fresh folder per README, in the order
  they appear, together with the README's Python blocks whose first line is
  ``# runs as is`` (so a block can use the files an earlier one wrote). Every command must
  succeed. The install step of the top README (``pip install -e . && ...``) is not re-run:
  the package under test is installed; its test command is CI's (checked verbatim by
  tests/foundation/test_cli.py), so it is not run from inside the test suite.
- Every other ``skyfix ...`` command the READMEs show (untagged blocks, tables) must at
  least parse: the subcommand and every flag exist. Synopses with ``[...]``, ``|`` or
  ``…`` are skipped.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from skyfix.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
READMES = [ROOT / "README.md", *sorted(ROOT.glob("*/README.md")), *sorted((ROOT / "docs").glob("*.md"))]
_FENCE = re.compile(r"```([a-z]*)\n(.*?)```", re.S)
#: READMEs whose runnable blocks take long; still run in CI.
SLOW = {"README.md", "fusion/README.md", "thermal/README.md"}


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _lines(block: str) -> list[str]:
    """Shell lines of a block with backslash continuations joined and comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", block)
    out = []
    for line in joined.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            out.append(line)
    return out


def _runnable(readme: Path) -> list[tuple[str, str]]:
    """(kind, text) of the blocks to run, in order: kind 'sh' or 'python'."""
    out = []
    for lang, body in _FENCE.findall(readme.read_text()):
        if lang in ("sh", "bash", "shell"):
            out.append(("sh", body))
        elif lang == "python" and body.startswith("# runs as is"):
            out.append(("python", body))
    return out


def _as_run_here(line: str) -> str | None:
    """The line to run, or None for one CI runs instead (the README's install + test)."""
    if "python -m pytest" in line:
        return None
    return re.sub(r"^pip install -e \S+\s*&&\s*", "", line)


RUNNABLE = [r for r in READMES if _runnable(r)]


@pytest.mark.parametrize("readme", [
    pytest.param(r, id=_rel(r), marks=[pytest.mark.slow] if _rel(r) in SLOW else [])
    for r in RUNNABLE])
def test_readme_blocks_run_as_written(readme: Path, tmp_path: Path):
    for k, (kind, body) in enumerate(_runnable(readme)):
        if kind == "python":
            script = tmp_path / f"block{k}.py"
            script.write_text(body)
            cmd = [sys.executable, str(script)]
        else:
            lines = [x for x in (_as_run_here(ln) for ln in _lines(body)) if x]
            if not lines:
                continue
            cmd = ["bash", "-euo", "pipefail", "-c", "\n".join(lines)]
        out = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, (f"{_rel(readme)} block {k} failed (exit {out.returncode}):\n{body}\n"
                                     f"stderr: {out.stderr[-2000:]}")


def _shown_commands() -> list[tuple[str, str]]:
    """(README, command) for every ``skyfix ...`` command shown outside runnable blocks."""
    out = []
    for readme in READMES:
        text = readme.read_text()
        for lang, body in _FENCE.findall(text):
            if lang in ("sh", "bash", "shell", "python"):
                continue
            out += [(_rel(readme), ln) for ln in _lines(body) if ln.startswith("skyfix ")]
        no_fences = _FENCE.sub("", text)
        out += [(_rel(readme), c) for c in re.findall(r"`(skyfix [a-z][^`]*)`", no_fences)]
    return [(r, re.sub(r"\s+#.*$", "", c)) for r, c in out if not re.search(r"[\[\]|…]|\.\.\.", c)]


SHOWN = _shown_commands()


def test_readmes_show_commands():
    assert len(SHOWN) > 20 and len(RUNNABLE) >= 3


@pytest.mark.parametrize("readme, command", SHOWN, ids=[f"{r}: {c[:60]}" for r, c in SHOWN])
def test_shown_commands_parse(readme: str, command: str, capsys):
    parser = build_parser()
    argv = shlex.split(command)[1:]
    if _is_command_name(parser, argv):
        return  # a mention of the command itself ("`skyfix serve` runs one Node per drone")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        if exc.code == 0:  # --help, --version
            return
        pytest.fail(f"{readme}: '{command}' does not parse (exit {exc.code}): {capsys.readouterr().err.strip()}")
    assert getattr(args, "func", None) is not None, f"{readme}: '{command}' runs nothing"


def _is_command_name(parser, argv: list[str]) -> bool:
    """Whether ``argv`` is only a path of existing subcommand names."""
    import argparse

    for word in argv:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or word not in subs[0].choices:
            return False
        parser = subs[0].choices[word]
    return True
