"""Small matplotlib helpers for the notebooks and reports.

Matplotlib is imported lazily inside the functions, and nothing here touches pyplot's
global state: pass an ``Axes`` (e.g. from ``plt.subplots()``) or let a function create a
standalone :class:`matplotlib.figure.Figure`.
"""

from __future__ import annotations

import importlib
import threading
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
    "magnification",
    "nice_125",
    "tip_displacement_figure",
    "energy_figure",
    "preload",
]


PRELOADED = ("matplotlib.figure", "matplotlib.backends.backend_agg")
"""The matplotlib modules every figure of a run needs (the ``Figure`` class and the
Agg renderer of ``savefig``)."""


def preload() -> threading.Thread:
    """Import :data:`PRELOADED` in a background (daemon) thread and return it.

    A run that writes figures calls this before its solve: matplotlib's import (about
    0.5 s) then overlaps the solve's compiled and host work instead of adding to the
    command's time. A figure function later imports the same modules as usual (Python's
    import lock makes it wait for the thread's import if that is still running). An
    import error is left for that later import to raise where it is expected.
    """

    def work() -> None:
        for name in PRELOADED:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 (raised again by the figure's own import)
                return

    thread = threading.Thread(target=work, name="jaxelastic-preload-matplotlib", daemon=True)
    thread.start()
    return thread


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


def feature_edges(mesh, angle_deg: float = 30.0, *, facets=None) -> np.ndarray:
    """Outline edges ``(m, 2)`` of a mesh at rest: the boundary edges in 2D; in 3D the edges
    between boundary triangles whose normals differ by more than ``angle_deg`` (the
    edges of a box) and open edges. ``facets``: the mesh's linear boundary pieces
    ``(m, dim)`` if already at hand (``_linear_facets``), else they are computed."""
    facets = _linear_facets(mesh) if facets is None else facets
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


def wire_edges(mesh, *, facets=None) -> np.ndarray:
    """Edges ``(m, 2)`` for a light wireframe: all cell edges in 2D, boundary-triangle
    edges in 3D (``facets``: the linear boundary pieces if already at hand)."""
    from .mesh import linear_cells

    if mesh.dim == 2:
        tris = linear_cells(mesh)
    else:
        tris = _linear_facets(mesh) if facets is None else facets
    return _unique_edges(tris)[0]


def _linear_facets(mesh) -> np.ndarray:
    """Boundary facets as linear pieces ``(m, dim)``: P2/composite facets are split at their
    mid-edge nodes (an edge into 2 segments, a 6-node triangle into 4), so the drawing
    passes through every boundary node (curved P2 edges appear as polylines). Outward
    oriented like :func:`~jaxelastic.mesh.boundary_facets`.

    Computing them is the costly part of a 3D picture (0.42 s at 146k tet4 cells, the
    ``np.unique`` of all cell faces), so the drawing functions compute them once and pass
    them on."""
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
    dict(color="0.3", lw=1.1, ls=(0, (5, 3))),
    dict(color="C0", lw=1.6, ls="-"),
    dict(color="C3", lw=1.4, ls="-."),
    dict(color="C2", lw=1.4, ls=":"),
)
"""Outline styles: rest (dark grey dashed), then blue solid, red dash-dotted, green dotted."""

SMALL_DEFORMATION = 0.05
"""Deformations whose largest displacement is below this fraction of the rest bounding-box
diagonal are drawn magnified (:func:`magnification`)."""
MAGNIFIED_TARGET = 0.10
"""The fraction of the bounding-box diagonal a magnified largest displacement reaches."""


def nice_125(x: float) -> float:
    """The number of the 1-2-5 series (…, 0.5, 1, 2, 5, 10, 20, …) nearest to ``x > 0`` on a
    log scale."""
    if not (x > 0 and np.isfinite(x)):
        raise ValueError(f"nice_125 needs a finite positive number, got {x!r}")
    k = np.floor(np.log10(x))
    cands = np.array([1.0, 2.0, 5.0, 10.0]) * 10.0**k
    return float(cands[np.argmin(np.abs(np.log(cands / x)))])


