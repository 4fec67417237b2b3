"""Measurement files of ``[[fit.case.observation]]`` entries, read into observations.

One entry per load factor of the case (the layouts the schema documents):

* ``reaction``: CSV with the header ``factor,force``, one row per load factor (in the
  order of ``load_factors``), the force along ``direction`` [N];
* ``moment``: CSV with the header ``factor,moment``, likewise, the support moment of
  ``nodes`` about ``axis`` (3D; out of plane in 2D) through ``origin`` [N·m];
* ``points``: NPZ with ``points`` ``(n, dim)`` rest coordinates [m] and ``displacements``
  ``(n_levels, n, dim)`` [m] (components not in ``components`` are ignored);
* ``positions``: NPZ with ``nodes`` ``(n,)`` and ``positions`` ``(n_levels, n, dim)`` [m];
* ``surface``: NPZ with ``points`` ``(n_levels, m, dim)`` measured deformed positions [m];
* ``volume``: CSV with the header ``factor,volume``, one row per load factor, the volume
  of the ``[[cavity]]`` named by ``cavity`` [m³] (2D: area per unit thickness [m²]).

Every problem is a :class:`~jaxelastic.scene.errors.SceneError` naming the key, the file
and the row or entry, raised before any solve.
"""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np

from .. import fitting
from .load import Scene
from .positions import check_positions
from .problem import Built, select_nodes
from .schema import FitCase, FitObservation

__all__ = ["read_observation", "check_nodes"]


