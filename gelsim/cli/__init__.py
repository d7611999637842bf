"""The ``gelsim`` command line: a thin layer over the Python API.

Each command group lives in its own module exposing ``register(subparsers)``;
the handler it installs receives the parsed ``argparse.Namespace`` and returns
an exit code. A :class:`~gelsim.errors.GelsimError` becomes one line on stderr
and exit status 2 (:func:`guarded`; the scripts under ``benchmarks/`` and ``tools/``
get the same contract from :func:`run_script`).
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
from typing import Callable, NoReturn

from .. import __version__
from ..atomic import json_default
from ..errors import GelsimError

# Command modules, in the order they appear in --help.
COMMAND_MODULES = (
    "bench_cmd",
    "fabrics_cmd",
    "generate_cmd",
    "press_cmd",
    "realism_cmd",
    "render_cmd",
    "sensors_cmd",
    "show_cmd",
    "texture_cmd",
)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows defaults and keeps the descriptions' line breaks. An option whose help states its default
    itself, or whose default is None (resolved later, e.g. from a preset), gets no "(default: None)"."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default is None or "default" in text.lower():
            return text
        return super()._get_help_string(action)


class ArgumentParser(argparse.ArgumentParser):
    """argparse with the CLI's error contract: a bad option (an unknown one, a bad number or choice, a
    missing required one) is one line ``PROG: error: <problem>; see `PROG --help``` on stderr and
    status 2, without argparse's usage block. Sub-command parsers inherit it."""

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {message}; see `{self.prog} --help`", file=sys.stderr)
        sys.exit(2)


def seed_arg(text: str) -> int:
    """argparse ``type`` of every ``--seed``: a whole number >= 0 (numpy's generators refuse a negative seed,
    which was a traceback)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a seed; give a whole number >= 0")
    return value


def print_json(obj) -> None:
    """Write one JSON document to stdout (the ``--json`` contract of every command)."""
    json.dump(obj, sys.stdout, indent=2, default=json_default)
    sys.stdout.write("\n")


def print_result(as_json: bool, doc, *lines: str) -> int:
    """A command's result: ``doc`` as one JSON document with ``--json`` (``as_json``), else ``lines``,
    one per line. Returns 0, the handler's exit status."""
    if as_json:
        print_json(doc)
    else:
        for line in lines:
            print(line)
    return 0


def warn(prog: str, message: str) -> None:
    """One line ``PROG: warning: <message>`` on stderr: the result was made, but not as asked."""
    print(f"{prog}: warning: {message}", file=sys.stderr)


def warn_if_bottomed(prog: str, bottomed: bool, carried_n: float, asked_n: float | None) -> None:
    """Out-of-range physics said on stderr, not only in ``--json``: the pad reached its full travel."""
    if not bottomed:
        return
    asked = "" if asked_n is None else f" of the {asked_n:g} N asked"
    warn(prog, f"the gel bottomed out (pressed to its full travel) and carries {carried_n:.3g} N{asked}; "
               "ask for less force or depth to stay within the gel's range")


def say_first_run(prog: str) -> None:
    """For a command that renders frames: the first compile of the numba kernels on this machine (10-30 s)
    is said on stderr in one line, ``PROG: first run on this machine: compiling ...`` (gelsim.firstrun), when
    stderr is a terminal: a person waits there; a log or a test reading stderr gets only the command's own
    lines."""
    if not sys.stderr.isatty():
        return
    from ..firstrun import announce_compiles

    announce_compiles(lambda line: print(f"{prog}: {line}", file=sys.stderr, flush=True))


def needs_subcommand(parser: argparse.ArgumentParser, subparsers) -> None:
    """``parser``, a command of subcommands (``subparsers``, its ``add_subparsers()``, all added), run
    without one: one line naming them, status 2 (argparse alone would run nothing)."""
    names = list(subparsers.choices)

    def handler(args) -> int:
        raise GelsimError(f"`{parser.prog}` needs a subcommand, one of {', '.join(names)}; e.g. "
                          f"`{parser.prog} {names[0]}` (see `{parser.prog} --help`)")

    parser.set_defaults(handler=handler)


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog="gelsim",
        description="GelSight tactile simulator and synthetic dataset generator.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"gelsim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


def dispatch(parser: argparse.ArgumentParser, argv: list[str] | None, *,
             interrupted: str = "rerun the same command to continue") -> int:
    """Parse ``argv`` and run the chosen command's handler under :func:`guarded` (the CLI's error
    contract); no command: the help and status 2."""
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    return guarded(parser.prog, lambda: args.handler(args), interrupted=interrupted)


def guarded(prog: str, run: Callable[[], int | None], *,
            interrupted: str = "rerun the same command to continue") -> int:
    """``run()``'s exit status (None is 0) under the CLI's error contract: a GelsimError is one line
    ``PROG: error: <message>`` on stderr and status 2; Ctrl-C exits 130 with ``interrupted``; a closed
    stdout pipe (``| head``) ends quietly with status 141."""
    try:
        code = int(run() or 0)
        sys.stdout.flush()  # inside the try: a reader gone away (`| head`) shows up here, not at exit
        return code
    except GelsimError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; {interrupted}", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader closed the pipe: stop quietly, as cat does. Point stdout at /dev/null so that
        # Python's own flush at exit does not raise again; 141 = 128 + SIGPIPE, a shell's status for it.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


def run_script(main: Callable[[], int | None]) -> NoReturn:
    """``if __name__ == "__main__": run_script(main)``: a benchmark's or tool's ``main()`` under
    :func:`guarded` (the script's file name as the program's), exiting with its status."""
    sys.exit(guarded(os.path.basename(sys.argv[0]), main))


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
