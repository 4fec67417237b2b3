"""Cross-check report: autodiff mechanics against hand derivations and finite differences.

Everything jaxelastic computes (stress, forces, Hessian-vector products) is obtained by
differentiating ψ with JAX. This module checks, for every built-in model, that

* **P** — the autodiff stress ``first_piola(psi)(F)`` equals the hand-derived closed form
  :data:`jaxelastic.materials.reference.HAND_P` to ≤ 1e-12 (relative, float64) over a battery of
  deformation gradients: identity, pure rotations, uniaxial stretch up to 5×, compression
  to 0.05×, simple shear, repeated singular values, near inversion (J = 1e-3), inverted
  states (J < 0) and seeded random F;
* **forces-FD** — :func:`jaxelastic.forces` equals minus the central-difference gradient of
  :func:`jaxelastic.energy` (every degree of freedom) on a small, randomly deformed mesh
  (``rectangle(3, 3)`` in 2D, ``box(2, 2, 2)`` in 3D);
* **hvp-FD** — :func:`jaxelastic.hvp` applied to every unit vector equals minus the
  central difference of the forces (the full Hessian, both ways);
* **five-step** — the lecture notes' hand force recipe
  :func:`jaxelastic.materials.reference.five_step_forces` with the hand P equals autodiff
  :func:`jaxelastic.forces` (≤ 1e-12 relative).

Relative difference of an autodiff value ``a`` against a reference ``b``::

    rel = max|a − b| / max(max|b|, floor)

For P the floor is the shear modulus μ (an absolute stress scale): at the identity and at
pure rotations the exact P is zero and both sides are round-off, so dividing by ``max|b|``
would compare noise with noise. Near zero strain this makes the check absolute, in units
of μ; wherever ``|P| ≥ μ`` it is an ordinary relative error. For the mesh checks the
reference is far from zero (the mesh is deformed) and the floor is the smallest positive
float.

Cases outside a model's domain are skipped (no row): neo-Hookean and the rubber/tissue
families need J > 0 and a finite ψ (they are +∞ otherwise: Gent beyond its locking
stretch, the HGO exponential past overflow at J = 1e-3), and ``stable_neo_hookean_log``
is defined in 3D only.

Run it as ``python -m jaxelastic crosscheck`` (or :func:`main`). The checks need float64:
:func:`main` enables it; callers of :func:`crosscheck` must enable it themselves with
``jax.config.update("jax_enable_x64", True)`` before creating any array.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys

import jax
import jax.numpy as jnp
import numpy as np

from .. import materials
from ..io import write_json
from ..materials import Lame, reference
from ..mechanics.kernels import energy, first_piola, forces, hvp
from ..mechanics.kinematics import deformation_gradients
from ..mesh import box, rectangle

__all__ = [
    "P_TOL",
    "FD_TOL",
    "FIVE_STEP_TOL",
    "MODELS",
    "deformation_battery",
    "relative_difference",
    "crosscheck",
    "format_table",
    "main",
]

P_TOL = 1e-12
"""Required agreement of autodiff P with the hand-derived P (relative, float64)."""

FD_TOL = 1e-6
"""Required agreement of forces/HVP with central finite differences (relative)."""

FIVE_STEP_TOL = 1e-12
"""Required agreement of the five-step hand forces with autodiff forces (relative)."""

MODELS = tuple(
    name for name in (*materials.BUILTIN, *materials.FAMILIES) if name in reference.HAND_P
)
"""Built-in models that have a hand-derived P (all of them): the Lamé-parameter models of
:data:`jaxelastic.materials.BUILTIN` and the rubber/tissue :data:`~jaxelastic.materials.FAMILIES`
(checked at their documented typical parameters ``<name>_params()``)."""

_FD_STEP = 1e-5  # central-difference step [length]; truncation ~h², round-off ~eps/h
_SEED = 20240611


def _domain_ok(model: str, dim: int, J: float) -> bool:
    """Whether ``model`` is defined at a deformation with determinant ``J`` in ``dim``."""
    if model == "stable_neo_hookean_log" and dim != 3:
        return False
    if (model == "neo_hookean" or model in materials.FAMILIES) and not J > 0:
        return False
    return True


def _finite(psi, F, params) -> bool:
    """Whether ``psi(F)`` is finite (outside the domain, e.g. Gent past its locking
    stretch or an overflowing HGO exponential, the models return +inf: no row)."""
    return bool(np.isfinite(np.asarray(psi(jnp.asarray(F), params))))


def _psi(model: str):
    return materials.BUILTIN[model] if model in materials.BUILTIN else materials.FAMILIES[model]


def _model_params(model: str, lame_params: Lame):
    """The parameters a model is checked at: ``lame_params`` for the Lamé models, the
    documented defaults ``<name>_params()`` (float64) for the rubber/tissue families."""
    if model in materials.BUILTIN:
        return lame_params
    return jax.tree_util.tree_map(
        lambda v: jnp.asarray(v, jnp.float64), materials.FAMILY_PARAMS[model]()
    )


def _stress_scale(params) -> float:
    """The absolute stress floor of the P comparison: the initial shear modulus."""
    return float(params.mu if isinstance(params, Lame) else params.shear_modulus)


def _cell_params(params, n_cells: int):
    """``params`` ready for mesh-level calls: shared fibre directions broadcast per cell."""
    if isinstance(params, materials.HolzapfelGasserOgden):
        return materials.per_cell_fibres(params, n_cells)
    if isinstance(params, materials.Guccione):
        return materials.per_cell_basis(params, n_cells)
    return params


def _rotation(dim: int, angle: float, axis=(1.0, 2.0, 3.0)) -> np.ndarray:
    """Rotation matrix ``(dim, dim)``: angle [rad] in 2D, axis–angle (Rodrigues) in 3D."""
    c, s = math.cos(angle), math.sin(angle)
    if dim == 2:
        return np.array([[c, -s], [s, c]])
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * Kx + (1.0 - c) * Kx @ Kx


def _random_rotation(dim: int, rng: np.random.Generator) -> np.ndarray:
    Q, Rr = np.linalg.qr(rng.standard_normal((dim, dim)))
    Q = Q * np.sign(np.diag(Rr))[None, :]
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def _diag(dim: int, values) -> np.ndarray:
    """``diag(values[:dim])``, padded with ones when fewer than ``dim`` values are given."""
    vals = list(values)[:dim]
    v = np.ones(dim)
    v[: len(vals)] = vals
    return np.diag(v)


def deformation_battery(dim: int, seed: int = _SEED) -> list[tuple[str, np.ndarray]]:
    """The deformation gradients the P check runs over.

    Args:
        dim: 2 or 3.
        seed: seed of the random cases.

    Returns:
        A list of ``(case name, F)`` with ``F`` a ``(dim, dim)`` float64 NumPy array.
    """
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    rng = np.random.default_rng(seed + dim)
    Q = _rotation(dim, 0.7, axis=(1.0, -2.0, 0.5))
    shear = np.eye(dim)
    cases = [
        ("identity", np.eye(dim)),
        ("rotation 0.3 rad", _rotation(dim, 0.3)),
        ("rotation 3.0 rad", _rotation(dim, 3.0, axis=(0.0, 1.0, 1.0))),
        ("uniaxial stretch 2x", _diag(dim, [2.0])),
        ("uniaxial stretch 5x", _diag(dim, [5.0])),
        ("compression 0.5x", _diag(dim, [0.5])),
        ("compression 0.05x", _diag(dim, [0.05])),
        ("uniform scaling 1.5x", 1.5 * np.eye(dim)),
        ("rotated stretch 3x", Q @ _diag(dim, [3.0, 0.8])),
    ]
    if dim == 3:  # in 2D, repeated singular values are the uniform scaling above
        cases.append(("repeated sigma (2,2,0.5)", Q @ _diag(3, [2.0, 2.0, 0.5]) @ Q.T))
    for gamma in (0.5, 2.0):
        S = shear.copy()
        S[0, 1] = gamma
        cases.append((f"simple shear {gamma:g}", S))
    # near inversion: J = 1e-3, rotated so that no entry is trivially zero
    cases.append(("near inversion J=1e-3", Q @ _diag(dim, [1.0] * (dim - 1) + [1e-3]) @ Q.T))
    # inverted: the smallest signed singular value is negative
    cases.append(("inverted (1,...,-0.5)", Q @ _diag(dim, [1.0] * (dim - 1) + [-0.5])))
    for k in range(3):
        s = np.exp(rng.uniform(np.log(0.2), np.log(5.0), size=dim))
        F = _random_rotation(dim, rng) @ np.diag(s) @ _random_rotation(dim, rng).T
        cases.append((f"random {k}", F))
    s = np.exp(rng.uniform(np.log(0.3), np.log(3.0), size=dim))
    s[-1] = -s[-1]
    F = _random_rotation(dim, rng) @ np.diag(s) @ _random_rotation(dim, rng).T
    cases.append(("random inverted", F))
    return cases


def relative_difference(a, b, floor: float = 0.0) -> float:
    """``max|a − b| / max(max|b|, floor, tiny)`` as a Python float (NaN if non-finite).

    Args:
        a: the value under test (any shape).
        b: the reference, same shape as ``a``.
        floor: an absolute scale for ``b`` (e.g. μ for stresses) used when ``|b|`` is
            smaller, so that a reference that is exactly zero is compared in its units.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shape mismatch: {a.shape} vs {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return math.nan
    scale = max(float(np.max(np.abs(b), initial=0.0)), float(floor), np.finfo(np.float64).tiny)
    return float(np.max(np.abs(a - b), initial=0.0)) / scale


def _row(model, dim, check, case, rel, tol) -> dict:
    passed = bool(math.isfinite(rel) and rel <= tol)
    return {
        "model": model,
        "dim": int(dim),
        "check": check,
        "case": case,
        "rel_diff": rel if math.isfinite(rel) else None,
        "tol": tol,
        "passed": passed,
    }


def _test_mesh(dim: int):
    """Small mesh and a deformed state: a rotated stretch plus a seeded perturbation.

    Returns:
        ``(mesh, x, description)`` with ``x`` of shape ``(n_nodes, dim)``, every cell with
        ``J ≥ 0.5`` so that every model (neo-Hookean included) is defined around ``x``.
    """
    if dim == 2:
        mesh, label, h = rectangle(3, 3), "rectangle(3,3)", 1.0 / 3.0
    else:
        mesh, label, h = box(2, 2, 2), "box(2,2,2)", 1.0 / 2.0
    rng = np.random.default_rng(_SEED + 10 * dim)
    X = np.asarray(mesh.points)
    A = _rotation(dim, 0.3) @ _diag(dim, [1.2, 0.9, 1.05])  # affine part
    noise = rng.uniform(-1.0, 1.0, size=X.shape)
    amp = 0.15 * h
    while True:
        x = X @ A.T + amp * noise
        J = np.linalg.det(np.asarray(deformation_gradients(jnp.asarray(x), mesh)))
        if J.min() >= 0.5:
            break
        amp *= 0.5
    return mesh, jnp.asarray(x), f"{label}, perturbed"


# Each compiled check runs once on a tiny problem, so compile time is nearly all the cost;
# XLA's backend (LLVM) optimisation level 0 cuts it by ~40%. Arithmetic stays IEEE float64
# (no fast-math either way); only rounding of the FD stencils changes, at the 1e-11 level.
_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}


