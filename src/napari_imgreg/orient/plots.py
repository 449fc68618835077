"""Residual plots of an orientation: Δξ and Δρ against survey path and measured trend.

Drawn with matplotlib (imported when a plot is made) into a given figure, for
the widget's dock, or written as a PNG beside ORIENTATION.json.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._atomic import atomic_path
from .diagnostics import PATH_SLOPE_MAX, TREND_SLOPE_MAX

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from .result import OrientationResult

__all__ = ["draw_residual_plots", "save_residual_plots"]

def draw_residual_plots(
    figure: Figure, result: OrientationResult, vertical: bool = False
) -> Figure:
    """Draw Δξ and Δρ against path position and against measured trend.

    Photos the chosen estimator set aside are drawn as crosses and left out
    of the fitted lines (as in the flags).

    Parameters
    ----------
    figure : matplotlib.figure.Figure
        Cleared and drawn into.
    result : OrientationResult
    vertical : bool
        Stack the two panels (for a narrow dock) instead of side by side.

    Returns
    -------
    Figure
    """
    from matplotlib.ticker import FuncFormatter

    figure.clear()
    panels = figure.subplots(2, 1) if vertical else figure.subplots(1, 2, sharey=True)
    set_aside = ~result.used
    untested = {flag.key for flag in result.flags if flag.status == "n/a"}
    series = (
        ("Δξ", result.delta_xi_deg, "tab:blue", "o", "delta_xi"),
        ("Δρ", result.delta_rho_deg, "tab:orange", "s", "delta_rho"),
    )
    for ax, x, key, xlabel, title, slope_fmt in (
        (panels[0], result.path_position, "path", "position along the survey path (0 to 1)",
         f"doming if |slope| ≥ {PATH_SLOPE_MAX:g}", "{:+.1f}"),
        (panels[1], result.measured_trend_deg, "trend", "measured trend of ξ (°)",
         f"compass off if |slope| > {TREND_SLOPE_MAX:g}", "{:+.2f}"),
    ):
        if f"slope_vs_{key}" in untested:
            # Too few photos, too narrow a fan, or steep views: the flag's reading says which.
            title += " — not testable here (n/a)"
        for name, y, color, marker, prefix in series:
            fit = result.fits[f"{prefix}_vs_{key}"]
            label = name
            if fit is not None:
                label += f": slope {slope_fmt.format(fit.slope)}, R² {fit.r2:.2f}"
            ax.scatter(
                x[~set_aside], y[~set_aside], s=12, color=color, marker=marker, label=label,
                alpha=0.75,
            )
            if set_aside.any():
                ax.scatter(x[set_aside], y[set_aside], s=28, color=color, marker="x")
            if fit is not None:
                xs = np.array([x.min(), x.max()])
                ax.plot(xs, fit.slope * xs + fit.intercept, color=color, lw=1.2)
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel("residual (°)", fontsize=8)
        ax.set_title(title, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6.5, loc="best", framealpha=0.7)
        ax.grid(alpha=0.3)
    # Trends are unwrapped about their mean for the fit; label them as compass readings.
    panels[1].xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v % 360:.0f}"))
    figure.tight_layout()
    return figure


def save_residual_plots(
    result: OrientationResult, folder: str | os.PathLike, dpi: int = 120
) -> Path:
    """Write ``orientation_residuals.png`` (Δξ, Δρ vs path and trend) into a folder."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(10, 4))
    FigureCanvasAgg(figure)
    draw_residual_plots(figure, result)
    out = Path(folder) / "orientation_residuals.png"
    with atomic_path(out) as tmp:
        figure.savefig(tmp, dpi=dpi, format="png")
    return out
