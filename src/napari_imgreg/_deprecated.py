"""Old module paths of napari-imgreg, kept importable with a DeprecationWarning.

Version 0.2 moved the flat modules into packages by stage (``registration/``,
``interpret/``, ``orient/``, ``cli/``) and split a few mixed modules
(``sun`` into ``solar``, ``io.exif`` and ``registration.stages.relight``;
the prior out of ``io.records``). A script written against 0.1 keeps working:
``import napari_imgreg.pipeline`` returns ``napari_imgreg.registration.pipeline``
and warns once where it was imported. An old module that was split becomes a
read-only view whose names are looked up in each of its new homes.

The table :data:`OLD_MODULES` is the whole deprecation path; remove an entry
one minor release after its warning first shipped.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import types
import warnings
from typing import Any, Callable

#: old module (under ``napari_imgreg.``) -> its new home(s), first match wins.
OLD_MODULES: dict[str, tuple[str, ...]] = {
    "params": ("registration.params",),
    "filters": ("registration.filters",),
    "features": ("registration.features",),
    "pose": ("registration.pose",),
    "quality": ("registration.quality",),
    "pipeline": ("registration.pipeline",),
    "manual": ("registration.manual",),
    "area": ("registration.stages.area",),
    "edges": ("registration.stages.edges",),
    "dense": ("registration.stages.dense",),
    "interpret": ("interpret.project",),
    "structural": ("interpret.structural",),
    "io.interpretations": ("interpret.files",),
    "cli_batch": ("cli.batch",),
    # cli.interpret forwards add_parsers and the cmd_* names (with a warning).
    "cli_interpret": ("cli.interpret", "cli.project", "cli.measure"),
    "cli_orient": ("cli.orient",),
    "_layers": ("widgets._layers",),
    "sun": ("solar", "io.exif", "registration.stages.relight"),
}

_PREFIX = "napari_imgreg."
_MISSING = object()


class _MergedModule(types.ModuleType):
    """An old module split in several: attribute look-ups go to the new homes."""

    def __init__(self, name: str, homes: tuple[str, ...]):
        super().__init__(name)
        self.__homes = homes

    def __getattr__(self, attr: str):
        if attr.startswith("__"):
            raise AttributeError(attr)
        for home in self.__homes:
            module = importlib.import_module(_PREFIX + home)
            # One look-up: a home that forwards the name itself warns once.
            value = getattr(module, attr, _MISSING)
            if value is not _MISSING:
                return value
        raise AttributeError(f"module {self.__name__!r} has no attribute {attr!r}")


class _OldPathLoader(importlib.abc.Loader):
    def __init__(self, old: str, homes: tuple[str, ...]):
        self.old, self.homes = old, homes

    def create_module(self, spec):
        new = ", ".join(_PREFIX + h for h in self.homes)
        warnings.warn(
            f"{_PREFIX}{self.old} moved to {new} in napari-imgreg 0.2; "
            "the old path will be removed in a later release",
            DeprecationWarning,
            stacklevel=6,
        )
        if len(self.homes) == 1:
            return importlib.import_module(_PREFIX + self.homes[0])
        return _MergedModule(_PREFIX + self.old, self.homes)

    def exec_module(self, module) -> None:  # the new home is already executed
        pass


class _OldPathFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        if not fullname.startswith(_PREFIX):
            return None
        old = fullname[len(_PREFIX):]
        homes = OLD_MODULES.get(old)
        if homes is None:
            return None
        return importlib.util.spec_from_loader(fullname, _OldPathLoader(old, homes))


def install() -> None:
    """Put the old-path finder on ``sys.meta_path`` (idempotent)."""
    if not any(isinstance(f, _OldPathFinder) for f in sys.meta_path):
        sys.meta_path.append(_OldPathFinder())


def forward_moved_names(module: str, moved: dict[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` (PEP 562) for names that moved in 0.2.

    Parameters
    ----------
    module : str
        The old module's ``__name__``.
    moved : dict
        Old name -> ``"napari_imgreg.new.module"`` or, for a renamed object,
        ``"napari_imgreg.new.module:new_name"``.

    Returns
    -------
    callable
        Assign it to the old module's ``__getattr__``: it looks the name up
        in its new home (by an import *string*, so the layer contracts see no
        upward import) and warns once per access with a DeprecationWarning.
    """

    def __getattr__(name: str) -> Any:
        target = moved.get(name)
        if target is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        home, _, new_name = target.partition(":")
        new_name = new_name or name
        warnings.warn(
            f"{module}.{name} moved to {home}.{new_name} in napari-imgreg 0.2; "
            "the old name will be removed in a later release",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module(home), new_name)

    return __getattr__