@functools.partial(jax.jit, static_argnames=("psi", "hand"), compiler_options=_COMPILER_OPTIONS)
def _checks(Fs, x, mesh, p, pc, *, psi, hand):
    """Every compared quantity of one model, in one compiled function.

    Args:
        Fs: ``(n_cases, d, d)`` deformation gradients of the P battery.
        x: ``(n_nodes, d)`` deformed positions on ``mesh``.
        p: shared material parameters (P battery); pc: the same for the mesh (shared
            vectors broadcast per cell); psi, hand: ψ and its hand-derived P (static).

    Returns:
        ``P_auto, P_hand`` ``(n_cases, d, d)``; ``fd_grad`` ``(n·d,)``; ``f`` ``(n, d)``;
        ``fd_hess, hv`` ``(n·d, n, d)``; ``f5`` ``(n, d)``.
    """
    P_auto = jax.vmap(first_piola(psi), in_axes=(0, None))(Fs, p)
    P_hand = jax.vmap(hand, in_axes=(0, None))(Fs, p)
    n, d = x.shape
    basis = jnp.eye(n * d, dtype=x.dtype).reshape(n * d, n, d)  # unit vectors
    h = _FD_STEP

    def energy_and_forces(y):
        return energy(psi, y, mesh, pc), forces(psi, y, mesh, pc)

    # both FD stencils from one batched evaluation at x ± h·e_i
    e_pm, f_pm = jax.vmap(energy_and_forces)(
        jnp.concatenate([x[None] + h * basis, x[None] - h * basis])
    )
    fd_grad = (e_pm[: n * d] - e_pm[n * d :]) / (2.0 * h)  # (n·d,) = ∂E/∂x_i
    fd_hess = -(f_pm[: n * d] - f_pm[n * d :]) / (2.0 * h)  # (n·d, n, d) = H e_i
    f = forces(psi, x, mesh, pc)
    hv = jax.vmap(lambda v: hvp(psi, x, v, mesh, pc))(basis)  # (n·d, n, d)
    f5 = reference.five_step_forces(hand, x, mesh, pc)
    return P_auto, P_hand, fd_grad, f, fd_hess, hv, f5


