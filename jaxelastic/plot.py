"""Small matplotlib helpers for the notebooks and reports.

Matplotlib is imported lazily inside the functions, and nothing here touches pyplot's
global state: pass an ``Axes`` (e.g. from ``plt.subplots()``) or let a function create a
standalone :class:`matplotlib.figure.Figure`.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

__all__ = [
    "new_axes",
    "stress_stretch",
    "feature_edges",
    "wire_edges",
    "view_axes",
    "shapes",
    "shapes_3d",
    "final_shape_figure",
    "tip_displacement_figure",
    "energy_figure",
]


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


# ----------------------------------------------------------------------------------------
# deformed shapes and time histories (used by `jaxelastic run`)
# ----------------------------------------------------------------------------------------

_AXIS_NAMES = "xyz"


def _unique_edges(tris: np.ndarray):
    """Unique sorted edges of triangles ``(f, 3)``: ``(edges, inverse, counts, tri_of)``."""
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    tri_of = np.tile(np.arange(len(tris)), 3)
    keys = np.sort(e, axis=1)
    uniq, inv, cnt = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return uniq, inv.ravel(), cnt, tri_of


def feature_edges(mesh, angle_deg: float = 30.0) -> np.ndarray:
    """Outline edges ``(m, 2)`` of a mesh at rest: the boundary edges in 2D; in 3D the edges
    between boundary triangles whose normals differ by more than ``angle_deg`` (the
    edges of a box) and open edges."""
    facets = _linear_facets(mesh)
    if mesh.dim == 2:
        return np.asarray(facets)
    X = np.asarray(mesh.points)
    P = X[facets]
    N = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    uniq, inv, cnt, tri_of = _unique_edges(np.asarray(facets))
    order = np.argsort(inv, kind="stable")
    starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    a = tri_of[order[starts]]
    b = tri_of[order[np.minimum(starts + 1, len(order) - 1)]]
    cos = np.sum(N[a] * N[b], axis=1)
    return uniq[(cnt != 2) | (cos < np.cos(np.radians(angle_deg)))]


def wire_edges(mesh) -> np.ndarray:
    """Edges ``(m, 2)`` for a light wireframe: all cell edges in 2D, boundary-triangle
    edges in 3D."""
    from .mesh import linear_cells

    tris = linear_cells(mesh) if mesh.dim == 2 else _linear_facets(mesh)
    return _unique_edges(tris)[0]


def _linear_facets(mesh) -> np.ndarray:
    """Boundary facets as linear pieces ``(m, dim)``: P2/composite facets are split at their
    mid-edge nodes (an edge into 2 segments, a 6-node triangle into 4), so the drawing
    passes through every boundary node (curved P2 edges appear as polylines)."""
    from .mesh import boundary_facets
    from .mesh.elements import TRI3X4

    f = np.asarray(boundary_facets(mesh))
    if f.shape[1] == mesh.dim:
        return f
    if mesh.dim == 2:
        return np.concatenate([f[:, [0, 2]], f[:, [2, 1]]])
    return f[:, np.asarray(TRI3X4.sub_cells)].reshape(-1, 3)


def view_axes(rest, deformed=()) -> tuple[int, int]:
    """Projection axes ``(horizontal, vertical)`` for a side view of a 3D body: the longest
    rest extent horizontally, and of the others the one with the largest displacement."""
    rest = np.asarray(rest)
    if rest.shape[1] == 2:
        return 0, 1
    ext = np.ptp(rest, axis=0)
    i = int(np.argmax(ext))
    others = [a for a in range(3) if a != i]
    disp = np.zeros(3)
    for x in deformed:
        disp = np.maximum(disp, np.abs(np.asarray(x) - rest).max(axis=0))
    if disp[others].max() > 0:
        j = others[int(np.argmax(disp[others]))]
    else:
        j = others[int(np.argmax(ext[others]))]
    return i, j


_SHAPE_STYLES = (
    dict(color="0.55", lw=0.9, ls=":"),
    dict(color="C0", lw=1.6, ls="-"),
    dict(color="C3", lw=1.4, ls="--"),
    dict(color="C2", lw=1.4, ls="-."),
)


def shapes(ax, mesh, configurations, *, axes=None, wire: bool = True):
    """Draw the outline of ``mesh`` in several configurations (a side view in 3D).

    Args:
        ax: a matplotlib ``Axes``.
        mesh: the rest mesh.
        configurations: label → ``(n_nodes, dim)`` positions, drawn in order with the
            styles rest (grey dotted), then blue solid, red dashed, green dash-dotted.
            The first configuration is taken as the rest shape for the view.
        axes: projection ``(horizontal, vertical)`` (default :func:`view_axes`).
        wire: also draw a light wireframe of the second configuration.

    Returns:
        ``ax``.
    """
    from matplotlib.collections import LineCollection

    configs = {k: np.asarray(v, dtype=float) for k, v in configurations.items()}
    labels = list(configs)
    rest = configs[labels[0]]
    i, j = axes if axes is not None else view_axes(rest, [configs[k] for k in labels[1:]])
    feat = feature_edges(mesh)
    if wire and len(labels) > 1:
        xw = configs[labels[1]][:, [i, j]]
        ax.add_collection(
            LineCollection(list(xw[wire_edges(mesh)]), colors="C0", linewidths=0.3, alpha=0.35)
        )
    for k, label in enumerate(labels):
        st = dict(_SHAPE_STYLES[min(k, len(_SHAPE_STYLES) - 1)])
        xy = configs[label][:, [i, j]]
        ax.add_collection(
            LineCollection(
                list(xy[feat]),
                colors=st["color"],
                linewidths=st["lw"],
                linestyles=st["ls"],
                label=label,
            )
        )
    allxy = np.concatenate([c[:, [i, j]] for c in configs.values()])
    lo, hi = allxy.min(axis=0), allxy.max(axis=0)
    pad = 0.04 * max(float((hi - lo).max()), 1e-12)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel(f"{_AXIS_NAMES[i]} [m]")
    ax.set_ylabel(f"{_AXIS_NAMES[j]} [m]")
    ax.legend(loc="best", fontsize="small")
    ax.grid(alpha=0.25)
    return ax


def shapes_3d(ax, mesh, configurations, *, wire: bool = True):
    """Like :func:`shapes` on a matplotlib 3D ``Axes`` (``projection="3d"``)."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    configs = {k: np.asarray(v, dtype=float) for k, v in configurations.items()}
    labels = list(configs)
    feat = feature_edges(mesh)
    if wire and len(labels) > 1:
        xw = configs[labels[1]]
        ax.add_collection3d(
            Line3DCollection(xw[wire_edges(mesh)], colors="C0", linewidths=0.3, alpha=0.3)
        )
    for k, label in enumerate(labels):
        st = dict(_SHAPE_STYLES[min(k, len(_SHAPE_STYLES) - 1)])
        ax.add_collection3d(
            Line3DCollection(
                configs[label][feat],
                colors=st["color"],
                linewidths=st["lw"],
                linestyles=st["ls"],
                label=label,
            )
        )
    allx = np.concatenate(list(configs.values()))
    lo, hi = allx.min(axis=0), allx.max(axis=0)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(np.maximum(hi - lo, 1e-3 * (hi - lo).max()))
    ax.view_init(elev=22, azim=-55)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend(loc="upper left", fontsize="small")
    return ax


