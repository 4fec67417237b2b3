"""Scene ``[[pressure]]`` / ``[[cavity]]`` tables → the pressure term, the cavity volumes
per load step and the pressure–volume plot.

A scene with neither table gets no pressure term (``Potential.pressure = None``: nothing of
it is compiled) and no cavity entries. Every check runs at build time, before any solve:
an empty selection, interior facets, a non-finite pressure or origin, a cavity whose facets
enclose no positive volume at rest (an outer surface), a pressure surface that is not part
of the cavity it names, and a rim that neither is fixed nor slides on a symmetry plane
through the closing point (the follower load would not be conservative:
:func:`~jaxelastic.mechanics.pressure.check_closed`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..loads import Dirichlet
from ..mechanics.potential import Potential
from ..mechanics.pressure import Pressure, check_closed, pressure_term
from ..mesh import Mesh
from ..solvers import solve_volume_controlled
from .load import Scene

__all__ = [
    "Cavities",
    "build_pressure",
    "pressures_at",
    "pressure_schedule",
    "cavity_pressures",
    "cavity_report",
    "pressure_volume_figure",
    "volume_controlled_solve",
]


class Cavities(NamedTuple):
    """The scene's cavities, for their volumes (not part of the potential).

    Attributes:
        names: one per ``[[cavity]]``.
        term: a :class:`~jaxelastic.mechanics.pressure.Pressure` over the cavities'
            surfaces (zero pressures: only its ``volumes(x)`` is used).
        pressure: ``(n_cavities,)`` the full pressure on each cavity [Pa] (the sum of the
            ``[[pressure]]`` entries that name it; 0 where none does).
        volumes: ``(n_cavities,)`` the prescribed volumes of a volume-controlled scene
            (every cavity has one; the potential's pressure term is then the cavities'
            surfaces), or None.
    """

    names: tuple[str, ...]
    term: Pressure
    pressure: np.ndarray
    volumes: np.ndarray | None = None


def _corner_set(facets: np.ndarray, dim: int) -> set:
    return {tuple(sorted(f[:dim])) for f in np.asarray(facets).tolist()}


def _single(
    scene: Scene, key: str, mesh: Mesh, facets, p: float, origin, follower: bool = False
) -> Pressure:
    try:
        return pressure_term(mesh, facets, p, origin, what=key, follower=follower)
    except ValueError as e:
        raise scene.error(str(e)) from None


def _cavities(scene: Scene, mesh: Mesh, select: Callable, md) -> list[tuple[np.ndarray, Pressure]]:
    """Per ``[[cavity]]``: ``(facets, single-surface term)``, checked to enclose V > 0."""
    out = []
    X = jnp.asarray(mesh.points)
    for i, c in enumerate(scene.spec.cavity):
        key = f"[cavity][{i}]"
        facets = select(scene, f"{key}.facets", c.facets, mesh, md)
        t = _single(scene, key, mesh, facets, 0.0, c.origin)
        v0 = float(t.volumes(X)[0])
        if not v0 > 0:
            raise scene.error(
                f"{key} ({c.name!r}): its facets enclose a volume of {v0:.4g} <= 0 at rest: "
                "they do not bound a cavity (the body lies inside them: an outer surface?); "
                "select the cavity's own wall, and for an open cavity set origin on the "
                "plane of its opening"
            )
        out.append((facets, t))
    return out


def build_pressure(
    scene: Scene, pot: Potential, bc: Dirichlet, md, select: Callable
) -> tuple[Potential, Cavities | None]:
    """``pot`` with the scene's pressure term (unchanged without ``[[pressure]]``) and the
    scene's :class:`Cavities` (None without ``[[cavity]]``).

    Args:
        bc: the Dirichlet data at the full load (the rims are checked against it).
        md: the mesh file's data (named groups) or None.
        select: ``(scene, key, selector, mesh, md) -> (m, k) facets`` (the scene's facet
            selection, :func:`~jaxelastic.scene.problem.select_facets`).

    Raises:
        SceneError: see the module docstring.
    """
    spec = scene.spec
    if not spec.pressure and not spec.cavity:
        return pot, None
    mesh = pot.mesh
    d = mesh.dim
    cav = _cavities(scene, mesh, select, md)
    names = [c.name for c in spec.cavity]
    X, mask, vals = (np.asarray(a) for a in (mesh.points, bc.mask, bc.values))
    sets, ps, origins = [], [], []
    cav_p = np.zeros(len(names))
    for i, p in enumerate(spec.pressure):
        key = f"[pressure][{i}]"
        facets = select(scene, f"{key}.facets", p.facets, mesh, md)
        origin = p.origin
        if p.cavity is not None:
            k = names.index(p.cavity)  # the schema checked the name
            if not _corner_set(facets, d) <= _corner_set(np.asarray(cav[k][1].facets), d):
                raise scene.error(
                    f"{key}: its facets are not part of the surface of cavity {p.cavity!r} "
                    "(the surface does not bound the named cavity)"
                )
            origin = origin if origin is not None else np.asarray(cav[k][1].origin[0])
            cav_p[k] += p.pressure
        t = _single(scene, key, mesh, facets, p.pressure, origin, p.follower)
        try:
            check_closed(t, X, mask, vals, what=key)
        except ValueError as e:
            raise scene.error(str(e)) from None
        sets.append(np.asarray(t.facets))
        ps.append(p.pressure)
        origins.append(np.asarray(t.origin[0]))
    if sets:  # one term; any follower surface makes it a follower term (exact for all)
        follower = any(p.follower for p in spec.pressure)
        term = pressure_term(mesh, sets, ps, np.stack(origins), follower=follower)
        pot = pot.replace(pressure=term)
    if not cav:
        return pot, None
    term = pressure_term(
        mesh,
        [np.asarray(t.facets) for _, t in cav],
        np.zeros(len(cav)),
        np.stack([np.asarray(t.origin[0]) for _, t in cav]),
    )
    targets = [c.volume for c in spec.cavity]
    if any(v is not None for v in targets):  # volume control: the cavities are loaded
        if any(v is None for v in targets):
            raise scene.error(
                "[cavity]: volume control needs a volume for every [[cavity]] (or none)"
            )
        for i, (_, t) in enumerate(cav):
            try:
                check_closed(t, X, mask, vals, what=f"[cavity][{i}]")
            except ValueError as e:
                raise scene.error(str(e)) from None
        pot = pot.replace(pressure=term)
        return pot, Cavities(tuple(names), term, cav_p, np.asarray(targets, np.float64))
    return pot, Cavities(tuple(names), term, cav_p)


def volume_controlled_solve(built, steps: int, on_increment: Callable):
    """The static solve of a volume-controlled scene
    (:func:`~jaxelastic.solvers.solve_volume_controlled`, ``steps`` volume increments):
    ``(x, per-increment stats, solution)`` like :func:`~jaxelastic.scene.run.static_solve`;
    ``on_increment(s, solution)`` gets the cavity pressures in
    ``solution.stats["cavity_pressure"]``.

    Raises:
        SolveError: an increment did not converge.
    """
    cav = built.cavities
    pot = built.potential.replace(mass=None)

    def cb(s, res, V, p):
        on_increment(s, res._replace(stats=dict(res.stats, cavity_pressure=p)))

    sol = solve_volume_controlled(
        pot, built.bc, cav.volumes, steps=steps, solver=built.solver.newton, callback=cb
    )
    stats = []
    for r in sol.stats["path"]:
        mine = [h for h in sol.stats["solves"] if h["load_factor"] == r["load_factor"]]
        stats.append(
            dict(
                status=mine[-1]["status"],
                newton_steps=sum(h["steps"] for h in mine),
                linear_iterations=sum(h["linear_iterations"] for h in mine),
                residual=mine[-1]["residual"],
                wall_time=sum(h["wall_time"] for h in mine),
                load_factor=r["load_factor"],
                accepted=True,
                multiplier_updates=r["updates"],
                cavity_pressure=r["pressure"],
            )
        )
    return sol.x, stats, sol


def pressures_at(scene: Scene, t: float) -> np.ndarray:
    """Dynamics: the pressures ``(n_pressures,)`` [Pa] of the ``[[pressure]]`` entries at
    time ``t`` [s], in the order of the scene's pressure term: each grows linearly until
    its ``ramp_time``, or acts in full from t = 0."""
    return np.array(
        [
            p.pressure * (1.0 if p.ramp_time is None else min(max(t, 0.0) / p.ramp_time, 1.0))
            for p in scene.spec.pressure
        ],
        np.float64,
    )


def pressure_schedule(scene: Scene) -> Callable[[float], np.ndarray] | None:
    """``t ↦`` :func:`pressures_at` for a dynamic scene with a ``ramp_time``; None when no
    entry has one (the term's own pressures act at every step: a step load)."""
    if not any(p.ramp_time is not None for p in scene.spec.pressure):
        return None
    return lambda t: pressures_at(scene, t)


def cavity_pressures(scene: Scene, cav: Cavities, entries: np.ndarray) -> np.ndarray:
    """``(n_cavities,)`` each cavity's pressure [Pa]: the sum of the pressures
    ``entries`` ``(n_pressures,)`` of the ``[[pressure]]`` entries that name it."""
    q = np.zeros(len(cav.names))
    for i, p in enumerate(scene.spec.pressure):
        if p.cavity is not None:
            q[cav.names.index(p.cavity)] += float(entries[i])
    return q


@jax.jit
def _volumes(term: Pressure, x):
    return term.volumes(x)


def cavity_report(cav: Cavities, steps: list, variable: str = "load_factor") -> dict:
    """``{name: {<variable>, pressure, volume, rest_volume}}`` over the load steps (or, in
    dynamics with ``variable="time"``, over the output frames).

    Args:
        steps: ``(load factor s or time t, positions (n_nodes, dim), pressures or None)``
            of the rest state and of every converged increment or frame (None: the
            pressure at ``s`` is ``s`` times the full one; volume control and dynamics pass
            the pressures, one per cavity).
        variable: the name of the first entry of each step in the report.
    """
    vols = np.stack(
        [np.asarray(_volumes(cav.term, jnp.asarray(x)), np.float64) for _, x, _ in steps]
    )
    s = [float(si) for si, _, _ in steps]
    ps = [
        [si * float(p) for p in cav.pressure] if q is None else [float(v) for v in q]
        for si, _, q in steps
    ]
    return {
        n: {
            variable: s,
            "pressure": [p[k] for p in ps],
            "volume": vols[:, k].tolist(),
            "rest_volume": float(vols[0, k]),
        }
        for k, n in enumerate(cav.names)
    }


def pressure_volume_figure(report: dict, out: str, title: str, save: Callable) -> str:
    """``pressure_volume.png``: each cavity's pressure against its volume over the load
    steps; ``save(fig, path)`` writes it. Returns the path."""
    from ..plot import new_axes

    fig, ax = new_axes()
    for name, r in report.items():
        ax.plot(r["volume"], r["pressure"], "o-", label=name)
    ax.set_xlabel("cavity volume [m³] (2D: area per unit thickness [m²])")
    ax.set_ylabel("pressure [Pa]")
    ax.set_title(f"{title}: pressure–volume")
    ax.grid(True, alpha=0.3)
    ax.legend()
    path = os.path.join(out, "pressure_volume.png")
    save(fig, path)
    return path
