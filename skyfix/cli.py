"""The ``skyfix`` command line: one entry point, one subcommand per capability.

Each subsystem contributes its subcommands through a module exposing
``register(subparsers)``; that module imports heavy dependencies lazily, inside the
command function, so ``skyfix --help`` stays fast. A command function takes the parsed
``argparse.Namespace`` and returns the process exit code.

Errors have one shape everywhere (:func:`run_command`): a skyfix exception about the
user's input (:class:`~skyfix.errors.InputError`, :class:`~skyfix.errors.DataError`,
:class:`~skyfix.errors.ConfigurationError`, :class:`~skyfix.errors.NotAvailableError`) or
an ``OSError`` on a file the user named is one line on stderr and exit code 2
(argparse's own code for a bad command line); a failure of the operation itself (link
lost, timeout, command rejected, estimate impossible) is one line and exit code 1. The
line is logged (``ERROR skyfix: ...`` on stderr), so ``-q`` keeps it. Tracebacks only
with ``-v``. ``-v``/``-q`` work before or after the subcommand.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import importlib.util
import logging
import os
import re
import sys
import traceback
from collections.abc import Callable, Sequence

import skyfix
from skyfix import progress
from skyfix.errors import ConfigurationError, DataError, InputError, NotAvailableError, SkyfixError

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


class SkyfixArgumentParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line naming the command and where to
    look (argparse prints the whole usage block first); subcommands inherit it."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser, with every available subcommand registered."""
    parser = SkyfixArgumentParser(
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
                        help="more log output: skyfix's info is shown by default; -v adds other libraries' info, -vv debug")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="only warnings and errors; no progress bars")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    for name in SUBCOMMAND_MODULES:
        if _module_exists(name):
            _register(name, subparsers)
    for _path, sub in iter_parsers(parser):
        sub.formatter_class = _skyfix_formatter(sub.formatter_class)
        if sub is not parser and "-" in sub.prefix_chars:  # not the stand-ins of a missing extra
            _add_log_flags(sub)
    return parser


#: Commands of a subcommand module that needs an extra to import, and that extra: without
#: it they stay listed and say which extra to install.
EXTRA_COMMANDS = {"skyfix.mapping.cli": ("mapping", ("lens", "plan", "map"))}


def _register(module: str, subparsers: argparse._SubParsersAction) -> None:
    """Register a module's subcommands; one that cannot import for want of an extra gets
    stand-ins that fail with the one-line 'install the extra' error."""
    try:
        importlib.import_module(module).register(subparsers)
    except ModuleNotFoundError as exc:
        extra, commands = EXTRA_COMMANDS.get(module, (None, ()))
        if extra is None or (exc.name or "").split(".")[0] not in EXTRAS:
            raise
        for command in (c for c in commands if c not in subparsers.choices):  # some may be registered already
            stub = subparsers.add_parser(command, help=f"(needs the '{extra}' extra: pip install 'skyfix[{extra}]')",
                                         add_help=False, prefix_chars="\0")
            stub.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
            stub.set_defaults(func=functools.partial(_reraise, exc))


def _reraise(exc: BaseException, _args: argparse.Namespace) -> int:
    raise exc


def iter_parsers(parser: argparse.ArgumentParser, prefix: str = "skyfix"):
    """Yield ``(command path, parser)`` for ``parser`` and every subcommand at any depth."""
    yield prefix, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from iter_parsers(sub, f"{prefix} {name}")


