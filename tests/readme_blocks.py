"""Running a README's blocks as written (used by tests/test_readme_commands.py and tests/conftest.py).

- Fenced ``sh``/``bash`` blocks are run by bash in one folder per README, in the order they
  appear, together with the README's Python blocks whose first line is ``# runs as is`` (so a
  block can use the files an earlier one wrote). The install step of the top README
  (``pip install -e . && ...``) is not re-run: the package under test is installed; its test
  command is CI's (checked verbatim by tests/foundation/test_cli.py), so it is not run from
  inside the test suite.
"""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"```([a-z]*)\n(.*?)```", re.S)


def rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def shell_lines(block: str) -> list[str]:
    """Shell lines of a block with backslash continuations joined and comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", block)
    out = []
    for line in joined.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            out.append(line)
    return out


def runnable(readme: Path) -> list[tuple[str, str]]:
    """(kind, text) of the blocks to run, in order: kind 'sh' or 'python'."""
    out = []
    for lang, body in FENCE.findall(readme.read_text()):
        if lang in ("sh", "bash", "shell"):
            out.append(("sh", body))
        elif lang == "python" and body.startswith("# runs as is"):
            out.append(("python", body))
    return out


def as_run_here(line: str) -> str | None:
    """The line to run, or None for one CI runs instead (the README's install + test)."""
    if "python -m pytest" in line:
        return None
    return re.sub(r"^pip install -e \S+\s*&&\s*", "", line)


@dataclass(frozen=True)
class BlockRun:
    """One block run in ``folder``: its text, the command, and what the command did."""

    index: int
    body: str
    command: list[str]
    folder: Path
    returncode: int
    stdout: str
    stderr: str


def run_blocks(readme: Path, folder: Path) -> list[BlockRun]:
    """Run the README's runnable blocks in order in ``folder`` (stops after the first that fails)."""
    runs = []
    for k, (kind, body) in enumerate(runnable(readme)):
        if kind == "python":
            script = folder / f"block{k}.py"
            script.write_text(body)
            cmd = [sys.executable, str(script)]
        else:
            lines = [x for x in (as_run_here(ln) for ln in shell_lines(body)) if x]
            if not lines:
                continue
            cmd = ["bash", "-euo", "pipefail", "-c", "\n".join(lines)]
        out = subprocess.run(cmd, cwd=folder, capture_output=True, text=True, timeout=600)
        runs.append(BlockRun(k, body, cmd, folder, out.returncode, out.stdout, out.stderr))
        if out.returncode != 0:
            break
    return runs
