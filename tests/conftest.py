"""Fixtures shared across the test folders."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from readme_blocks import ROOT, BlockRun, run_blocks


@pytest.fixture(scope="session")
def readme_runs(tmp_path_factory) -> Callable[[Path], list[BlockRun]]:
    """The runs of a README's blocks (readme_blocks.run_blocks), once per session and README:
    tests/test_readme_commands.py checks that every block succeeds, and tests that check what
    a block produced (tests/crps/test_recovery_demo.py: the top README's ``skyfix demo``) read
    the same run instead of running the command again."""
    done: dict[Path, list[BlockRun]] = {}

    def runs(readme: Path) -> list[BlockRun]:
        readme = Path(readme).resolve()
        if readme not in done:
            folder = tmp_path_factory.mktemp(str(readme.relative_to(ROOT)).replace("/", "_").replace(".", "_"))
            done[readme] = run_blocks(readme, folder)
        return done[readme]

    return runs


@pytest.fixture(scope="session")
def readme_demo(readme_runs) -> BlockRun:
    """The top README's ``skyfix demo`` block as its README test ran it (seeded, so the flight is
    the same each run); its files are in ``folder / "skyfix-demo"`` (the command's default)."""
    runs = [r for r in readme_runs(ROOT / "README.md") if "skyfix demo" in r.command[-1]]
    assert runs, "README.md: no block runs 'skyfix demo'"
    assert "--seed" in runs[0].command[-1], "README.md's demo must be seeded: tests check its flight's figures"
    return runs[0]