def _model_rows(model: str, dim: int, params) -> list[dict]:
    if not _domain_ok(model, dim, 1.0):
        return []
    psi = _psi(model)
    cases = [
        (name, F)
        for name, F in deformation_battery(dim)
        if _domain_ok(model, dim, np.linalg.det(F)) and _finite(psi, F, params)
    ]
    Fs = jnp.asarray(np.stack([F for _, F in cases]))  # (n_cases, d, d)
    mesh, x, label = _test_mesh(dim)
    hand = reference.HAND_P[model]
    pc = _cell_params(params, mesh.n_cells)
    out = _checks(Fs, x, mesh, params, pc, psi=psi, hand=hand)
    P_auto, P_hand, fd_grad, f, fd_hess, hv, f5 = (np.asarray(a) for a in out)
    mu = _stress_scale(params)
    rows = [
        _row(model, dim, "P", name, relative_difference(P_auto[i], P_hand[i], floor=mu), P_TOL)
        for i, (name, _) in enumerate(cases)
    ]
    rows.append(
        _row(model, dim, "forces-FD", label, relative_difference(-f.reshape(-1), fd_grad), FD_TOL)
    )
    rows.append(_row(model, dim, "hvp-FD", label, relative_difference(hv, fd_hess), FD_TOL))
    rows.append(_row(model, dim, "five-step", label, relative_difference(f5, f), FIVE_STEP_TOL))
    return rows


