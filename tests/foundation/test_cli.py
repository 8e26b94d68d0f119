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


def test_log_flags_work_after_the_subcommand(capsys):
    argv = ["tags", "dimension", "--area-m", "5", "4", "--min-height-m", "1", "--max-height-m", "3"]
    assert main([*argv, "-q"]) == 0
    assert main([*argv, "-v"]) == 0
    assert '"tile_m"' in capsys.readouterr().out


def test_help_states_each_default_once_and_no_escaped_percent():
    from skyfix.cli import iter_parsers

    for path, sub in iter_parsers(build_parser()):
        text = sub.format_help()
        assert "%%" not in text, f"'{path} --help' shows a literal %%"
        for block in re.split(r"\n  (?=-)", text):  # one option's help per block
            flat = " ".join(block.split()).lower()
            # The doubling users saw: "(default 50) (default: 50)", "(default: None)".
            assert not re.search(r"default[^()]*\)\s*\(default:", flat) and "(default: none)" not in flat, \
                f"'{path} --help' repeats a default: {flat[:160]}"


def test_top_level_help_lists_every_command_and_tags_board(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    top = capsys.readouterr().out
    for action in build_parser()._subparsers._group_actions[0].choices:
        assert f"    {action}" in top
    with pytest.raises(SystemExit):
        main(["tags", "--help"])
    assert "board" in capsys.readouterr().out


def test_errors_are_one_line_exit_2_and_operational_failures_exit_1(tmp_path, capsys):
    from skyfix.cli import run_command
    from skyfix.errors import DataError, SkyfixTimeout

    def bad(_):
        raise DataError("photo.jpg: photo.jpg: corrupt JPEG")

    def late(_):
        raise SkyfixTimeout("no heartbeat from udpin:127.0.0.1:14550 in 5 s")

    def missing(_):
        open(tmp_path / "nope.csv")

    def bug(_):
        raise KeyError("x")

    from skyfix.cli import configure_logging

    assert main(["-q", "tags", "board", "-o", str(tmp_path / "b" / "b.json"), "--rows", "1", "--cols", "1"]) == 0
    capsys.readouterr()
    restore = configure_logging(0, True)
    try:
        for func, code, text in ((bad, 2, "photo.jpg: corrupt JPEG"), (late, 1, "no heartbeat"),
                                 (missing, 2, "nope.csv: No such file"), (bug, 1, "internal error: KeyError")):
            assert run_command(func, None) == code
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and text in err[0] and "Traceback" not in err[0], err
    finally:
        restore()
    import logging

    assert not [h for h in logging.getLogger().handlers if type(h).__name__ == "LogHandler"]  # main leaves none
