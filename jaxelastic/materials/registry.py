"""The table of built-in material laws, their names and parameter types.

:data:`BUILTIN` maps the name of every law of :class:`~jaxelastic.materials.parameters.Lame`
parameters to its ψ; :data:`FAMILIES` the rubber and soft-tissue laws to theirs, each with
its own parameter type, whose documented typical values :data:`FAMILY_PARAMS` builds.
:data:`MODEL_NAMES`, :data:`FAMILY_KEYS` and :data:`FAMILY_POSITIVE_KEYS` are what the scene
schema validates ``[material]`` against.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..mechanics.quadrature_fields import is_at_quadrature
from .cardiac import ActiveTension, Guccione, guccione, guccione_params
from .fibres import HolzapfelGasserOgden, holzapfel_gasser_ogden, holzapfel_gasser_ogden_params
from .isotropic import (
    arap,
    corotated,
    fixed_corotated,
    linear,
    neo_hookean,
    stable_neo_hookean,
    stable_neo_hookean_log,
    stvk,
)
from .parameters import Lame, check_lame
from .rubber import (
    ArrudaBoyce,
    Gent,
    MooneyRivlin,
    Ogden,
    Yeoh,
    arruda_boyce,
    arruda_boyce_params,
    gent,
    gent_params,
    mooney_rivlin,
    mooney_rivlin_params,
    ogden,
    ogden_params,
    yeoh,
    yeoh_params,
)

__all__ = [
    "BUILTIN",
    "FAMILIES",
    "FAMILY_PARAMS",
    "FAMILY_TYPES",
    "MODEL_NAMES",
    "FAMILY_KEYS",
    "FAMILY_POSITIVE_KEYS",
    "MaterialParameterError",
    "check_family",
    "check_material",
    "GENT_JM_MIN",
    "FIBRE_LENGTH_MIN",
    "PARALLEL_TOL",
    "check_guccione",
    "DIRECTION_KEYS",
]

BUILTIN = {
    "linear": linear,
    "stvk": stvk,
    "corotated": corotated,
    "neo_hookean": neo_hookean,
    "stable_neo_hookean": stable_neo_hookean,
    "stable_neo_hookean_log": stable_neo_hookean_log,
    "fixed_corotated": fixed_corotated,
    "arap": arap,
}
"""Name → ψ of every built-in model (a read-only mapping by convention)."""


FAMILIES = {
    "mooney_rivlin": mooney_rivlin,
    "yeoh": yeoh,
    "ogden": ogden,
    "gent": gent,
    "arruda_boyce": arruda_boyce,
    "holzapfel_gasser_ogden": holzapfel_gasser_ogden,
    "guccione": guccione,
}
"""Name → ψ of the rubber and soft-tissue models (:mod:`jaxelastic.materials.rubber`,
:mod:`jaxelastic.materials.fibres`), each with its own parameter type (not
:class:`~jaxelastic.materials.parameters.Lame`)."""

FAMILY_PARAMS = {
    "mooney_rivlin": mooney_rivlin_params,
    "yeoh": yeoh_params,
    "ogden": ogden_params,
    "gent": gent_params,
    "arruda_boyce": arruda_boyce_params,
    "holzapfel_gasser_ogden": holzapfel_gasser_ogden_params,
    "guccione": guccione_params,
}
"""Name → ``<name>_params(**overrides)``, the documented typical parameters of each of
:data:`FAMILIES` (their types expose ``shear_modulus`` and ``bulk_modulus``)."""


MODEL_NAMES = (*BUILTIN, *FAMILIES)
"""Every built-in model name: the Lamé laws, then the rubber/tissue families."""

FAMILY_TYPES = {
    "mooney_rivlin": MooneyRivlin,
    "yeoh": Yeoh,
    "ogden": Ogden,
    "gent": Gent,
    "arruda_boyce": ArrudaBoyce,
    "holzapfel_gasser_ogden": HolzapfelGasserOgden,
    "guccione": Guccione,
}
"""Name → the parameter type (a ``NamedTuple``) of each of :data:`FAMILIES`."""

# read from the types, not from instances: building the typical values runs JAX, and a
# library import must not start JAX's runtime (jax.distributed.initialize must come first)
FAMILY_KEYS = {name: tuple(t._fields) for name, t in FAMILY_TYPES.items()}
"""Rubber/tissue model name → its parameter keys (the fields of its parameter type, e.g.
``("c10", "c01", "kappa")`` for ``mooney_rivlin``), all required in a scene's ``[material]``."""