def crosscheck(dims=(2, 3), models=None, params: Lame | None = None) -> list[dict]:
    """Run every check and return one row per (model, dim, check, case).

    Args:
        dims: spatial dimensions to check, a subset of ``(2, 3)``.
        models: built-in model names (default: all of :data:`MODELS`).
        params: scalar Lamé parameters of the Lamé models (default: ``lame(E=1e5, ν=0.3)``:
            μ ≈ 3.8e4, λ ≈ 5.8e4); the rubber/tissue families use their ``<name>_params()``.
            The initial shear modulus is the absolute scale of the P comparison.

    Returns:
        A list of dicts with keys ``model`` (str), ``dim`` (int), ``check`` (``"P"``,
        ``"forces-FD"``, ``"hvp-FD"`` or ``"five-step"``), ``case`` (str), ``rel_diff``
        (float, or None when a value was NaN/inf), ``tol`` (float) and ``passed`` (bool).
        Cases outside a model's domain produce no row.

    Raises:
        ValueError: unknown model or dimension.
        RuntimeError: float64 is not enabled (the tolerances are float64 tolerances).
    """
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            "crosscheck needs float64: call jax.config.update('jax_enable_x64', True) first"
        )
    dims = tuple(dict.fromkeys(int(d) for d in dims))  # de-duplicated, order kept
    bad_dims = [d for d in dims if d not in (2, 3)]
    if bad_dims:
        raise ValueError(f"dims must be 2 and/or 3, got {bad_dims}")
    models = MODELS if models is None else tuple(dict.fromkeys(models))
    unknown = [m for m in models if m not in MODELS]
    if unknown:
        raise ValueError(f"unknown model(s) {unknown}; available: {list(MODELS)}")
    if params is None:
        params = Lame.from_E_nu(1e5, 0.3)
    params = Lame(jnp.asarray(params.mu, jnp.float64), jnp.asarray(params.lam, jnp.float64))
    rows: list[dict] = []
    for model in models:
        for dim in dims:
            rows += _model_rows(model, dim, _model_params(model, params))
    return rows


