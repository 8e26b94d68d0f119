"""The skyfix command line and the CI/README contract."""

import re
import subprocess
import sys
from pathlib import Path

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


def test_every_subcommand_has_complete_help():
    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert subparsers.choices, "no subcommand registered"
    for name, sub in subparsers.choices.items():
        text = sub.format_help()
        assert sub.description or any(h.help for h in subparsers._choices_actions if h.dest == name), name
        for action in sub._actions:
            if action.dest != "help" and not action.option_strings == []:
                assert action.help, f"skyfix {name}: option {action.option_strings} has no help"
        assert text


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
