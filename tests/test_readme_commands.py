"""The README's and every module README's commands run as written (issue 20).

- Fenced ``sh``/``bash`` blocks are run by bash in a fresh folder per README (tests/readme_blocks.py,
  once per session: tests/crps/test_recovery_demo.py checks the top README's demo run), in the order
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
from pathlib import Path

import pytest
from readme_blocks import FENCE as _FENCE
from readme_blocks import ROOT, runnable
from readme_blocks import rel as _rel
from readme_blocks import shell_lines as _lines

from skyfix.cli import build_parser

READMES = [ROOT / "README.md", *sorted(ROOT.glob("*/README.md")), *sorted((ROOT / "docs").glob("*.md"))]
#: READMEs whose runnable blocks take long; still run in CI.
SLOW = {"README.md", "fusion/README.md", "thermal/README.md"}


RUNNABLE = [r for r in READMES if runnable(r)]


@pytest.mark.parametrize("readme", [
    pytest.param(r, id=_rel(r), marks=[pytest.mark.slow] if _rel(r) in SLOW else [])
    for r in RUNNABLE])
def test_readme_blocks_run_as_written(readme: Path, readme_runs):
    """Every block succeeds (run once per session by the ``readme_runs`` fixture, which other
    tests read too; see tests/readme_blocks.py for what is run and how)."""
    runs = readme_runs(readme)
    assert runs, f"{_rel(readme)}: no block ran"
    for run in runs:
        assert run.returncode == 0, (f"{_rel(readme)} block {run.index} failed (exit {run.returncode}):\n"
                                     f"{run.body}\nstderr: {run.stderr[-2000:]}")


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