def magnification(
    rest, deformed=(), *, small: float = SMALL_DEFORMATION, target: float = MAGNIFIED_TARGET
) -> float:
    """The factor to draw displacements with, like ParaView's *Warp By Vector* scale: 1 when
    the largest displacement of the ``deformed`` ``(n, dim)`` positions is at least
    ``small`` × the rest bounding-box diagonal (or zero), else the 1-2-5 number
    (:func:`nice_125`) nearest to ``target × diagonal / max |u|`` (so the drawn largest
    displacement is about ``target`` of the diagonal, 6–16 %).

    Args:
        rest: ``(n, dim)`` rest positions; deformed: positions of the same nodes.
    """
    rest = np.asarray(rest, dtype=float)
    diag = float(np.linalg.norm(np.ptp(rest, axis=0)))
    umax = 0.0
    for x in deformed:
        u = np.asarray(x, dtype=float) - rest
        if np.isfinite(u).all():
            umax = max(umax, float(np.linalg.norm(u, axis=1).max(initial=0.0)))
    if diag <= 0 or umax <= 0 or umax >= small * diag:
        return 1.0
    return max(1.0, nice_125(target * diag / umax))


def _factor_text(factor: float) -> str:
    return f"{factor:g}" if factor < 1e5 else f"{factor:.0e}"


def _magnified(configs: dict, factor: float) -> dict:
    """Positions ``rest + factor·u`` of every configuration but the first (the rest)."""
    labels = list(configs)
    rest = configs[labels[0]]
    return {
        k: (v if i == 0 else rest + factor * (v - rest)) for i, (k, v) in enumerate(configs.items())
    }


UNIFORM_REL = 1e-6
"""A field whose range is at most this fraction of its magnitude is drawn as uniform: one
colour and one colour-bar tick with its value (its variation is round-off, which a
stretched colour range would draw as gradients)."""


def _value_norm(values):
    """The colour range of ``values``; a (nearly) uniform field gets a range centred on its
    value and the attribute ``uniform_value`` (read by the colour bar)."""
    from matplotlib.colors import Normalize

    v = np.asarray(values, dtype=float)
    fin = v[np.isfinite(v)]
    lo, hi = (float(fin.min()), float(fin.max())) if fin.size else (0.0, 1.0)
    scale = max(abs(lo), abs(hi))
    if hi - lo <= UNIFORM_REL * scale or hi <= lo:
        mid = 0.5 * (lo + hi)
        half = max(0.05 * abs(mid), 1e-300) if mid else 1.0
        norm = Normalize(mid - half, mid + half)
        norm.uniform_value = mid  # type: ignore[attr-defined]
        return norm
    return Normalize(lo, hi)


def _front_faces(mesh, x, i: int, j: int, facets=None):
    """Boundary triangles of a 3D body facing a viewer looking along the remaining axis
    (from its negative side for a right-handed ``(i, j)`` view), sorted back to front:
    ``(tris (m, 3), order)``."""
    tris = _linear_facets(mesh) if facets is None else facets
    P = np.asarray(x)[tris]
    n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    k = 3 - i - j
    sign = np.sign(np.cross(np.eye(3)[i], np.eye(3)[j])[k])  # +1: the view looks along -k
    facing = sign * n[:, k] > 0
    tris = tris[facing]
    depth = sign * P[facing][:, :, k].mean(axis=1)
    return tris[np.argsort(depth)]


def _draw_colored_2d(ax, mesh, x, values, norm, cmap, i: int, j: int, facets=None):
    """The deformed body filled with nodal ``values`` (Gouraud shading on the linear
    sub-triangles in 2D; front boundary faces coloured by their mean in a 3D side view)."""
    from matplotlib.collections import PolyCollection

    from .mesh import linear_cells

    xy = np.asarray(x)[:, [i, j]]
    v = np.asarray(values, dtype=float)
    if mesh.dim == 2:
        return ax.tripcolor(
            xy[:, 0],
            xy[:, 1],
            linear_cells(mesh),
            v,
            shading="gouraud",
            cmap=cmap,
            norm=norm,
            zorder=1,
            rasterized=True,
        )
    tris = _front_faces(mesh, x, i, j, facets)
    pc = PolyCollection(
        list(xy[tris]),
        array=v[tris].mean(axis=1),
        cmap=cmap,
        norm=norm,
        edgecolors="face",
        linewidths=0.2,
        zorder=1,
    )
    ax.add_collection(pc)
    return pc