def final_shape_figure(mesh, configurations, *, title: str | None = None):
    """A standalone figure of the rest and deformed configurations (rest first).

    2D: the outlines in the plane. 3D: a side view (:func:`shapes`) for an elongated body
    (longest rest extent ≥ 2× the others, e.g. a beam), else a perspective view
    (:func:`shapes_3d`).
    """
    confs = list(configurations.values())
    rest = np.asarray(confs[0])
    ext_rest = np.ptp(rest, axis=0)
    srt = np.sort(ext_rest)[::-1]
    if mesh.dim == 3 and srt[0] < 2.0 * srt[1]:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(7.0, 6.0), layout="constrained")
        ax = fig.add_subplot(projection="3d")
        shapes_3d(ax, mesh, configurations)
        if title:
            ax.set_title(title, fontsize="medium")
        return fig
    i, j = view_axes(rest, confs[1:])
    ext = np.ptp(np.concatenate([np.asarray(c) for c in confs]), axis=0)
    aspect = float(ext[j] / max(ext[i], 1e-12))
    fig, ax = new_axes(figsize=(7.5, float(np.clip(7.0 * aspect + 1.2, 2.8, 7.0))))
    shapes(ax, mesh, configurations, axes=(i, j))
    if title:
        view = "" if mesh.dim == 2 else f" (side view, {_AXIS_NAMES[i]}-{_AXIS_NAMES[j]} plane)"
        ax.set_title(title + view, fontsize="medium")
    return fig


