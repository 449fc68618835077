"""Keyboard shortcuts of the workbench, bound as napari viewer keybindings.

They act while the canvas has the keyboard focus (click the canvas first),
as napari's own do. None of them is one of napari's defaults — the viewer's,
the application's menus, or any layer's (drawing tools included) —
``tests/widgets/test_workbench_workspace.py`` checks that against the napari
installed. The nudges move by the step chosen in the Pose tab.

=========================  ==============================
action                     keys
=========================  ==============================
turn left / right (trend)  Shift+Left / Shift+Right
look up / down (plunge)    Ctrl+Shift+Up / Ctrl+Shift+Down
roll left / right          Ctrl+Shift+Left / Ctrl+Shift+Right
move forward / back        Ctrl+Shift+W / Ctrl+Shift+S
step left / right          Ctrl+Shift+A / Ctrl+Shift+D
move up / down             Ctrl+Shift+R / Ctrl+Shift+F
Run (one trial)            Shift+R
Auto (adapted trials)      Shift+T
accept the pose            Shift+Enter
next / previous photo      PageDown / PageUp
next needing attention     N
undo / redo (pose)         Shift+Z / Shift+Y
=========================  ==============================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    import napari

    from .workbench import Workbench

__all__ = ["Shortcut", "SHORTCUTS", "key_of", "install", "uninstall", "help_text"]


@dataclass(frozen=True)
class Shortcut:
    """One keybinding: its name, napari key string, what it does, and the
    action (called with the workbench)."""

    name: str
    key: str
    text: str
    action: Callable[[Workbench], None]


def _nudge(key: str, **unit: float) -> Callable[[Workbench], None]:
    return lambda wb: wb.pose_panel.nudge(key, **unit)


#: Every shortcut, in the order of the help text.
SHORTCUTS: tuple[Shortcut, ...] = (
    Shortcut("turn left", "Shift+Left", "turn left", _nudge("turn left", d_trend=-1)),
    Shortcut("turn right", "Shift+Right", "turn right", _nudge("turn right", d_trend=1)),
    Shortcut("look up", "Ctrl+Shift+Up", "look up", _nudge("look up", d_plunge=-1)),
    Shortcut("look down", "Ctrl+Shift+Down", "look down", _nudge("look down", d_plunge=1)),
    Shortcut("roll left", "Ctrl+Shift+Left", "roll left", _nudge("roll left", d_roll=-1)),
    Shortcut("roll right", "Ctrl+Shift+Right", "roll right", _nudge("roll right", d_roll=1)),
    Shortcut("forward", "Ctrl+Shift+W", "move forward", _nudge("forward", forward=1)),
    Shortcut("back", "Ctrl+Shift+S", "move back", _nudge("back", forward=-1)),
    Shortcut("left", "Ctrl+Shift+A", "step left", _nudge("left", right=-1)),
    Shortcut("right", "Ctrl+Shift+D", "step right", _nudge("right", right=1)),
    Shortcut("up", "Ctrl+Shift+R", "move up", _nudge("up", up=1)),
    Shortcut("down", "Ctrl+Shift+F", "move down", _nudge("down", up=-1)),
    Shortcut("run", "Shift+R", "Run (one trial)",
             lambda wb: wb.controller.run_registration(auto=False)),
    Shortcut("auto", "Shift+T", "Auto (adapted trials)",
             lambda wb: wb.controller.run_registration(auto=True)),
    Shortcut("accept", "Shift+Enter", "accept the pose, go to the next needing attention",
             lambda wb: wb.controller.accept()),
    Shortcut("next", "PageDown", "next photo", lambda wb: wb.controller.select_next(1)),
    Shortcut("previous", "PageUp", "previous photo", lambda wb: wb.controller.select_next(-1)),
    Shortcut("attention", "N", "next photo needing attention",
             lambda wb: wb.controller.next_needing_attention()),
    Shortcut("undo", "Shift+Z", "undo the last pose edit", lambda wb: wb.controller.undo()),
    Shortcut("redo", "Shift+Y", "redo", lambda wb: wb.controller.redo()),
)

_BY_NAME = {s.name: s for s in SHORTCUTS}
#: The shortcuts that move the current camera (nudges, undo, redo).
_POSE_EDITS = {s.name for s in SHORTCUTS if s.name not in (
    "run", "auto", "accept", "next", "previous", "attention")}


def _drawing(viewer) -> bool:
    """The active layer is a photo's drawings (its keys are the drawing's)."""
    from ._layers import INTERPRETATION_OF

    layer = viewer.layers.selection.active
    return layer is not None and INTERPRETATION_OF in getattr(layer, "metadata", {})


def key_of(name: str) -> str:
    """The key of a shortcut, as shown to the user ("Shift+Left")."""
    return _BY_NAME[name].key


def help_text(names: tuple[str, ...] | None = None, sep: str = " · ") -> str:
    """A one-line list "key: action" of the shortcuts (all, or those named)."""
    chosen = SHORTCUTS if names is None else tuple(_BY_NAME[n] for n in names)
    return sep.join(f"{s.key}: {s.text}" for s in chosen)


def install(viewer: napari.viewer.Viewer, workbench: Workbench) -> list[str]:
    """Bind every shortcut on the viewer for ``workbench``.

    A key some other code has bound on this viewer already is left to it
    (napari's ``overwrite=False``) and returned, so that nothing of the
    user's or another plugin's is taken away.

    Returns
    -------
    list of str
        The keys that could not be bound.
    """
    taken = []
    for shortcut in SHORTCUTS:
        def press(_viewer, shortcut=shortcut):
            if workbench.controller.closed:
                return
            if shortcut.name in _POSE_EDITS and _drawing(viewer):
                # Shift+Z while drawing is a drawing undo to the hand, not a
                # registration undone under the lines (the camera moved metres).
                from napari.utils.notifications import show_info

                message = (f"{shortcut.key} ({shortcut.text}) moves the camera: not applied "
                           "while a drawing layer is selected (select the photo layer first)")
                workbench.controller.status.emit(message)
                show_info(message)
                return
            shortcut.action(workbench)

        press.__doc__ = f"napari-imgreg: {shortcut.text}"
        try:
            viewer.bind_key(shortcut.key, press, overwrite=False)
        except ValueError:  # bound already on this viewer
            taken.append(shortcut.key)
    return taken


def uninstall(viewer: napari.viewer.Viewer) -> None:
    """Remove the workbench's shortcuts from the viewer (the workbench was closed)."""
    for shortcut in SHORTCUTS:
        bound = viewer.keymap.get(_key(shortcut.key))
        if bound is not None and (bound.__doc__ or "").startswith("napari-imgreg:"):
            viewer.bind_key(shortcut.key, None)


def _key(key: str):
    from napari.utils.key_bindings import coerce_keybinding

    return coerce_keybinding(key)
