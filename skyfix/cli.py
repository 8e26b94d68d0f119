"""The ``skyfix`` command line: one entry point, one subcommand per capability.

Each subsystem contributes its subcommands through a module exposing
``register(subparsers)``; that module imports heavy dependencies lazily, inside the
command function, so ``skyfix --help`` stays fast. A command function takes the parsed
``argparse.Namespace`` and returns the process exit code.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys
from collections.abc import Sequence

import skyfix
from skyfix import progress
from skyfix.errors import SkyfixError

log = logging.getLogger("skyfix")

#: Modules that may add subcommands; a module that does not exist yet is skipped.
SUBCOMMAND_MODULES: tuple[str, ...] = (
    "skyfix.crps.demo",
    "skyfix.thermal.cli",
    "skyfix.crps.cli",
    "skyfix.tags.cli",
    "skyfix.mapping.cli",
    "skyfix.fusion.cli",
    "skyfix.drivers.cli",
    "skyfix.datasets.cli",
    "skyfix.crps.serve_cli",
)


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser, with every available subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="skyfix",
        description=(
            "skyfix keeps drones localised and turns their imagery into maps: thermal "
            "hotspot geolocation, drone-to-drone ranging, fiducial-tag localisation, "
            "photo-to-model mapping, gtsam fusion and MAVLink drivers."
        ),
        epilog="Run 'skyfix COMMAND --help' for the options of one command.",
    )
    parser.add_argument("--version", action="version", version=f"skyfix {skyfix.__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-v: info, -vv: debug)")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="only warnings and errors; no progress bars")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    for name in SUBCOMMAND_MODULES:
        if _module_exists(name):
            importlib.import_module(name).register(subparsers)
    return parser


def configure_logging(verbose: int, quiet: bool) -> None:
    """Log to stderr at a level chosen by -v/-q (default: warnings and info of skyfix)."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose >= 2 else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if quiet:
        progress.set_enabled(False)
    if verbose < 2:  # third-party chatter only at -vv
        for noisy in ("matplotlib", "PIL", "rasterio"):
            logging.getLogger(noisy).setLevel(logging.WARNING)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``skyfix`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except SkyfixError as exc:
        log.error("%s", exc)
        return 1
    except KeyboardInterrupt:
        log.error("interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