class _DefaultsMixin:
    """Help that states each option's default once: appended only when the option has a
    default and its help does not already mention one; ``%%`` in descriptions shown as ``%``."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        no_default = action.default is None or action.default is False or action.default is argparse.SUPPRESS
        counter = isinstance(action, argparse._CountAction)
        if "default" in text.lower() or no_default or counter or not action.option_strings:
            return text
        return text + " (default: %(default)s)"

    def _format_text(self, text: str) -> str:
        if "%(prog)" not in text:
            text = text.replace("%%", "%")
        return super()._format_text(text)


def _skyfix_formatter(base: type) -> type:
    """``base`` (a parser's formatter class) with :class:`_DefaultsMixin`; the plain
    HelpFormatter for ArgumentDefaultsHelpFormatter, which would add a second default."""
    if issubclass(base, _DefaultsMixin):
        return base
    if issubclass(base, argparse.ArgumentDefaultsHelpFormatter):
        base = argparse.HelpFormatter
    return type(f"Skyfix{base.__name__}", (_DefaultsMixin, base), {})


def _add_log_flags(parser: argparse.ArgumentParser) -> None:
    """``-v``/``-q`` after a subcommand too (stored apart, merged in :func:`main`)."""
    taken = {s for a in parser._actions for s in a.option_strings}
    if not taken & {"-v", "--verbose"}:
        parser.add_argument("-v", "--verbose", action="count", dest="sub_verbose", default=argparse.SUPPRESS,
                            help="-v: other libraries' info too, -vv: debug (also before the command)")
    if not taken & {"-q", "--quiet"}:
        parser.add_argument("-q", "--quiet", action="store_true", dest="sub_quiet", default=argparse.SUPPRESS,
                            help="only warnings and errors; no progress bars (also before the command)")


#: Python loggers of third-party libraries, kept at ERROR unless -v.
THIRD_PARTY_LOGGERS = ("matplotlib", "PIL", "rasterio", "zenoh", "pycolmap", "urllib3", "asyncio", "websockets",
                       "mavsdk", "foxglove", "fiona", "numba", "h5py")


def configure_logging(verbose: int, quiet: bool):
    """Log to stderr at a level chosen by -v/-q (default: warnings and info of skyfix);
    returns a function that undoes it (``main`` run in-process leaves no trace).

    Without -v, third-party chatter is silenced: their Python loggers at ERROR, OpenCV's
    own log at ERROR (OPENCV_LOG_LEVEL, read when cv2 is imported; cv2 is imported lazily by
    the commands), COLMAP/glog at ERROR (GLOG_minloglevel), zenoh's Rust log off (RUST_LOG).
    Log lines are written through tqdm so they do not break a progress bar."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose >= 2 else logging.INFO)
    root, own = logging.getLogger(), logging.getLogger("skyfix")
    third_party = logging.DEBUG if verbose >= 2 else (logging.INFO if verbose else logging.ERROR)
    noisy = [logging.getLogger(name) for name in THIRD_PARTY_LOGGERS]
    saved = (root.level, own.level, [lg.level for lg in noisy], progress.enabled_setting())
    handler = progress.LogHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    own.setLevel(level)
    if verbose:
        root.setLevel(min(level, root.level))
    progress.set_enabled(False if quiet else None)
    for lg in noisy:
        lg.setLevel(third_party)

    def restore() -> None:
        root.removeHandler(handler)
        root.setLevel(saved[0])
        own.setLevel(saved[1])
        for lg, lvl in zip(noisy, saved[2], strict=True):
            lg.setLevel(lvl)
        progress.set_enabled(saved[3])

    if not verbose:
        os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
        os.environ.setdefault("GLOG_minloglevel", "2")
        os.environ.setdefault("RUST_LOG", "error")
        if "cv2" in sys.modules:  # already loaded: the environment variable is read too late
            try:
                import cv2.utils.logging as cv_log

                cv_log.setLogLevel(cv_log.LOG_LEVEL_ERROR)
            except (ImportError, AttributeError):
                pass
    return restore


#: Optional packages -> the skyfix extra that installs them (pyproject.toml).
EXTRAS = {"pycolmap": "mapping", "piexif": "mapping", "simplekml": "mapping", "simplejpeg": "mapping",
          "rasterio": "thermal",
          "torch": "gpu", "kornia": "gpu", "pupil_apriltags": "bench", "filterpy": "bench"}

#: skyfix exceptions that mean "the input is wrong" (exit 2); other SkyfixErrors exit 1.
INPUT_ERRORS = (InputError, DataError, ConfigurationError, NotAvailableError)


def error_line(exc: BaseException) -> str:
    """One line for the user: the message (which names the input), without doubled prefixes."""
    if isinstance(exc, OSError) and not isinstance(exc, SkyfixError) and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror or exc}"
    else:
        text = str(exc) or type(exc).__name__
    text = " ".join(text.split())
    # A name prefixed twice by nested handlers ("a.jpg: a.jpg: corrupt JPEG") is said once.
    return re.sub(r"^([^:\s]+): (\1: )+", r"\1: ", text)


def run_command(func: Callable[[argparse.Namespace], int | None], args: argparse.Namespace, verbose: int = 0) -> int:
    """Run a command function; turn its errors into one line on stderr and an exit code:
    2 for bad input (skyfix input errors, a file the user named that cannot be read or
    written), 1 for a failed operation, 130 for Ctrl-C. The traceback only with -v."""
    try:
        return int(func(args) or 0)
    except KeyboardInterrupt:
        log.error("interrupted")
        return 130
    except BrokenPipeError:  # output piped into `head` and the like: stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except (SkyfixError, OSError) as exc:
        bad_input = isinstance(exc, INPUT_ERRORS) or (isinstance(exc, OSError) and not isinstance(exc, SkyfixError))
        if verbose:
            traceback.print_exc()
        log.error("%s", error_line(exc))
        return 2 if bad_input else 1
    except Exception as exc:  # a missing extra, or a bug in skyfix: still one line, the traceback with -v
        if verbose:
            traceback.print_exc()
        top = (getattr(exc, "name", None) or "").split(".")[0] if isinstance(exc, ModuleNotFoundError) else ""
        if top in EXTRAS:
            log.error("%s is not installed: this command needs skyfix's optional '%s' extra (pip install "
                      "'skyfix[%s]', or 'skyfix[all]' for every extra)", top, EXTRAS[top], EXTRAS[top])
            return 2
        log.error("internal error: %s: %s (a bug: please report it with the output of the same command "
                  "run with -v)", type(exc).__name__, error_line(exc))
        return 1


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``skyfix`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.verbose += getattr(args, "sub_verbose", 0) or 0
    args.quiet = args.quiet or getattr(args, "sub_quiet", False)
    restore = configure_logging(args.verbose, args.quiet)
    try:
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        return run_command(args.func, args, args.verbose)
    finally:
        restore()


if __name__ == "__main__":
    sys.exit(main())