def shapes(
    ax,
    mesh,
    configurations,
    *,
    axes=None,
    wire: bool = True,
    values=None,
    cmap: str = "viridis",
    legend: bool = True,
):
    """Draw the outline of ``mesh`` in several configurations (a side view in 3D).

    Args:
        ax: a matplotlib ``Axes``.
        mesh: the rest mesh.
        configurations: label → ``(n_nodes, dim)`` positions, drawn in order with the
            styles rest (dark grey dashed, filled light grey in 2D), then blue solid, red
            dash-dotted, green dotted. The first configuration is taken as the rest shape
            for the view.
        axes: projection ``(horizontal, vertical)`` (default :func:`view_axes`).
        wire: also draw a light wireframe of the second configuration (without ``values``).
        values: ``(n_nodes,)`` values to colour the second configuration with (e.g. von
            Mises stress), or None.
        cmap: the colour map of ``values``.
        legend: draw a legend on ``ax`` (``loc="best"``).

    Returns:
        The colour mappable of ``values`` (for a colour bar), or None.
    """
    from matplotlib.collections import LineCollection, PolyCollection

    from .mesh import linear_cells

    configs = {k: np.asarray(v, dtype=float) for k, v in configurations.items()}
    labels = list(configs)
    rest = configs[labels[0]]
    i, j = axes if axes is not None else view_axes(rest, [configs[k] for k in labels[1:]])
    facets = _linear_facets(mesh)  # once: feature edges, faces and wireframe all need them
    feat = feature_edges(mesh, facets=facets)
    if mesh.dim == 2:  # the rest body lightly filled: the deformed one reads against it
        tri = rest[:, [i, j]][linear_cells(mesh)]
        ax.add_collection(PolyCollection(list(tri), facecolors="0.9", edgecolors="none", zorder=0))
    mappable = None
    if values is not None and len(labels) > 1:
        v = np.asarray(values, dtype=float)
        mappable = _draw_colored_2d(
            ax, mesh, configs[labels[1]], v, _value_norm(v), cmap, i, j, facets
        )
    elif wire and len(labels) > 1:
        xw = configs[labels[1]][:, [i, j]][wire_edges(mesh, facets=facets)]
        ax.add_collection(LineCollection(list(xw), colors="C0", linewidths=0.3, alpha=0.35))
    for k, label in enumerate(labels):
        st = dict(_SHAPE_STYLES[min(k, len(_SHAPE_STYLES) - 1)])
        if k == 1 and mappable is not None:
            st["color"] = "k"
            st["lw"] = 1.2
        xy = configs[label][:, [i, j]]
        ax.add_collection(
            LineCollection(
                list(xy[feat]),
                colors=st["color"],
                linewidths=st["lw"],
                linestyles=st["ls"],
                label=label,
                zorder=3 if k == 0 else 2,
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
    if legend:
        ax.legend(loc="best", fontsize="small")
    ax.grid(alpha=0.25)
    return mappable


def shapes_3d(
    ax, mesh, configurations, *, wire: bool = True, values=None, cmap="viridis", legend=True
):
    """Like :func:`shapes` on a matplotlib 3D ``Axes`` (``projection="3d"``): with
    ``values`` the second configuration's boundary surface is coloured (face means of the
    nodal values) and the outlines are drawn on top of it."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    configs = {k: np.asarray(v, dtype=float) for k, v in configurations.items()}
    labels = list(configs)
    tris = _linear_facets(mesh)  # once (0.42 s at 146k tet4 cells): edges, faces, wireframe
    feat = feature_edges(mesh, facets=tris)
    mappable = None
    if values is not None and len(labels) > 1:
        v = np.asarray(values, dtype=float)
        norm = _value_norm(v)
        mappable = Poly3DCollection(
            configs[labels[1]][tris],
            array=v[tris].mean(axis=1),
            cmap=cmap,
            norm=norm,
            edgecolors=(0.0, 0.0, 0.0, 0.3),
            linewidths=0.1,
            alpha=1.0,
            zorder=1,
        )
        ax.add_collection3d(mappable)
        ax.computed_zorder = False  # outlines drawn over the surface, in the given order
    elif wire and len(labels) > 1:
        xw = configs[labels[1]]
        ax.add_collection3d(
            Line3DCollection(
                xw[wire_edges(mesh, facets=tris)], colors="C0", linewidths=0.3, alpha=0.3
            )
        )
    for k, label in enumerate(labels):
        st = dict(_SHAPE_STYLES[min(k, len(_SHAPE_STYLES) - 1)])
        if k == 1 and mappable is not None:
            st["color"], st["lw"] = "k", 1.0
        if k == 0 and mappable is not None:
            st["lw"] = 1.3
        ax.add_collection3d(
            Line3DCollection(
                configs[label][feat],
                colors=st["color"],
                linewidths=st["lw"],
                linestyles=st["ls"],
                label=label,
                zorder=3 if k == 0 else 2,
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
    if legend:
        ax.legend(loc="upper left", fontsize="small")
    return mappable


def _colorbar(fig, ax, mappable, label: str) -> None:
    """A colour bar beside ``ax``; large or small values with a power-of-ten offset."""
    from matplotlib.ticker import ScalarFormatter

    cb = fig.colorbar(mappable, ax=ax, shrink=0.85, pad=0.02)
    uniform = getattr(mappable.norm, "uniform_value", None)
    if uniform is not None:  # one tick with the value, no offset: a uniform field
        cb.set_ticks([uniform], labels=[f"{uniform:.4g}"])
        cb.set_label(f"{label} (uniform)" if label else "uniform")
        return
    fmt = cb.formatter
    if isinstance(fmt, ScalarFormatter):
        fmt.set_powerlimits((-3, 4))  # 1e5 Pa with an offset "1e5", not 100000
    cb.set_label(label)


def _plane_figsize(aspect: float) -> tuple[float, float]:
    """Figure size [in] of a plane view whose drawing has height/width ``aspect``: an axes
    box of at most 5.8 × 6.5 in, plus room for the colour bar and the legend below."""
    if aspect <= 1.0:
        w_ax, h_ax = 5.8, float(np.clip(5.8 * aspect, 1.4, 6.5))
    else:
        w_ax, h_ax = float(np.clip(6.5 / aspect, 1.6, 5.8)), 6.5
    return max(w_ax + 2.4, 5.0), h_ax + 1.7


OBSTACLE_COLOR, OBSTACLE_ALPHA = "0.45", 0.35
"""How obstacles are drawn in the pictures (grey, translucent, behind the body)."""


def _obstacle_kind(ob) -> str:
    return type(ob).__name__ if type(ob).__name__ in ("HalfSpace", "Sphere", "Box") else ""


def _draw_obstacles_2d(ax, obstacles, pts: np.ndarray, i: int, j: int) -> None:
    """Obstacles in the ``(i, j)`` view plane: a half-space as a band beyond its line
    (when its normal lies in the view), a sphere as a disc, a box as a rectangle."""
    from matplotlib.patches import Circle, Polygon, Rectangle

    lo, hi = pts.min(0), pts.max(0)
    pad = 0.5 * float(np.max(hi - lo)) or 1.0
    for ob in obstacles:
        kind = _obstacle_kind(ob)
        if kind == "Sphere":
            c, r = np.asarray(ob.center, float), float(ob.radius)
            ax.add_patch(
                Circle((c[i], c[j]), r, color=OBSTACLE_COLOR, alpha=OBSTACLE_ALPHA, zorder=0)
            )
        elif kind == "Box":
            a, b = np.asarray(ob.lo, float), np.asarray(ob.hi, float)
            ax.add_patch(
                Rectangle(
                    (a[i], a[j]),
                    b[i] - a[i],
                    b[j] - a[j],
                    color=OBSTACLE_COLOR,
                    alpha=OBSTACLE_ALPHA,
                    zorder=0,
                )
            )
        elif kind == "HalfSpace":
            n = np.asarray(ob.normal, float)
            n2 = np.array([n[i], n[j]])
            if np.linalg.norm(n2) < 0.5 * np.linalg.norm(n):
                continue  # the plane is (nearly) parallel to the view
            n2 = n2 / np.linalg.norm(n2)
            p0 = np.asarray(ob.point, float)[[i, j]]
            t = np.array([-n2[1], n2[0]])
            L = float(np.linalg.norm(hi - lo)) + 2 * pad
            mid = p0 + t * float(np.dot(0.5 * (lo + hi)[[i, j]] - p0, t))
            a, b = mid - L * t, mid + L * t
            ax.add_patch(
                Polygon(
                    [a, b, b - 0.3 * pad * n2, a - 0.3 * pad * n2],
                    color=OBSTACLE_COLOR,
                    alpha=OBSTACLE_ALPHA,
                    zorder=0,
                )
            )


def _draw_obstacles_3d(ax, obstacles, pts: np.ndarray) -> None:
    """Obstacles in a 3D view: a half-space as a square of its plane under the body, a
    sphere and a box as wireframes."""
    lo, hi = pts.min(0), pts.max(0)
    size = float(np.max(hi - lo)) or 1.0
    style = dict(color=OBSTACLE_COLOR, alpha=OBSTACLE_ALPHA)
    for ob in obstacles:
        kind = _obstacle_kind(ob)
        if kind == "HalfSpace":
            n = np.asarray(ob.normal, float)
            n = n / np.linalg.norm(n)
            u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
            u = u / np.linalg.norm(u)
            v = np.cross(n, u)
            c = 0.5 * (lo + hi)
            c = c - np.dot(c - np.asarray(ob.point, float), n) * n  # onto the plane
            s, t = np.meshgrid([-size, size], [-size, size])
            P = c[:, None, None] + u[:, None, None] * s + v[:, None, None] * t
            ax.plot_surface(P[0], P[1], P[2], **style, shade=False)
        elif kind == "Sphere":
            c, r = np.asarray(ob.center, float), float(ob.radius)
            a, b = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
            ax.plot_wireframe(
                c[0] + r * np.cos(a) * np.sin(b), c[1] + r * np.sin(a) * np.sin(b),
                c[2] + r * np.cos(b), linewidth=0.5, **style,
            )  # fmt: skip
        elif kind == "Box":
            a, b = np.asarray(ob.lo, float), np.asarray(ob.hi, float)
            for k in range(3):  # the 12 edges: 4 along each axis
                for p in range(2):
                    for q in range(2):
                        other = [m for m in range(3) if m != k]
                        e0 = np.array(a, float)
                        e0[other[0]] = (a, b)[p][other[0]]
                        e0[other[1]] = (a, b)[q][other[1]]
                        e1 = e0.copy()
                        e1[k] = b[k]
                        ax.plot(*zip(e0, e1, strict=True), linewidth=0.8, **style)


def final_shape_figure(
    mesh,
    configurations,
    *,
    title: str | None = None,
    values=None,
    values_label: str | None = None,
    scale="auto",
    cmap: str = "viridis",
    obstacles=(),
):
    """A standalone figure of the rest and deformed configurations (rest first).

    Long because: the choice of view, the magnification and the decorations (colour bar,
    legend, obstacles, title) of one figure read best in order.

    2D: the outlines in the plane. 3D: a side view (:func:`shapes`) for an elongated body
    (longest rest extent ≥ 2× the others, e.g. a beam), else a perspective view
    (:func:`shapes_3d`). The second configuration is coloured by ``values`` with a colour
    bar (default: its displacement magnitude |u|). Small deformations are magnified
    (``scale="auto"``: :func:`magnification`; or a given factor) and the factor is in the
    title and the legend, like ParaView's warp factor. The legend sits below the axes,
    where it hides nothing.

    Args:
        mesh: the rest mesh; configurations: label → ``(n_nodes, dim)`` positions.
        title: the title (the view and the magnification are appended).
        values: ``(n_nodes,)`` nodal values for the colours (e.g. the von Mises stress
            :func:`jaxelastic.postprocess.nodal_stress` recovers), or None for |u| [m].
        values_label: the colour bar's label (default ``"|u| [m]"`` without ``values``).
        scale: ``"auto"`` or a displacement factor ≥ 1 (1: true scale).
        obstacles: contact obstacles to draw in grey (half-spaces, spheres, boxes of
            :mod:`jaxelastic.contact`, at rest; others are skipped).
    """
    from matplotlib.figure import Figure

    configs = {k: np.asarray(v, dtype=float) for k, v in configurations.items()}
    labels = list(configs)
    rest = configs[labels[0]]
    if values is None and len(labels) > 1:
        values = np.linalg.norm(configs[labels[1]] - rest, axis=1)
        values_label = values_label or "|u| [m]"
    factor = (
        magnification(rest, [configs[k] for k in labels[1:]]) if scale == "auto" else float(scale)
    )
    if factor != 1.0:
        configs = _magnified(configs, factor)
        configs = {
            (k if i == 0 else f"{k} (u ×{_factor_text(factor)})"): v
            for i, (k, v) in enumerate(configs.items())
        }
    confs = list(configs.values())
    ext_rest = np.ptp(rest, axis=0)
    srt = np.sort(ext_rest)[::-1]
    mag = f"displacements ×{_factor_text(factor)}" if factor != 1.0 else ""
    if mesh.dim == 3 and srt[0] < 2.0 * srt[1]:
        fig = Figure(figsize=(7.0, 6.4), layout="constrained")
        ax = fig.add_subplot(projection="3d")
        m = shapes_3d(ax, mesh, configs, values=values, cmap=cmap, legend=False)
        _draw_obstacles_3d(ax, obstacles, np.concatenate(confs))
        view = ""
    else:
        i, j = view_axes(rest, confs[1:])
        ext = np.ptp(np.concatenate(confs), axis=0)
        fig = Figure(
            figsize=_plane_figsize(float(ext[j] / max(ext[i], 1e-12))), layout="constrained"
        )
        ax = fig.add_subplot()
        m = shapes(ax, mesh, configs, axes=(i, j), values=values, cmap=cmap, legend=False)
        _draw_obstacles_2d(ax, obstacles, np.concatenate(confs), i, j)
        view = "" if mesh.dim == 2 else f"side view, {_AXIS_NAMES[i]}-{_AXIS_NAMES[j]} plane"
    if m is not None:
        _colorbar(fig, ax, m, values_label or "")
    _legend_below(fig, [ax], max_cols=3)
    extra = ", ".join(p for p in (view, mag) if p)
    if title or extra:
        text = (title or "") + (f" ({extra})" if extra else "")
        ax.set_title(text, fontsize="medium")
    return fig


def _legend_below(fig, axes, max_cols: int = 4) -> None:
    """One legend of all the labelled lines of ``axes``, below them (outside: it hides
    no data; needs a constrained-layout figure)."""
    handles, labels = [], []
    for ax in axes:
        h, lab = ax.get_legend_handles_labels()
        handles += h
        labels += lab
    if handles:
        fig.legend(
            handles,
            labels,
            loc="outside lower center",
            ncols=min(len(labels), max_cols),
            fontsize="small",
            frameon=False,
        )


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
    _legend_below(fig, [ax])
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
    axes = [ax]
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
        axes.append(ax2)
    _legend_below(fig, axes)
    if title:
        fig.suptitle(title, fontsize="medium")
    return fig
