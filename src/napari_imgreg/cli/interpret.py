"""Forwarding module: ``project`` and ``measure`` now live in
:mod:`napari_imgreg.cli.project` and :mod:`napari_imgreg.cli.measure`.

Kept for :func:`add_parsers` (registers both commands, as
``napari_imgreg.cli_interpret`` did in 0.1) and for the 0.1 handler names
``cmd_project`` / ``cmd_measure``, which warn and forward to the ``run`` of
the new modules.
"""

from __future__ import annotations

import argparse

from .._deprecated import forward_moved_names
from . import measure, project

__all__ = ["add_parsers"]

#: 0.1 name -> (module, name) of its new home.
_MOVED = {
    "cmd_project": "napari_imgreg.cli.project:run",
    "cmd_measure": "napari_imgreg.cli.measure:run",
    "_load_scene": "napari_imgreg.cli.project:_load_surface",
}
__getattr__ = forward_moved_names(__name__, _MOVED)


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register the ``project`` and ``measure`` sub-commands."""
    project.add_parser(subparsers)
    measure.add_parser(subparsers)


