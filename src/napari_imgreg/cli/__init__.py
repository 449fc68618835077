"""The ``napari-imgreg`` command line (contract §8).

Every command prints a short human summary and writes machine-readable
output. Exit codes: 0 success, 1 a registration that failed its quality bar,
2 bad input (one line on stderr naming the file and the problem).

One module per command (:mod:`~napari_imgreg.cli.render`, ``register``,
``demo``, ``project``, ``measure``, ``orient``, ``batch``, ``sample``), each
with ``add_parser(subparsers)``, which sets the command's handler
``run(args) -> int`` as ``func``; what they share (exit codes, the error
line, atomic output files, ``--params``) is in :mod:`napari_imgreg.cli._common`.
:func:`main` builds the parser from the modules and turns bad input into
exit code 2. The command line is Qt-free but for ``demo --gui``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys

from .. import __version__
from .._allocator import tune_allocator
from .._atomic import OutputError
from .._deprecated import forward_moved_names
from .._platform import tolerant_console
from . import (
    batch,
    demo,
    measure,
    orient,
    project,
    register,
    render,
    sample,
    workspace,
)
from ._common import (
    EXIT_BAD_INPUT,
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    Terminated,
    one_line,
    print_error,
    sigterm_as_interrupt,
)
from ..errors import InputError
from ..validate import FieldValueError

__all__ = ["main"]

#: The command modules, in the order ``napari-imgreg --help`` lists them.
COMMANDS = (render, register, demo, project, measure, orient, batch, sample, workspace)


def build_parser() -> argparse.ArgumentParser:
    """The ``napari-imgreg`` parser with every command of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="napari-imgreg",
        description="Register field photographs to textured 3D outcrop models.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    # Output redirected on Windows is in the ANSI code page: a "σ" in a help
    # text or a photo's name in a summary must not end the command.
    with tolerant_console():
        return _run(argv)


def _run(argv: list[str] | None) -> int:
    """:func:`main` once the console prints any text."""
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        # argparse reports these from the top parser, with its usage; the
        # command's own usage is the one that helps.
        _parser_of_command(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    tune_allocator()  # image buffers reused, not re-faulted (see _allocator)
    # A reader that closed our stdout (``| head``) must not turn a command
    # that did its work into a traceback: its lines are dropped instead.
    sys.stdout = _QuietWhenClosed(sys.stdout)
    try:
        # Not around a GUI (demo --gui): in Qt's event loop a Python handler runs
        # only when Python code does, so `kill` would no longer end the window.
        with contextlib.nullcontext() if getattr(args, "gui", False) else sigterm_as_interrupt():
            return int(args.func(args) or 0)
    except (InputError, FieldValueError) as exc:
        # FieldValueError: a value checked where no file is known (an API
        # object built from an option); still bad input, still one line.
        print_error(_command_name(args), exc)
        return EXIT_BAD_INPUT
    except OutputError as exc:  # its message names the output already
        print_error(_command_name(args), exc)
        return EXIT_BAD_INPUT
    except OSError as exc:
        # A file the system refused (no permission, a folder in the way)
        # outside the atomic writers. Without a file name (a broken pipe)
        # there is no file to name: a traceback is the only useful report.
        where = exc.filename2 if exc.filename2 is not None else exc.filename
        if where is None:
            raise
        print_error(_command_name(args), f"{os.fsdecode(where)}: "
                                         f"{exc.strerror or one_line(exc)}")
        return EXIT_BAD_INPUT
    except Terminated:
        print("terminated (SIGTERM)", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if isinstance(sys.stdout, _QuietWhenClosed):
            sys.stdout = sys.stdout.stream


def _parser_of_command(parser: argparse.ArgumentParser,
                       args: argparse.Namespace) -> argparse.ArgumentParser:
    """The innermost sub-parser of the command as typed (``workspace add``'s)."""
    while True:
        subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        chosen = getattr(args, subparsers[0].dest, None) if subparsers else None
        if chosen not in (subparsers[0].choices if subparsers else {}):
            return parser
        parser = subparsers[0].choices[chosen]


def _command_name(args: argparse.Namespace) -> str:
    """The command as typed, with its action: ``workspace add``, ``render``."""
    action = getattr(args, "action", None)
    return f"{args.command} {action}" if action else args.command


class _QuietWhenClosed:
    """A text stream whose writes are dropped once the reader has gone."""

    def __init__(self, stream):
        self.stream, self.closed_by_reader = stream, False

    def write(self, text: str) -> int:
        if not self.closed_by_reader:
            try:
                return self.stream.write(text)
            except (BrokenPipeError, ValueError):  # ValueError: stream closed
                self.closed_by_reader = True
        return len(text)

    def flush(self) -> None:
        if not self.closed_by_reader:
            try:
                self.stream.flush()
            except (BrokenPipeError, ValueError):
                self.closed_by_reader = True

    def __getattr__(self, name: str):
        return getattr(self.stream, name)


#: Names of napari-imgreg 0.1's ``cli`` module -> (module, name) of their new home.
_MOVED = {
    "cmd_render": "napari_imgreg.cli.render:run",
    "cmd_register": "napari_imgreg.cli.register:run",
    "cmd_demo": "napari_imgreg.cli.demo:run",
    "cmd_sample": "napari_imgreg.cli.sample:run",
    "_demo_gui": "napari_imgreg.cli.demo:open_gui",
    "_scene": "napari_imgreg.cli._common:load_scene",
    "EXIT_OK": "napari_imgreg.cli._common:EXIT_OK",
    "EXIT_FAILED": "napari_imgreg.cli._common:EXIT_FAILED",
}
__getattr__ = forward_moved_names(__name__, _MOVED)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
