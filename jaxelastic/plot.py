"""Small matplotlib helpers for the notebooks and reports.

Matplotlib is imported lazily inside the functions, and nothing here touches pyplot's
global state: pass an ``Axes`` (e.g. from ``plt.subplots()``) or let a function create a
standalone :class:`matplotlib.figure.Figure`.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

__all__ = ["new_axes", "stress_stretch"]


def new_axes(ncols: int = 1, *, figsize=(6.0, 4.0)):
    """A standalone ``Figure`` (not registered with pyplot) and its ``ncols`` axes.

    Returns:
        ``(fig, axes)``; ``axes`` is a single ``Axes`` when ``ncols == 1``, else an array.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(1, ncols, squeeze=True)
    return fig, axes


def stress_stretch(
    ax,
    stretch,
    curves: Mapping[str, object],
    *,
    reference: Mapping[str, tuple] | None = None,
    styles: Mapping[str, Mapping] | None = None,
    ylim=None,
    xlabel: str = "stretch $a = \\ell/L$",
    ylabel: str = "nominal stress $P_{11}$",
    title: str | None = None,
):
    """Draw one curve per model against the stretch, with optional reference points.

    Non-finite values are drawn as gaps (mask a branch with NaN to leave it out).

    Args:
        ax: a matplotlib ``Axes``.
        stretch: ``(n,)`` abscissa.
        curves: label → ``(n,)`` values, drawn as lines in insertion order.
        reference: label → ``(x, y)`` drawn as markers only (e.g. a closed form).
        styles: label → extra keyword arguments for that line (``ls``, ``color``, ...).
        ylim: optional ``(ymin, ymax)``.

    Returns:
        ``ax``.
    """
    x = np.asarray(stretch, dtype=float)
    styles = dict(styles or {})
    for label, y in curves.items():
        y = np.asarray(y, dtype=float)
        y = np.where(np.isfinite(y), y, np.nan)
        kw = dict(lw=1.6)
        kw.update(styles.get(label, {}))
        ax.plot(x, y, label=label, **kw)
    for label, (xr, yr) in (reference or {}).items():
        kw = dict(ls="none", marker="o", ms=4, mfc="none", color="k", zorder=5)
        kw.update(styles.get(label, {}))
        ax.plot(np.asarray(xr, dtype=float), np.asarray(yr, dtype=float), label=label, **kw)
    ax.axhline(0.0, color="0.6", lw=0.8, zorder=0)
    ax.axvline(1.0, color="0.6", lw=0.8, ls=":", zorder=0)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    return ax
