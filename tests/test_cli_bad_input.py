"""Every CLI command, fed the bad input a new user gives it, answers with one line naming
the input, exit code 2, and no traceback (issue 20).

The commands are enumerated from the parser: a command that is in neither the cases below
nor ``NO_FILE_INPUT`` fails :func:`test_every_command_is_walked`, so a new command cannot
escape. Wrong types are generated for every numeric option of every command. Cases that
still fail in an area owned by someone else are ``xfail(strict=True)`` with the owner
named, so they turn into failures the day they are fixed and the mark must go.

Commands run in-process (fast); the ones that could run for long when they wrongly
accept their input run in a subprocess with a time limit.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from skyfix.cli import build_parser, iter_parsers, main

PARSER = build_parser()
_NUMERIC = (int, float)


def _leaves() -> dict[str, argparse.ArgumentParser]:
    """Command path (without 'skyfix ') -> parser, for every command that does work."""
    out = {}
    for path, p in iter_parsers(PARSER):
        if not any(isinstance(a, argparse._SubParsersAction) for a in p._actions) and path != "skyfix":
            out[path.removeprefix("skyfix ")] = p
    return out


LEAVES = _leaves()

#: Commands without a file or folder input; their bad numbers are covered by the generic
#: wrong-type case and the out-of-range cases below.
NO_FILE_INPUT = {
    "vehicle status", "vehicle arm", "vehicle disarm", "vehicle takeoff", "vehicle goto", "vehicle rtl",
    "vehicle land", "vehicle param get", "vehicle param set", "sim", "plan corners", "plan polygon",
    "tags dimension", "demo",
}


def _one_line_error(rc: int, err: str, *names: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert "Traceback" not in err, err
    assert rc == 2, f"exit {rc}, stderr: {err!r}"
    assert len(lines) == 1, f"{len(lines)} lines on stderr: {err!r}"
    assert any(n in lines[0] for n in names), f"error does not name {names}: {lines[0]!r}"


def _run_main(argv: list[str], capsys) -> tuple[int, str]:
    capsys.readouterr()
    try:
        rc = main(["-q", *argv])
    except SystemExit as exc:  # argparse
        rc = exc.code
    return rc, capsys.readouterr().err


def _run_sub(argv: list[str], timeout_s: float = 30.0) -> tuple[int, str]:
    try:
        out = subprocess.run([sys.executable, "-m", "skyfix", "-q", *argv], capture_output=True, text=True,
                             timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return -1, f"still running after {timeout_s} s: the input was accepted"
    return out.returncode, out.stderr


# --- inputs -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bad")
    (d / "empty").mkdir()
    (d / "text").mkdir()
    (d / "text" / "notes.txt").write_text("not a photo")
    (d / "fake.jpg").write_text("not a jpeg at all")
    (d / "fake.png").write_text("not a png")
    ok, jpg = cv2.imencode(".jpg", (np.random.default_rng(0).random((120, 160, 3)) * 255).astype(np.uint8))
    (d / "truncated.jpg").write_bytes(jpg.tobytes()[: len(jpg) // 2])
    cv2.imwrite(str(d / "ok.png"), np.full((64, 64), 180, np.uint8))
    (d / "afile").write_text("a file where a folder is needed")
    (d / "bad.json").write_text("{not json")
    (d / "empty.csv").write_text("")
    return {k: d / k for k in ("empty", "text", "fake.jpg", "fake.png", "truncated.jpg", "afile", "bad.json",
                              "empty.csv", "ok.png")} | {"missing": d / "missing_input", "dir": d,
                                               "unwritable": d / "afile" / "out" / "result.json"}


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("thermal")
    assert main(["-q", "thermal", "simulate", str(out), "--fires", "1", "--frames", "3", "--size", "160x128"]) == 0
    return out


@pytest.fixture(scope="module")
def field(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tags") / "field.json"
    assert main(["-q", "tags", "generate", "-o", str(out), "--rows", "3", "--cols", "3", "--time-limit-s", "0.2"]) == 0
    return out


def _owner(case, owner: str, what: str):
    return pytest.param(*case, marks=pytest.mark.xfail(strict=True, reason=f"{owner}: {what}"))


# (command, argv builder (files, flight, field) -> argv, names one of which the error must carry)
CASES = [
    # thermal
    ("thermal locate", lambda f, fl, _: ["thermal", "locate", str(f["missing"]), "--poses", str(fl / "poses.csv"),
                                          "--camera", str(fl / "camera.json"), "--ground-alt", "30", "-o",
                                          str(f["dir"] / "o.geojson")], ["missing_input"]),
    ("thermal locate", lambda f, fl, _: ["thermal", "locate", str(f["empty"]), "--poses", str(fl / "poses.csv"),
                                          "--camera", str(fl / "camera.json"), "--ground-alt", "30", "-o",
                                          str(f["dir"] / "o.geojson")], ["empty"]),
    ("thermal locate", lambda f, fl, _: ["thermal", "locate", str(f["text"]), "--poses", str(fl / "poses.csv"),
                                          "--camera", str(fl / "camera.json"), "--ground-alt", "30", "-o",
                                          str(f["dir"] / "o.geojson")], ["text"]),
    ("thermal locate", lambda f, fl, _: ["thermal", "locate", str(fl / "frames"), "--poses", str(f["empty.csv"]),
                                          "--camera", str(fl / "camera.json"), "--ground-alt", "30", "-o",
                                          str(f["dir"] / "o.geojson")], ["empty.csv"]),
    ("thermal locate", lambda f, fl, _: ["thermal", "locate", str(fl / "frames"), "--poses", str(fl / "poses.csv"),
                                          "--camera", str(f["bad.json"]), "--ground-alt", "30", "-o",
                                          str(f["dir"] / "o.geojson")], ["bad.json"]),
    ("thermal locate", lambda f, fl, _: ["thermal", "locate", str(fl / "frames"), "--poses", str(fl / "poses.csv"),
                                          "--camera", str(fl / "camera.json"), "--ground-alt", "30", "-o",
                                          str(f["unwritable"])], ["afile"]),
    ("thermal locate", lambda f, fl, _: ["thermal", "locate", str(fl / "frames"), "--poses", str(fl / "poses.csv"),
                                          "--camera", str(fl / "camera.json"), "--dem", str(f["fake.png"]), "-o",
                                          str(f["dir"] / "o.geojson")], ["fake.png"]),
    ("thermal detect", lambda f, fl, _: ["thermal", "detect", str(f["missing"]), "--pose", str(fl / "poses.csv"),
                                          "--camera", str(fl / "camera.json"), "--ground-alt", "30", "-o",
                                          str(f["dir"] / "h.geojson")], ["missing_input"]),
    ("thermal detect", lambda f, fl, _: ["thermal", "detect", str(f["truncated.jpg"]), "--pose",
                                          str(fl / "poses.csv"), "--camera", str(fl / "camera.json"),
                                          "--ground-alt", "30", "-o", str(f["dir"] / "h.geojson")],
     ["truncated.jpg"]),
    ("thermal simulate", lambda f, fl, _: ["thermal", "simulate", str(f["afile"])], ["afile"]),
    ("thermal simulate", lambda f, fl, _: ["thermal", "simulate", str(f["dir"] / "s"), "--frames", "0"],
     ["--frames"]),
    ("thermal simulate", lambda f, fl, _: ["thermal", "simulate", str(f["dir"] / "s2"), "--size", "big"],
     ["--size"]),
    ("datasets thermal-flight", lambda f, fl, _: ["datasets", "thermal-flight", str(f["afile"])], ["afile"]),
    ("datasets thermal-flight", lambda f, fl, _: ["datasets", "thermal-flight", str(f["dir"] / "s3"),
                                                  "--frames", "0"], ["--frames"]),
    ("datasets thermal-flight", lambda f, fl, _: ["datasets", "thermal-flight", str(f["dir"] / "s4"),
                                                  "--size", "big"], ["--size"]),
    # tags
    ("tags generate", lambda f, fl, _: ["tags", "generate", "-o", str(f["unwritable"]), "--rows", "2", "--cols", "2",
                                         "--time-limit-s", "0.1"], ["afile"]),
    ("tags generate", lambda f, fl, _: ["tags", "generate", "-o", str(f["dir"] / "g.json"), "--rows", "0"],
     ["rows"]),
    ("tags board", lambda f, fl, _: ["tags", "board", "-o", str(f["unwritable"])], ["afile"]),
    ("tags board", lambda f, fl, _: ["tags", "board", "-o", str(f["dir"] / "b.json"), "--dictionary", "nope"],
     ["nope"]),
    ("tags locate", lambda f, fl, fd: ["tags", "locate", str(f["missing"]), "--field", str(fd), "--hfov-deg", "60",
                                        "-o", str(f["dir"] / "t.csv")], ["missing_input"]),
    ("tags locate", lambda f, fl, fd: ["tags", "locate", str(f["truncated.jpg"]), "--field", str(fd),
                                        "--hfov-deg", "60", "-o", str(f["dir"] / "t.csv")], ["truncated.jpg"]),
    ("tags locate", lambda f, fl, fd: ["tags", "locate", str(f["fake.jpg"]), "--field", str(fd), "--hfov-deg", "60",
                                        "-o", str(f["dir"] / "t.csv")], ["fake.jpg"]),
    ("tags locate", lambda f, fl, fd: ["tags", "locate", str(f["fake.jpg"]), "--field", str(f["bad.json"]),
                                        "--hfov-deg", "60", "-o", str(f["dir"] / "t.csv")], ["bad.json"]),
    ("tags dimension", lambda f, fl, _: ["tags", "dimension", "--area-m", "5", "5", "--min-height-m", "-1",
                                          "--max-height-m", "3"], ["height"]),
    # crps
    ("crps range", lambda f, fl, _: ["crps", "range", str(f["missing"]), "--camera", "80", "--size-m", "0.5"],
     ["missing_input"]),
    ("crps range", lambda f, fl, _: ["crps", "range", str(f["truncated.jpg"]), "--camera", "80", "--size-m", "0.5"],
     ["truncated.jpg"]),
    ("crps range", lambda f, fl, _: ["crps", "range", str(f["fake.jpg"]), "--camera", "80", "--size-m", "0.5"],
     ["fake.jpg"]),
    ("crps range", lambda f, fl, _: ["crps", "range", str(f["ok.png"]), "--camera", "80", "--size-m", "-1"],
     ["--size-m"]),
    # mapping
    ("lens correct", lambda f, fl, _: ["lens", "correct", str(f["missing"]), str(f["dir"] / "lc"), "--barrel",
                                        "0.1 -0.32 0"], ["missing_input"]),
    ("lens correct", lambda f, fl, _: ["lens", "correct", str(f["empty"]), str(f["dir"] / "lc"), "--barrel",
                                        "0.1 -0.32 0"], ["empty"]),
    ("lens calibrate", lambda f, fl, _: ["lens", "calibrate", str(f["missing"])], ["missing_input"]),
    ("lens calibrate", lambda f, fl, _: ["lens", "calibrate", str(f["text"])], ["text"]),
    ("lens convert", lambda f, fl, _: ["lens", "convert", "--calibration", str(f["missing"])], ["missing_input"]),
    ("plan extend", lambda f, fl, _: ["plan", "extend", str(f["missing"]), "--alarm", "46.5,6.6", "--joining", "1",
                                       "-o", str(f["dir"] / "pe")], ["missing_input"]),
    ("plan handoff", lambda f, fl, _: ["plan", "handoff", str(f["bad.json"]), "--next-index", "1", "--available",
                                        "2=46.5,6.6", "-o", str(f["dir"] / "ph")], ["bad.json"]),
    ("plan polygon", lambda f, fl, _: ["plan", "polygon", "--polygon", str(f["bad.json"]), "--alt", "50",
                                        "-o", str(f["dir"] / "pp")], ["bad.json"]),
    ("plan corners", lambda f, fl, _: ["plan", "corners", "--corners", "46.5,6.6", "46.501,6.6", "46.501,6.601",
                                        "--step", "-5", "--alt", "30", "-o", str(f["dir"] / "pc")], ["step"]),
    ("plan corners", lambda f, fl, _: ["plan", "corners", "--corners", "46.5,6.6", "46.501,6.6", "46.501,6.601",
                                        "--step", "0.1", "--alt", "30", "-o", str(f["dir"] / "pc")], ["--step"]),
    ("lens correct", lambda f, fl, _: ["lens", "correct", str(f["dir"]), str(f["dir"] / "lq"), "--barrel",
                                        "0.1 -0.32 0", "--quality", "500"], ["--quality"]),
    ("map", lambda f, fl, _: ["map", str(f["missing"]), "--out-dir", str(f["dir"] / "m")], ["missing_input"]),
    ("map", lambda f, fl, _: ["map", str(f["empty"]), "--out-dir", str(f["dir"] / "m")], ["empty"]),
    # fusion, datasets
    ("fusion replay", lambda f, fl, _: ["fusion", "replay", str(f["missing"])], ["missing_input"]),
    ("fusion replay", lambda f, fl, _: ["fusion", "replay", str(f["bad.json"])], ["bad.json"]),
    ("datasets fusion-log", lambda f, fl, _: ["datasets", "fusion-log", str(f["unwritable"])], ["afile"]),
    ("datasets fusion-log", lambda f, fl, _: ["datasets", "fusion-log", str(f["dir"] / "fl.jsonl"),
                                               "--duration-s", "-3"], ["duration"]),
    # drivers, crps service
    ("vehicle mission upload", lambda f, fl, _: ["vehicle", "mission", "upload", "udpout:127.0.0.1:9",
                                                  str(f["missing"]), "--timeout", "0.5"], ["missing_input"]),
    ("vehicle mission download", lambda f, fl, _: ["vehicle", "mission", "download", "tcp:127.0.0.1:bad", "-o",
                                                    str(f["dir"] / "m.json"), "--timeout", "0.5"],
     ["tcp:127.0.0.1:bad"]),
    ("vehicle status", lambda f, fl, _: ["vehicle", "status", "udpin:127.0.0.1:9", "--timeout", "-1"],
     ["--timeout"]),
    ("serve", lambda f, fl, _: ["serve", "--id", "d1", "--mavlink", "udpin:127.0.0.1:14999", "--swarm",
                                 "listen:tcp/127.0.0.1:7499", "--swarm-key-file", str(f["missing"])],
     ["missing_input"]),
    ("swarm status", lambda f, fl, _: ["swarm", "status", "--swarm", "tcp/127.0.0.1:7498", "--swarm-key-file",
                                        str(f["missing"]), "--listen-s", "0.2"], ["missing_input"]),
]

#: Cases that, wrongly accepted, would run a simulation: run in a subprocess with a limit.
SLOW_IF_ACCEPTED = [
    ("sim", ["sim", "--duration", "-3"], ["duration"]),
    ("sim", ["sim", "--param", "NOT_A_PARAM=3", "--duration", "0.2"], ["NOT_A_PARAM"]),
    ("demo", ["demo", "-o", "__FILE__"], ["afile"]),
    ("demo", ["demo", "--speed", "-1"], ["speed"]),
]


@pytest.mark.parametrize("command, argv, names", CASES, ids=[
    f"{c.values[0] if hasattr(c, 'values') else c[0]}-{i}" for i, c in enumerate(CASES)])
def test_bad_input_is_one_line_exit_2(command, argv, names, files, flight, field, capsys):
    rc, err = _run_main(argv(files, flight, field), capsys)
    _one_line_error(rc, err, *names)


@pytest.mark.parametrize("command, argv, names", SLOW_IF_ACCEPTED, ids=[
    f"{c.values[0] if hasattr(c, 'values') else c[0]}-{i}" for i, c in enumerate(SLOW_IF_ACCEPTED)])
def test_bad_input_of_long_commands(command, argv, names, files):
    argv = [str(files["afile"]) if a == "__FILE__" else a for a in argv]
    rc, err = _run_sub(argv, timeout_s=20.0)
    _one_line_error(rc, err, *names)


def _numeric_options() -> list[tuple[str, str]]:
    out = []
    for path, p in LEAVES.items():
        for a in p._actions:
            if a.option_strings and a.type in _NUMERIC:
                out.append((path, a.option_strings[-1]))
    return out


@pytest.mark.parametrize("command, option", _numeric_options())
def test_wrong_type_is_one_line_exit_2(command, option, capsys):
    rc, err = _run_main([*command.split(), option, "not-a-number"], capsys)
    _one_line_error(rc, err, option)


def test_every_command_is_walked():
    walked = {c.values[0] if hasattr(c, "values") else c[0] for c in CASES + SLOW_IF_ACCEPTED}
    missing = set(LEAVES) - walked - NO_FILE_INPUT
    assert not missing, f"commands with file input but no bad-input case here: {sorted(missing)}"
    assert not (set(NO_FILE_INPUT) - set(LEAVES)), "NO_FILE_INPUT names a command that no longer exists"
    assert len(_numeric_options()) > 50