def tip_displacement_figure(t, u, *, static=None, title: str | None = None):
    """Displacement components of one node over time, with the static values dashed.

    Args:
        t: ``(n,)`` times [s]; u: ``(n, dim)`` displacements [m]; static: ``(dim,)`` or None.
    """
    t = np.asarray(t, dtype=float)
    u = np.asarray(u, dtype=float)
    fig, ax = new_axes(figsize=(7.5, 4.0))
    shown = [
        a
        for a in range(u.shape[1])
        if np.abs(u[:, a]).max() > 0 or (static is not None and static[a] != 0)
    ]
    for a in shown:
        ax.plot(t, u[:, a], color=f"C{a}", lw=1.5, label=f"$u_{_AXIS_NAMES[a]}$")
    if static is not None:
        for a in shown:
            ax.axhline(
                static[a], color=f"C{a}", lw=1.0, ls="--", label=f"static $u_{_AXIS_NAMES[a]}$"
            )
    ax.axhline(0.0, color="0.6", lw=0.8, zorder=0)
    ax.set_xlabel("time $t$ [s]")
    ax.set_ylabel("displacement [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small", ncols=2 if static is not None else 1)
    if title:
        ax.set_title(title, fontsize="medium")
    return fig


def energy_figure(t, energies, *, settle_tol=None, title: str | None = None):
    """Energies over time; with ``settle_tol`` also the kinetic/elastic ratio (log scale)
    against the settling threshold.

    Args:
        t: ``(n,)`` times [s]; energies: label → ``(n,)`` [J] with at least ``kinetic``
            and ``elastic``; settle_tol: the settling threshold of the ratio, or None.
    """
    t = np.asarray(t, dtype=float)
    if settle_tol is None:
        fig, ax = new_axes(figsize=(7.5, 3.8))
    else:
        fig, (ax, ax2) = new_axes(2, figsize=(11.0, 3.8))
    for label, e in energies.items():
        ax.plot(t, np.asarray(e, dtype=float), lw=1.4, label=label)
    ax.set_xlabel("time $t$ [s]")
    ax.set_ylabel("energy [J]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small", ncols=2)
    if settle_tol is not None:
        ke = np.asarray(energies["kinetic"], dtype=float)
        el = np.abs(np.asarray(energies["elastic"], dtype=float))
        ok = el > 1e-9 * max(float(el.max()), np.finfo(float).tiny)  # skip round-off at rest
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(ok & (ke > 0), ke / np.where(ok, el, 1.0), np.nan)
        ax2.semilogy(t, ratio, color="C0", lw=1.4, label="kinetic / elastic")
        ax2.axhline(settle_tol, color="C3", ls="--", lw=1.0, label="settle tolerance")
        ax2.set_xlabel("time $t$ [s]")
        ax2.grid(alpha=0.3, which="both")
        ax2.legend(loc="best", fontsize="small")
    if title:
        fig.suptitle(title, fontsize="medium")
    return fig