FAMILY_POSITIVE_KEYS = frozenset({"c10", "kappa", "Jm", "lambda_m", "k2", "bulk", "mu"}) | {
    "C",  # Guccione
    "bf",
    "bt",
    "bfs",
}
"""The rubber/tissue parameter keys whose values must be > 0."""


GENT_JM_MIN = 1e-2
"""The smallest Gent locking parameter J_m accepted: the chains lock at Ī₁ − 3 = J_m, so
J_m = 0.01 already locks at about 6 % uniaxial stretch (rubbers: J_m ≈ 30–100)."""

FIBRE_LENGTH_MIN = 1e-8
"""The shortest HGO fibre direction accepted (ψ normalises it; a direction of length ~0
has no direction)."""

PARALLEL_TOL = 1e-8
"""Guccione's s0 counts as parallel to f0 when its component orthogonal to f0 is below this
fraction of |s0| (ψ orthogonalises s0 against f0: a parallel pair has no sheet)."""


class MaterialParameterError(ValueError):
    """A material constant no stable material has (:func:`check_family`).

    Attributes:
        key: the parameter's name (a field of the parameter type, e.g. ``"lambda_m"``).
        reason: what is wrong, without the key (``"must be > 1, got 0.8"``).
    """

    def __init__(self, model: str, key: str, reason: str):
        super().__init__(f"{model}: {key} {reason}")
        self.model, self.key, self.reason = model, key, reason


def _first(a: np.ndarray, bad: np.ndarray) -> str:
    """The first offending value (and its cell, for a per-cell field)."""
    if a.ndim == 0:
        return repr(float(a))
    i = int(np.flatnonzero(bad.ravel())[0])
    return f"{float(a.ravel()[i])!r} (at {int(bad.sum())} cell(s), first cell {i})"


