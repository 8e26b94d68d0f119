"""The skyfix command line and the CI/README contract."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

import skyfix
from skyfix.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[2]


def _run(*args):
    return subprocess.run([sys.executable, "-m", "skyfix", *args], capture_output=True, text=True,
                          timeout=120)


def test_version_and_help():
    out = _run("--version")
    assert out.returncode == 0 and skyfix.__version__ in out.stdout
    out = _run("--help")
    assert out.returncode == 0
    assert "demo" in out.stdout and "--verbose" in out.stdout


def _subcommands(parser, prefix="skyfix"):
    """Yield (command path, parser) for every subcommand at any depth."""
    for action in parser._actions:
        if action.__class__.__name__ == "_SubParsersAction":
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield f"{prefix} {name}", sub, helps.get(name)
                yield from _subcommands(sub, f"{prefix} {name}")


def test_every_subcommand_has_complete_help():
    commands = list(_subcommands(build_parser()))
    assert len(commands) >= 2, "no subcommand registered"
    for path, sub, summary in commands:
        assert summary, f"'{path}' has no one-line help in its parent's listing"
        assert sub.format_help()
        for action in sub._actions:
            if action.__class__.__name__ == "_SubParsersAction" or action.dest == "help":
                continue
            if not action.help:
                pytest.fail(f"'{path}': argument {action.option_strings or action.dest} has no help")


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "usage: skyfix" in capsys.readouterr().out


def test_ci_runs_the_readme_test_command_verbatim():
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)\n```", readme, re.S)
    assert len(blocks) >= 2
    install_and_demo, install_and_test = blocks[0].strip(), blocks[1].strip()
    assert "skyfix demo" in install_and_demo
    assert "pytest" in install_and_test
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert install_and_test in [line.strip() for line in ci]
