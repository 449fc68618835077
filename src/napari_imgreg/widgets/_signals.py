"""Workspace signals followed by a widget for as long as the widget lives."""

from __future__ import annotations

from typing import Callable, Iterable

__all__ = ["follow_while_alive"]


def follow_while_alive(widget, followed: Iterable[tuple[object, Callable]]) -> None:
    """Connect each ``(signal, handler)`` now and disconnect them when
    ``widget`` is destroyed: the Qt-free workspace may outlive its widgets (a
    script's), and would otherwise call handlers of deleted widgets.

    Parameters
    ----------
    widget : QObject
    followed : iterable of (psygnal signal, callable)
    """
    followed = list(followed)
    for signal, handler in followed:
        signal.connect(handler)

    def release(*_args) -> None:  # not a method of the widget: Qt drops those first
        for signal, handler in followed:
            signal.disconnect(handler)

    widget.destroyed.connect(release)