def check_family(model: str, values: Mapping) -> None:
    """Refuse rubber/tissue constants that make the material unstable or undefined: the
    one validation of :data:`FAMILIES`' parameters, used by :func:`check_material` (the
    Python API: ``je.solve``) and by the scene schema (``[material]``).

    Long because: the conditions of the seven families side by side, each a few lines, read
    and review best as one table.

    Checks, each naming the parameter: every value finite; a positive initial shear and
    bulk modulus at F = I; and each family's own conditions — Mooney–Rivlin c10 > 0 and
    c10 + c01 > 0; Yeoh c10 > 0; Ogden αₚ ≠ 0 and μₚαₚ ≥ 0 for every term (Ogden 1972's
    stability condition); Gent μ > 0 and J_m ≥ :data:`GENT_JM_MIN`; Arruda–Boyce μ > 0 and
    λ_m > 1 (λ_m = √N, the locking chain stretch: λ_m ≤ 1 locks at rest); HGO μ > 0,
    k1 ≥ 0, k2 > 0, κ ∈ [0, 1/3] and fibre directions of length ≥ :data:`FIBRE_LENGTH_MIN`;
    Guccione C, b_f, b_t, b_fs > 0 (each b sets a modulus of the linearised law: zero
    leaves a singular tangent) and f0, s0 nonzero directions of 2 or 3 components, s0 not
    parallel to f0 (:data:`PARALLEL_TOL`).

    Args:
        model: a name of :data:`FAMILIES`; values: parameter key → number or array
            (per-cell fields are checked cell by cell; keys not given are skipped).

    Raises:
        MaterialParameterError: naming the model, the key and the first offending value.
    """
    arr = {}
    for k, v in values.items():
        try:
            arr[k] = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            continue  # cell data or regions (scene fibre keys): checked where they are read
    for k, a in arr.items():
        if (bad := ~np.isfinite(a)).any():
            raise MaterialParameterError(model, k, f"must be finite, got {_first(a, bad)}")

    def need(key: str, ok, what: str, a=None):
        a = arr[key] if a is None else a
        if (bad := ~np.asarray(ok)).any():
            raise MaterialParameterError(model, key, f"{what}, got {_first(a, bad)}")

    def has(*keys) -> bool:
        return all(k in arr for k in keys)

    for k in ("kappa", "bulk"):  # the volumetric term's modulus: the bulk modulus
        if k in arr:
            need(k, arr[k] > 0, "(the bulk modulus) must be > 0")
    if model == "mooney_rivlin":
        if has("c10"):
            need("c10", arr["c10"] > 0, "must be > 0")
        if has("c10", "c01"):
            mu = 2.0 * (arr["c10"] + arr["c01"])
            need("c01", mu > 0, "must exceed -c10 (the shear modulus 2(c10 + c01) must be > 0)")
    elif model == "yeoh":
        if has("c10"):
            need("c10", arr["c10"] > 0, "(half the shear modulus) must be > 0")
    elif model == "ogden":
        for p in (1, 2, 3):
            mu, al = f"mu{p}", f"alpha{p}"
            if has(al):
                need(al, arr[al] != 0, "must be nonzero (psi divides by it)")
            if has(mu, al):
                need(
                    mu,
                    arr[mu] * arr[al] >= 0,
                    f"must have the sign of {al} (Ogden's stability condition mu_p alpha_p "
                    f">= 0; {al} = {float(np.ravel(arr[al])[0])!r})",
                )
        if has("mu1", "mu2", "mu3", "alpha1", "alpha2", "alpha3"):
            g = 0.5 * sum(arr[f"mu{p}"] * arr[f"alpha{p}"] for p in (1, 2, 3))
            need("mu1", g > 0, "gives a shear modulus 1/2 sum mu_p alpha_p <= 0", g)
    elif model == "gent":
        if has("mu"):
            need("mu", arr["mu"] > 0, "(the shear modulus) must be > 0")
        if has("Jm"):
            need(
                "Jm",
                arr["Jm"] >= GENT_JM_MIN,
                f"(the locking limit of I1bar - 3) must be >= {GENT_JM_MIN:g} (rubbers: 30-100; "
                "a tiny J_m locks the chains at once)",
            )
    elif model == "arruda_boyce":
        if has("mu"):
            need("mu", arr["mu"] > 0, "must be > 0")
        if has("lambda_m"):
            need(
                "lambda_m",
                arr["lambda_m"] > 1,
                "(the locking stretch sqrt(N)) must be > 1 (rubbers: 3-10; lambda_m <= 1 "
                "locks the chains at rest)",
            )
    elif model == "holzapfel_gasser_ogden":
        if has("mu"):
            need("mu", arr["mu"] > 0, "(the matrix shear modulus) must be > 0")
        if has("k1"):
            need("k1", arr["k1"] >= 0, "must be >= 0")
        if has("k2"):
            need("k2", arr["k2"] > 0, "must be > 0")
        if has("kappa_dispersion"):
            kd = arr["kappa_dispersion"]
            need("kappa_dispersion", (kd >= 0) & (kd <= 1.0 / 3.0), "must lie in [0, 1/3]")
        for k in ("a01", "a02"):
            if has(k) and arr[k].ndim >= 1:
                length = np.sqrt(np.sum(arr[k] ** 2, axis=-1))
                need(
                    k,
                    length >= FIBRE_LENGTH_MIN,
                    f"(a fibre direction) must have length >= {FIBRE_LENGTH_MIN:g}",
                    length,
                )
    elif model == "guccione":
        if has("C"):
            need("C", arr["C"] > 0, "(the stiffness scale) must be > 0")
        for k in ("bf", "bt", "bfs"):
            if has(k):
                need(k, arr[k] > 0, "must be > 0 (each b sets a modulus: zero is singular)")
        _check_basis(model, arr, need)