def format_table(rows: list[dict]) -> str:
    """A readable, column-aligned table of ``rows`` with a PASS/FAIL column and a summary."""
    header = ("model", "dim", "check", "case", "rel. diff", "tol", "status")
    body = []
    for r in rows:
        rel = "nan/inf" if r["rel_diff"] is None else f"{r['rel_diff']:.2e}"
        body.append(
            (
                r["model"],
                f"{r['dim']}D",
                r["check"],
                r["case"],
                rel,
                f"{r['tol']:.0e}",
                "PASS" if r["passed"] else "FAIL",
            )
        )
    widths = [max([len(h)] + [len(b[i]) for b in body]) for i, h in enumerate(header)]
    right = {1, 4, 5}  # numeric columns are right-aligned

    def line(cells):
        return "  ".join(
            c.rjust(w) if i in right else c.ljust(w)
            for i, (c, w) in enumerate(zip(cells, widths, strict=True))
        ).rstrip()

    out = [line(header), line(tuple("-" * w for w in widths))]
    out += [line(b) for b in body]
    n_fail = sum(not r["passed"] for r in rows)
    worst = {}
    for r in rows:
        if r["rel_diff"] is not None:
            worst[r["check"]] = max(worst.get(r["check"], 0.0), r["rel_diff"])
    summary = ", ".join(f"max {k} {v:.1e}" for k, v in worst.items())
    out.append("")
    out.append(
        f"{len(rows)} checks, {len(rows) - n_fail} passed, {n_fail} failed"
        + (f" ({summary})" if summary else "")
    )
    return "\n".join(out)


def main(argv=None) -> int:
    """Command-line entry point: run :func:`crosscheck`, print the table.

    Options: ``--dims 2 3``, ``--models neo_hookean stvk …``, ``--json PATH`` (rows written
    atomically). Enables float64. Returns 0 when every check passes, else 1.
    """
    parser = argparse.ArgumentParser(
        prog="python -m jaxelastic crosscheck",
        description="Check autodiff stress, forces and Hessian-vector products against "
        "hand-derived formulas and finite differences for the built-in materials.",
    )
    parser.add_argument(
        "--dims", type=int, nargs="+", choices=(2, 3), default=[2, 3], help="dimensions"
    )
    parser.add_argument(
        "--models",
        nargs="+",
        choices=MODELS,
        default=None,
        metavar="MODEL",
        help=f"models to check (default: all of {', '.join(MODELS)})",
    )
    parser.add_argument("--json", metavar="PATH", default=None, help="also write rows as JSON")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    rows = crosscheck(dims=tuple(args.dims), models=args.models)
    print(format_table(rows))
    if args.json is not None:
        write_json(args.json, rows, indent=2)
    return 0 if rows and all(r["passed"] for r in rows) else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
