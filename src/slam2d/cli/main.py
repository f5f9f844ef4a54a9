"""Entry point: builds one sub-command per module in ``COMMANDS``; the one error boundary of the CLI.

Every error a user can cause (a path that is missing, a directory, read-only or full; a config value out of range;
a malformed file; a numeric failure) ends as ONE line on stderr, ``slam2d CMD: error: ...`` naming the path or
field, and exit status 2. Anything else is a bug: one line saying so and exit status 3. ``--debug`` (anywhere on
the command line) or ``SLAM2D_DEBUG=1`` re-raises with the full stack instead.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings
from collections.abc import Sequence

#: one module per sub-command; each defines ``register(subparsers)`` and sets ``func`` on its parser
COMMANDS = [
    "slam2d.cli.simulate",
    "slam2d.cli.run",
    "slam2d.cli.demo",
    "slam2d.cli.experiment",
    "slam2d.cli.sweep",
    "slam2d.cli.report",
    "slam2d.cli.datasets",
    "slam2d.cli.optimize",
    "slam2d.cli.lab",
    "slam2d.cli.exercise",
    "slam2d.cli.lidar",
    "slam2d.cli.map",
    "slam2d.cli.fleet",
]

EXIT_USER = 2
EXIT_BUG = 3
EXIT_INTERRUPTED = 130


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("slam2d")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slam2d", description="Classical 2D SLAM: simulate, estimate, evaluate.",
                                     epilog="--debug (anywhere) shows the full stack of an error.")
    parser.add_argument("--version", action="version", version=f"slam2d {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(name).register(sub)
    return parser


def _one_line(text: str, limit: int = 600) -> str:
    s = " ".join(text.split())
    return s if len(s) <= limit else s[: limit - 3] + "..."


def describe(e: BaseException) -> str | None:
    """The one-line message for an error the user can cause; None for anything else (a bug)."""
    from slam2d.estimator import EstimatorStateError

    if isinstance(e, OSError):
        where = e.filename if e.filename is not None else ""
        why = e.strerror or str(e) or type(e).__name__
        if e.filename2 is not None:
            where = f"{where} -> {e.filename2}"
        return f"{where}: {why}" if where else why
    if isinstance(e, OverflowError | FloatingPointError | ZeroDivisionError):
        return f"numeric failure ({type(e).__name__}: {e})"
    if isinstance(e, RecursionError):
        return f"input nested too deeply ({e})"
    if isinstance(e, MemoryError):
        return "out of memory (reduce the problem size)"
    try:
        from numpy.linalg import LinAlgError
    except ImportError:  # pragma: no cover
        LinAlgError = ()  # type: ignore[assignment,misc]
    if isinstance(e, LinAlgError):
        return f"linear algebra failed ({e})"
    if isinstance(e, EstimatorStateError):
        return None
    # config (ValueError / TypeError naming the field) and every format error (LogFormatError, GraphFormatError,
    # DatasetFormatError, CARMEN errors, SolverError: all ValueError subclasses)
    if isinstance(e, ValueError | TypeError | KeyError | LookupError):
        return str(e) if not isinstance(e, KeyError) else f"missing key {e}"
    return None


def _debug_requested(argv: list[str]) -> bool:
    return "--debug" in argv or os.environ.get("SLAM2D_DEBUG", "") not in ("", "0")


def main(argv: Sequence[str] | None = None) -> int:
    args_in = list(sys.argv[1:] if argv is None else argv)
    debug = _debug_requested(args_in)
    args_in = [a for a in args_in if a != "--debug"]
    command = ["?"]
    with warnings.catch_warnings():
        if not debug:
            # numeric warnings are noise next to the one-line error: divergence is checked and reported as an error
            warnings.simplefilter("ignore", RuntimeWarning)
            # the library's own warnings (a file's skipped lines, ...) as one line each, without Python's source echo
            warnings.simplefilter("default", UserWarning)
            warnings.showwarning = lambda message, *_, **__: print(
                f"slam2d {command[0]}: warning: {_one_line(str(message))}", file=sys.stderr)
        return _run(args_in, command, debug)


def _run(args_in: list[str], command: list[str], debug: bool) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(args_in)
        command[0] = str(args.command)
        if not getattr(args, "func", None):
            parser.print_help()
            return EXIT_USER
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print(f"slam2d {command[0]}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # the reader went away (``slam2d datasets | head``): not an error of ours or theirs
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes at exit
        return 0
    except SystemExit:
        raise
    except Exception as e:
        if debug:
            raise
        msg = describe(e)
        if msg is None:
            print(f"slam2d {command[0]}: internal error: {_one_line(f'{type(e).__name__}: {e}')} "
                  "(a bug; --debug shows the stack)", file=sys.stderr)
            return EXIT_BUG
        print(f"slam2d {command[0]}: error: {_one_line(msg)}", file=sys.stderr)
        return EXIT_USER


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