def check_nodes(scene: Scene, where: str, nodes, n_nodes: int) -> np.ndarray:
    """``nodes`` as int64 ``(n,)``; SceneError naming the row of a non-integer, out-of-range
    or duplicated node (``where``: the key and file)."""
    a = np.asarray(nodes)
    if a.ndim != 1:
        raise scene.error(f"{where}: node indices must be one column, got shape {a.shape}")
    frac = np.flatnonzero(a != np.round(a)) if a.dtype.kind == "f" else np.array([], int)
    if frac.size:
        raise scene.error(f"{where}: row {int(frac[0])}: node {a[frac[0]]!r} is not an integer")
    a = a.astype(np.int64)
    bad = np.flatnonzero((a < 0) | (a >= n_nodes))
    if bad.size:
        i = int(bad[0])
        raise scene.error(f"{where}: row {i}: node {int(a[i])} is not in [0, {n_nodes})")
    _, first, counts = np.unique(a, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup = int(a[first[np.flatnonzero(counts > 1)[0]]])
        rows = np.flatnonzero(a == dup).tolist()
        raise scene.error(f"{where}: node {dup} appears more than once (rows {rows})")
    return a


def _finite(scene: Scene, where: str, name: str, a: np.ndarray) -> np.ndarray:
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        idx = tuple(int(i) for i in bad[0])
        raise scene.error(f"{where}: {name}{list(idx)} is not finite ({a[idx]})")
    return a


def _npz(scene: Scene, where: str, path: str, keys: tuple[str, ...]) -> dict:
    try:
        with np.load(path) as z:
            missing = [k for k in keys if k not in z]
            if missing:
                have = ", ".join(z.files) or "no arrays (an empty file)"
                raise scene.error(f"{where}: no array {missing[0]!r} (has {have})")
            return {k: np.asarray(z[k], dtype=np.float64) for k in keys}
    except (OSError, ValueError) as e:
        raise scene.error(f"{where}: cannot read the NPZ file: {e}") from None


def _shape(scene: Scene, where: str, name: str, a: np.ndarray, expected: tuple) -> None:
    if a.shape != expected or 0 in a.shape:
        want = "(" + ", ".join(str(x) for x in expected) + ")"
        raise scene.error(f"{where}: {name} must have shape {want}, got {a.shape}")


def _curve(scene, where: str, path: str, column: str, factors) -> np.ndarray:
    """The ``(n_levels,)`` values of a CSV ``factor,<column>`` with one row per load factor
    (SceneError naming the file and the row of a bad header, row count, value or factor)."""
    try:
        with open(path, encoding="utf-8") as fh:
            header = fh.readline().strip().replace(" ", "")
        if header != f"factor,{column}":
            raise scene.error(f"{where}: the first line must be 'factor,{column}', got {header!r}")
        rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except (OSError, ValueError) as e:
        raise scene.error(f"{where}: cannot read the CSV file: {e}") from None
    if rows.size == 0 or rows.shape[1] != 2 or rows.shape[0] != len(factors):
        raise scene.error(
            f"{where}: {len(factors)} data rows (one per load factor) of 2 columns expected, "
            f"got {rows.shape[0] if rows.size else 0}"
        )
    bad = np.flatnonzero(~np.isfinite(rows).all(axis=1))
    if bad.size:
        raise scene.error(f"{where}: row {int(bad[0]) + 1} (after the header) is not finite")
    off = np.flatnonzero(~np.isclose(rows[:, 0], factors, rtol=1e-9, atol=1e-12))
    if off.size:
        i = int(off[0])
        raise scene.error(
            f"{where}: row {i + 1}: factor {rows[i, 0]:g} but load_factors[{i}] = {factors[i]:g}"
        )
    return rows[:, 1]


def _reaction(scene, key, where, path, spec: FitObservation, factors, bt: Built):
    force = _curve(scene, where, path, "force", factors)
    assert spec.nodes is not None and spec.direction is not None  # schema
    nodes = select_nodes(scene, f"{key}.nodes", spec.nodes, bt.mesh, bt.mesh_data)
    d = np.asarray(spec.direction, dtype=np.float64)
    if d.shape != (bt.mesh.dim,):
        raise scene.error(f"{where}: direction must have {bt.mesh.dim} components")
    dt = bt.mesh.points.dtype
    e = jnp.asarray(d / np.linalg.norm(d), dt)
    return fitting.Reaction(jnp.asarray(nodes), e, jnp.asarray(force, dt), spec.sigma)


def _moment(scene, key, where, path, spec: FitObservation, factors, bt: Built):
    moment = _curve(scene, where, path, "moment", factors)
    assert spec.nodes is not None  # schema
    dim = bt.mesh.dim
    if dim == 3 and spec.axis is None:
        raise scene.error(f"{key}: kind = 'moment' in 3D needs axis = [ax, ay, az]")
    if dim == 2 and spec.axis is not None:
        raise scene.error(f"{key}.axis: a 2D moment is about the out-of-plane axis; omit axis")
    axis = np.asarray([1.0] if spec.axis is None else spec.axis, dtype=np.float64)
    if dim == 3 and axis.shape != (3,):
        raise scene.error(f"{key}.axis must have 3 components, got {axis.size}")
    origin = np.zeros(dim) if spec.origin is None else np.asarray(spec.origin, np.float64)
    if origin.shape != (dim,):
        raise scene.error(f"{key}.origin must have {dim} components, got {origin.size}")
    nodes = select_nodes(scene, f"{key}.nodes", spec.nodes, bt.mesh, bt.mesh_data)
    dt = bt.mesh.points.dtype
    return fitting.Moment(
        jnp.asarray(nodes),
        jnp.asarray(axis / np.linalg.norm(axis), dt),
        jnp.asarray(origin, dt),
        jnp.asarray(moment, dt),
        spec.sigma,
    )


def _points(scene, key, where, path, spec: FitObservation, factors, bt: Built):
    a = _npz(scene, where, path, ("points", "displacements"))
    dim, n = bt.mesh.dim, a["points"].shape[0] if a["points"].ndim == 2 else -1
    _shape(scene, where, "points", a["points"], (n, dim))
    _shape(scene, where, "displacements", a["displacements"], (len(factors), n, dim))
    _finite(scene, where, "points", a["points"])
    _finite(scene, where, "displacements", a["displacements"])
    try:
        return fitting.Points.at(
            bt.mesh, a["points"], a["displacements"], spec.sigma, spec.components
        )
    except ValueError as e:
        raise scene.error(f"{where}: {e}") from None


def _positions(scene, key, where, path, spec: FitObservation, factors, bt: Built):
    a = _npz(scene, where, path, ("nodes", "positions"))
    nodes = check_nodes(scene, where, a["nodes"], bt.mesh.n_nodes)
    dim, rest = bt.mesh.dim, bt.mesh.points
    pos = check_positions(scene, where, a["positions"], nodes, dim, rest, levels=len(factors))
    dt = bt.mesh.points.dtype
    return fitting.Positions(jnp.asarray(nodes), jnp.asarray(pos, dt), spec.sigma)


def _surface(scene, key, where, path, spec: FitObservation, factors, bt: Built):
    a = _npz(scene, where, path, ("points",))
    p = a["points"]
    m = p.shape[1] if p.ndim == 3 else -1
    _shape(scene, where, "points", p, (len(factors), m, bt.mesh.dim))
    _finite(scene, where, "points", p)
    return fitting.Surface.at(bt.mesh, p, spec.sigma)


def _volume(scene, key, where, path, spec: FitObservation, factors, bt: Built):
    volume = _curve(scene, where, path, "volume", factors)
    cav = bt.cavities
    assert cav is not None and spec.cavity in cav.names  # the schema checked the name
    k = cav.names.index(spec.cavity)
    term = cav.term
    facets = np.asarray(term.facets)[np.asarray(term.surface) == k]
    origin = np.asarray(term.origin)[k]
    dt = bt.mesh.points.dtype
    return fitting.CavityVolume.at(bt.mesh, facets, jnp.asarray(volume, dt), spec.sigma, origin)


_READERS = dict(
    reaction=_reaction,
    moment=_moment,
    points=_points,
    positions=_positions,
    surface=_surface,
    volume=_volume,
)


def read_observation(
    scene: Scene, key: str, spec: FitObservation, case: FitCase, bt: Built
) -> fitting.Observation:
    """The observation of one ``[[fit.case.observation]]`` entry (``key`` names it).

    Raises:
        SceneError: a missing file, a wrong layout or shape, NaN/inf (the entry named), a
            number of rows that does not match ``load_factors``, factors that differ,
            points outside the body, nodes out of range or duplicated, positions equal to
            the rest shape.
    """
    path = os.path.join(scene.base_dir, spec.file)
    where = f"{key} ({spec.file!r})"
    if not os.path.isfile(path):
        raise scene.error(f"{key}.file: no such file {path!r}")
    if os.path.getsize(path) == 0:
        raise scene.error(f"{where}: the file is empty")
    factors = np.asarray(case.load_factors, dtype=np.float64)
    return _READERS[spec.kind](scene, key, where, path, spec, factors, bt)