def _check_basis(model: str, arr: dict, need) -> None:
    """Guccione's f0 and s0 (shared ``(d,)`` or per cell ``(n_cells, d)``, d = 2 or 3):
    nonzero, and s0 not parallel to f0."""
    shared = all(arr[k].ndim == 1 for k in ("f0", "s0") if k in arr)

    def check(key, ok, what, value):  # a shared vector reports its value, a field its cell
        need(key, ok[0] if shared else ok, what, value[0] if shared else value)

    rows = {}
    for k in ("f0", "s0"):
        if k not in arr:
            continue
        a = np.atleast_2d(arr[k])
        if a.ndim != 2 or a.shape[-1] not in (2, 3):
            raise MaterialParameterError(
                model, k, f"must have 2 or 3 components, got shape {arr[k].shape}"
            )
        length = np.linalg.norm(a, axis=1)
        check(k, length > 0, "(a direction) must be nonzero; its length", length)
        rows[k] = np.pad(a, ((0, 0), (0, 3 - a.shape[-1])))
    if len(rows) == 2:
        f, s = np.broadcast_arrays(rows["f0"], rows["s0"])
        fn = f / np.linalg.norm(f, axis=1, keepdims=True)
        perp = np.linalg.norm(s - np.sum(s * fn, axis=1, keepdims=True) * fn, axis=1)
        ok = perp > PARALLEL_TOL * np.linalg.norm(s, axis=1)
        check("s0", ok, "must not be parallel to f0; its part across f0", perp)


def check_guccione(params: Guccione) -> None:
    """Refuse concrete Guccione parameters that define no solid: :func:`check_family`'s
    ``"guccione"`` conditions on a :class:`~jaxelastic.materials.cardiac.Guccione` (shared
    or per-cell). Traced parameters are not checked.

    Raises:
        MaterialParameterError: naming the parameter and the first offending cell.
    """
    try:
        values = {k: _host_values(getattr(params, k)) for k in Guccione._fields}
    except Exception:  # noqa: BLE001 — traced leaves (inside jit/grad): not checked
        return
    check_family("guccione", values)


def _host_values(v) -> np.ndarray:
    """A concrete parameter leaf as a NumPy array; a per-quadrature-point field
    ``(n_cells, n_q, ...)`` flattened to ``(n_cells·n_q, ...)`` (checked like a per-cell
    one; a message's index then counts points, cell-major)."""
    if is_at_quadrature(v):
        a = np.asarray(v.values)
        return a.reshape((-1,) + a.shape[2:])
    return np.asarray(v)


def check_material(params, dim: int) -> None:
    """Refuse concrete material parameters no stable material has: Lamé parameters
    (:func:`~jaxelastic.materials.parameters.check_lame`) or the constants of a
    rubber/tissue family (:func:`check_family`, by parameter type). Traced parameters and
    user types are not checked.

    Raises:
        ValueError: naming the parameter (:class:`MaterialParameterError` for a family).
    """
    if isinstance(params, ActiveTension):  # the passive law's constants
        try:
            Ta = _host_values(params.Ta)
        except Exception:  # noqa: BLE001 — traced (inside jit/grad): not checked
            Ta = np.zeros(())
        if not np.all(Ta >= 0):  # NaN fails too
            bad = np.ravel(Ta)[~(np.ravel(Ta) >= 0)][0]
            raise ValueError(
                f"ActiveTension.Ta must be >= 0 and finite (a fibre tension, [stress]), got "
                f"{float(bad)!r}"
            )
        params = params.passive
    if isinstance(params, Lame):
        check_lame(params, dim)
        return
    for name, t in FAMILY_TYPES.items():
        if isinstance(params, t):
            try:
                values = {k: _host_values(getattr(params, k)) for k in t._fields}
            except Exception:  # noqa: BLE001 — traced leaves (inside jit/grad): not checked
                return
            check_family(name, values)
            return


DIRECTION_KEYS = ("a01", "a02", "f0", "s0")
"""The parameter keys that are reference directions (vectors, shared or per cell), not
scalars: HGO's fibres, Guccione's fibre and sheet."""
