"""What every ``napari-imgreg`` command shares: exit codes, the error line,
atomic output files, ``--params`` and scene loading.

Exit codes (contract §8): :data:`EXIT_OK` (0) success, :data:`EXIT_FAILED` (1)
a registration that failed its quality bar, :data:`EXIT_BAD_INPUT` (2) bad
input, reported as one line on stderr naming the file and the problem;
:data:`EXIT_INTERRUPTED` (130) after Ctrl-C, as a shell reports SIGINT;
:data:`EXIT_TERMINATED` (143) after SIGTERM (a job scheduler's time limit,
``kill``), which every command handles as it does Ctrl-C
(:func:`sigterm_as_interrupt`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from .._atomic import atomic_path, atomic_write
from .._json import dumps as strict_dumps
from ..errors import input_error
from ..scene import Scene

if TYPE_CHECKING:  # the commands import their backend when run: a fast --help
    from ..registration.params import RegistrationParams

__all__ = [
    "EXIT_OK",
    "EXIT_FAILED",
    "EXIT_BAD_INPUT",
    "EXIT_INTERRUPTED",
    "EXIT_TERMINATED",
    "Terminated",
    "sigterm_as_interrupt",
    "one_line",
    "print_error",
    "write_json",
    "say",
    "silence_stdout",
    "write_npy",
    "read_params",
    "load_scene",
    "progress_printer",
    "same_file",
    "refuse_overwriting_inputs",
]

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2
EXIT_INTERRUPTED = 130
#: Exit code after SIGTERM, as a shell reports it (128 + 15).
EXIT_TERMINATED = 143


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the command is, so it unwinds as Ctrl-C does."""


def _raise_terminated(signum, frame) -> None:  # noqa: ARG001 - a signal handler's signature
    raise Terminated()


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM into :class:`Terminated` while the block runs.

    Without it SIGTERM ends the process where it stands: no ``finally`` runs,
    so a workspace keeps its ``workspace.lock``, a local Dask cluster's
    workers are left to die on their own (and multiprocessing warns of
    leaked semaphores) and the command says nothing. Unwinding as Ctrl-C
    does closes all of that and keeps whatever was saved. Outside the main
    thread (an application embedding a command) its own handler stays.
    """
    try:
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def one_line(exc: BaseException) -> str:
    """The message of ``exc`` with its whitespace runs (newlines too) made single
    spaces; the exception's type name when it has no message."""
    return " ".join(str(exc).split()) or type(exc).__name__


def print_error(command: str, message: object) -> None:
    """Print ``napari-imgreg COMMAND: error: MESSAGE`` on stderr."""
    print(f"napari-imgreg {command}: error: {message}", file=sys.stderr, flush=True)


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as indented, strict JSON, atomically and durably: an
    interrupted write leaves the old file (or none), never half a file.

    Non-finite numbers are written as ``null`` with the reason under the
    top-level ``null_reasons`` (see :func:`napari_imgreg._json.strict_json`):
    never ``NaN``/``Infinity``, which other tools cannot parse.
    """
    text = strict_dumps(data, indent=2) + "\n"  # serialised first: a bad value writes nothing
    # json escapes non-ASCII, so the bytes do not depend on the encoding.
    with atomic_write(path, encoding="utf-8") as fh:
        fh.write(text)


def say(*parts: object, **kwargs: Any) -> None:
    """``print`` for a command's human summary that survives a closed stdout.

    The outputs are files; stdout only tells a person about them. When stdout
    is a pipe whose reader has gone (``| head``) or a closed descriptor, the
    rest of the summary is dropped (stdout is pointed at the null device, so
    the interpreter's exit flush does not fail either) and the command goes on
    and exits with its own code.
    """
    kwargs.setdefault("flush", True)
    try:
        print(*parts, **kwargs)
    except (BrokenPipeError, ValueError, OSError):
        silence_stdout()


def silence_stdout() -> None:
    """Point stdout at the null device (after a broken pipe or closed stdout)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        # No usable descriptor at all: replace the object instead.
        sys.stdout = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115 - lives as long as the process


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write ``array`` as a NumPy ``.npy`` file, atomically."""
    # Through an open file: given a name, np.save appends ".npy" to any name
    # not ending in it exactly (``D.NPY``), and would write a stray file.
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, array)


def read_params(path: str | os.PathLike | None, scene: Scene | None = None) -> RegistrationParams:
    """The registration parameters of a ``--params`` JSON file (any subset of
    the fields), or the defaults when no file was given: those for the
    ``scene`` when given (a point cloud's, :meth:`RegistrationParams.for_scene`)."""
    from ..registration.params import RegistrationParams, load_params

    base = RegistrationParams.for_scene(scene)
    return load_params(path, base) if path else base


def load_scene(
    mesh: str | os.PathLike,
    georef: str | os.PathLike | None = None,
    dem: str | os.PathLike | None = None,
) -> Scene:
    """The mesh with its georeference and DEM (see :meth:`Scene.load`)."""
    return Scene.load(mesh, georef=georef, dem=dem)


def progress_printer(verbose: bool, indent: str) -> Callable[[Any], None]:
    """An ``on_progress`` callback for :func:`~napari_imgreg.registration.pipeline.register`
    that prints ``[ 40%] message`` lines, indented by ``indent``, when ``verbose``."""

    def show(progress) -> None:
        if verbose and progress.message:
            print(f"{indent}[{progress.fraction:4.0%}] {progress.message}", flush=True)

    return show


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when ``a`` and ``b`` name one file: :func:`os.path.samefile` where
    both exist (a link, another spelling of the path), else equal resolved paths."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return Path(a).resolve() == Path(b).resolve()


def refuse_overwriting_inputs(
    output: str | os.PathLike | None,
    inputs: Iterable[tuple[str, str | os.PathLike | None]],
) -> None:
    """Refuse, before any work, an output that is one of the command's inputs.

    Parameters
    ----------
    output : path-like or None
        A file the command writes (None: not asked for, nothing to check).
    inputs : iterable of (str, path-like or None)
        What each input is (``"lines"``, ``"sensor record"``) and its path
        (None: not given).

    Raises
    ------
    InputError
        ``"<output>: refusing to overwrite the input <what>; choose another name"``.
    """
    if not output:
        return
    for what, path in inputs:
        if path and same_file(output, path):
            raise input_error(output, f"refusing to overwrite the input {what}; "
                                      "choose another name")
