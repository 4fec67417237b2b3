"""Accuracy against known answers, and error against run time.

For every case: a refinement sequence × element variant (P1, P2, F-bar; see
``_report_common.ELEMENT_KW``) × solver setting (linear solver, preconditioner, Newton
tolerance), with the error, mesh size h, dofs, wall time split into compilation (cold call
minus warm call) and run (the warm second call, same compiled code), Newton and linear
iterations. The problems are those of :mod:`jaxelastic.verification` (their docstrings cite
the references; README section "Accuracy, error against run time, stability"):

* ``cook``: Cook's membrane, linear, plane stress (E = 1, ν = 1/3, total shear 1 on x = 48),
  u_y at (48, 52) against 23.96 (Cook 1974; the converged value quoted by e.g. Simo & Rifai
  1990 for this load).
* ``timoshenko``: plane-stress cantilever L = 48, D = 12, E = 3e7, ν = 0.3, parabolic end
  shear P = 1000, exact field imposed on x = 0 (Timoshenko & Goodier 1970, §21): relative
  L2 and energy-norm errors by quadrature against the exact field, observed rates.
* ``cantilever3d``: 3D tet cantilever 10 × 1 × 1 with 1, 2, 4, 8 elements through the depth
  against Timoshenko beam theory δ = PL³/(3EI) + PL/(κGA), κ = 10(1+ν)/(12+11ν) (Cowper
  1966): P1 tets shear-lock.
* ``uniaxial`` / ``shear``: homogeneous uniaxial tension and simple shear of a neo-Hookean
  block against the closed forms (Bonet & Wood 2008, §6.4; Poynting effect σ₁₁ = μγ²).
* ``patch``: MacNeal & Harder (1985) membrane patch (σx = σy = 1333.3, τ = 400) and an
  affine map reproduced exactly by every built-in material.
* ``twist``: the JAX-FEM twist benchmark (as ``scripts/bench_solvers.py``) against a fine
  reference.
* ``cook_nh``: nearly incompressible neo-Hookean Cook (plane strain, G = 80.1938,
  K = 40.0942e4, load 100), corner (48, 60) u_y against 6.91 (de Souza Neto et al. 1996;
  Elguedj et al. 2008).
* ``cook_incompressible``: nearly incompressible linear Cook (plane strain, G = 0.375,
  λ = 7500), mid-edge u_y against 16.43 (P1, P2 and B-bar, the small-strain F-bar).

Outputs in ``--out``: ``accuracy.json`` and ``accuracy.csv`` (all rows), one
``error_vs_time_<case>.png`` per case with a discretisation error, ``error_vs_time_summary.png``,
and a printed table. Run times on a shared machine are noisy; compare within a run.

Usage::

    python scripts/report_accuracy.py --quick --out out/report_accuracy_quick
    python scripts/report_accuracy.py --out out/report_accuracy          # moderate sizes
    python scripts/report_accuracy.py --cases cook,timoshenko --elements P1,P2
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import _report_common as rc
import numpy as np

from jaxelastic import verification as bm

# --------------------------------------------------------------------------------------
# solver settings and the generic row runner
# --------------------------------------------------------------------------------------


class SolverSpec(NamedTuple):
    """A solver setting of the error-against-time study."""

    linear: str  # "direct" | "amg" | "cg"
    rtol: float = 1e-8
    preconditioner: str = "block_jacobi"


SOLVERS = {
    "direct": SolverSpec("direct"),
    "amg": SolverSpec("amg"),
    "cg": SolverSpec("cg"),
    "cg-jacobi": SolverSpec("cg", preconditioner="jacobi"),
    "cg-loose": SolverSpec("cg", rtol=1e-4),
    "direct-loose": SolverSpec("direct", rtol=1e-4),
}


@dataclasses.dataclass
class Problem:
    """One discrete problem: potential, Dirichlet data, mesh size h, and how to score x."""

    pot: object
    bc: object
    h: float
    evaluate: Callable[[np.ndarray], dict]  # x (n_nodes, dim) -> {"error": .., ...}
    steps: int = 0  # > 0: load stepping (solve_incremental) with this many increments
    max_steps: int = 50


@dataclasses.dataclass
class Case:
    name: str
    title: str
    build: Callable[[int, str], Problem]
    levels: dict  # element -> (full levels, quick levels)
    solvers: tuple  # full
    quick_solvers: tuple
    error_label: str
    reference: str
    pareto: bool = True  # a discretisation error (plotted against time)


def _newton(prob: Problem, spec: SolverSpec):
    """The Newton solver of a row, its linear solver bound once (pattern analysis)."""
    import jaxelastic as je

    linear = je.CG(preconditioner=spec.preconditioner) if spec.linear == "cg" else spec.linear
    bound = je.solvers.linear.resolve(linear, prob.pot.mesh, prob.bc)
    return je.Newton(rtol=spec.rtol, max_steps=prob.max_steps, linear=bound)


def _solve_once(prob: Problem, solver) -> tuple[np.ndarray, dict]:
    """One solve (load stepping if ``prob.steps``): positions and iteration statistics."""
    import jaxelastic as je

    if prob.steps:
        r = je.solve_incremental(prob.pot, prob.bc, steps=prob.steps, solver=solver, throw=False)
        incs = r.stats["increments"]
        return r.x, dict(
            status=je.Status(int(r.status)).name,
            newton=sum(int(h["steps"]) for h in incs),
            linear_its=sum(int(h["linear_iterations"]) for h in incs),
            increments=len(incs),
        )
    r = je.solve(prob.pot, prob.bc, solver=solver, throw=False)
    return r.x, dict(
        status=je.Status(int(r.status)).name,
        newton=int(r.stats["steps"]),
        linear_its=int(r.stats["linear_iterations"]),
        increments=1,
    )


def _solve_twice(prob: Problem, spec: SolverSpec):
    """Cold and warm solves; returns (x, stats) with the warm call's statistics."""
    solver = _newton(prob, spec)  # pattern analysis: cold only
    t0 = time.perf_counter()
    _solve_once(prob, solver)
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    x, st = _solve_once(prob, solver)
    warm = time.perf_counter() - t0
    st.update(cold_s=cold, run_s=warm, compile_s=max(cold - warm, 0.0))
    return np.asarray(x), st


def run_row(case: Case, level: int, element: str, solver: str) -> dict:
    """Build, solve (cold + warm) and score one configuration; never raises for a failed
    solve or an unavailable element (the row says why)."""
    row = dict(case=case.name, element=element, level=level, solver=solver)
    try:
        prob = case.build(level, element)
    except rc.Unavailable as e:
        return dict(row, status="SKIPPED", reason=str(e))
    except Exception as e:  # noqa: BLE001 - one broken configuration must not end the report
        return dict(row, status="ERROR", reason=f"{type(e).__name__}: {e}"[:300])
    mesh = prob.pot.mesh
    row.update(h=prob.h, dofs=int(mesh.n_dofs), cells=int(mesh.n_cells), elem=mesh.element)
    spec = SOLVERS[solver]
    row.update(linear=spec.linear, rtol=spec.rtol, preconditioner=spec.preconditioner)
    x, st = _solve_twice(prob, spec)
    row.update(st)
    if not np.isfinite(x).all():
        row.update(status="NONFINITE", reason="non-finite positions")
        return row
    row.update(prob.evaluate(x))
    return row


# --------------------------------------------------------------------------------------
# helpers: error norms by quadrature, mesh size
# --------------------------------------------------------------------------------------


def _gauss01(n):
    p, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (p + 1.0), 0.5 * w


def _tri_rule(n=6):
    """Collapsed (Duffy) Gauss rule on the unit triangle, exact to degree 2n − 1."""
    u, wu = _gauss01(n)
    U, V = np.meshgrid(u, u, indexing="ij")
    W = np.outer(wu, wu) * (1 - U)
    return np.stack([U.ravel(), (V * (1 - U)).ravel()], 1), W.ravel()


def error_norms_2d(mesh, x, u_fn, grad_fn, mu, lam) -> tuple[float, float]:
    """Relative L2 and energy-norm errors of the FE displacement ``x − X`` against an exact
    field, by a degree-11 rule on every (sub-)cell.

    ``u_fn(X (k, 2)) -> (k, 2)``, ``grad_fn(X) -> (k, 2, 2)`` (∂u_i/∂X_j); energy norm
    ``(∫ ε : (2μ ε + λ tr ε I))^{1/2}`` of the small-strain error with the given (μ, λ).
    """
    from jaxelastic.mesh.elements import get_element

    el = mesh.element_type
    X = np.asarray(mesh.points)
    cells = np.asarray(mesh.cells)
    if el.is_composite:  # piecewise linear on sub-simplices: score it as that P1 mesh
        cells = cells[:, np.asarray(el.sub_cells)].reshape(-1, el.dim + 1)
        el = get_element("tri3")
    xi, wq = _tri_rule()
    N = el.shape_functions(xi)  # (q, k)
    dNr = el.shape_gradients(xi)  # (q, k, 2)
    Xe, Ue = X[cells], (np.asarray(x) - X)[cells]
    Jac = np.einsum("cka,qkb->cqab", Xe, dNr)
    det = np.linalg.det(Jac)
    dNdX = np.einsum("qkb,cqba->cqka", dNr, np.linalg.inv(Jac))
    Xq = np.einsum("qk,cka->cqa", N, Xe).reshape(-1, 2)
    uh = np.einsum("qk,cka->cqa", N, Ue).reshape(-1, 2)
    gh = np.einsum("cka,cqkb->cqab", Ue, dNdX).reshape(-1, 2, 2)
    w = (np.abs(det) * wq[None, :]).ravel()
    u, g = u_fn(Xq), grad_fn(Xq)

    def energy(G):
        e = 0.5 * (G + np.swapaxes(G, 1, 2))
        tr = np.trace(e, axis1=1, axis2=2)
        return 2 * mu * np.sum(e * e, axis=(1, 2)) + lam * tr**2

    l2 = math.sqrt(np.sum(w * np.sum((uh - u) ** 2, 1)) / np.sum(w * np.sum(u**2, 1)))
    en = math.sqrt(np.sum(w * energy(gh - g)) / np.sum(w * energy(g)))
    return l2, en


def _h(mesh) -> float:
    """Mesh size: (|Ω| / number of linear pieces)^(1/d) (sub-simplices for composite P1)."""
    el = mesh.element_type
    pieces = mesh.n_cells * (len(el.sub_cells) if el.is_composite else 1)
    return float((float(np.sum(np.asarray(mesh.volumes))) / pieces) ** (1.0 / mesh.dim))


def _p1_only(element: str, what: str) -> None:
    if element != "P1":
        raise rc.Unavailable(f"the {what} is defined on P1 here")


# --------------------------------------------------------------------------------------
# cases: a benchmark of jaxelastic.verification and how to score it
# --------------------------------------------------------------------------------------


def _score_probe_uy(b: bm.Benchmark) -> Problem:
    """Score u_y at the benchmark's probe node against its ``"u_y"`` reference."""
    i = int(b.probes["point"][0])
    Y = float(b.mesh.points[i, 1])
    ref = b.reference["u_y"]

    def evaluate(x):
        v = float(x[i, 1] - Y)
        return dict(value=v, reference=ref, error=abs(v - ref) / ref)

    return Problem(b.pot, b.bc, _h(b.mesh), evaluate, steps=b.steps)


def build_cook(n, element):
    """Cook's membrane, linear, plane stress; u_y(48, 52) against 23.96."""
    return _score_probe_uy(bm.cook_linear(n, **rc.element_kw(element)))


def build_cook_incompressible(n, element):
    """Nearly incompressible linear Cook (plane strain): u_y(48, 52) against 16.43."""
    return _score_probe_uy(bm.cook_incompressible(n, **rc.element_kw(element)))


def build_cook_nh(n, element):
    """Nearly incompressible neo-Hookean Cook (plane strain): u_y(48, 60) against 6.91."""
    return _score_probe_uy(bm.cook_neo_hookean(n, **rc.element_kw(element)))


def build_timoshenko(k, element):
    """Timoshenko–Goodier cantilever on a 4k × k mesh: L2 and energy-norm errors against the
    exact field, and the mean tip u_y."""
    b = bm.timoshenko_cantilever(k, **rc.element_kw(element))
    m, (mu, lam), tip = b.mesh, b.lame, b.probes["tip"]
    X = np.asarray(m.points)

    def evaluate(x):
        l2, en = error_norms_2d(m, x, lambda Z: b.exact(Z)[0], lambda Z: b.exact(Z)[1], mu, lam)
        v = float(np.mean(x[tip, 1] - X[tip, 1]))
        return dict(value=v, reference=b.reference["u_y"], error=en, error_L2=l2, error_energy=en)

    return Problem(b.pot, b.bc, _h(m), evaluate)


def build_cantilever3d(m_depth, element):
    """10 × 1 × 1 tet cantilever, m_depth elements through the depth: mean end u_z against
    the Timoshenko beam deflection."""
    b = bm.cantilever3d(m_depth, **rc.element_kw(element))
    end, delta = b.probes["end"], b.reference["delta"]
    X = np.asarray(b.mesh.points)

    def evaluate(x):
        v = float(-np.mean(x[end, 2] - X[end, 2]))
        return dict(value=v, reference=delta, ratio=v / delta, error=abs(1 - v / delta))

    return Problem(b.pot, b.bc, _h(b.mesh), evaluate)


def build_uniaxial(k, element):
    """Neo-Hookean uniaxial tension (a = 1.5): lateral stretch and the nominal stress P₁₁
    from the reaction on x = 1."""
    import jax.numpy as jnp

    from jaxelastic import postprocess

    b = bm.uniaxial_tension(k, **rc.element_kw(element))
    m, ref = b.mesh, b.reference
    pull, corner = bm.pull_bc(m), int(b.probes["corner"][0])

    def evaluate(x):
        R = postprocess.reaction_force(b.psi, jnp.asarray(x), m, b.params, pull)
        P_num, b_num = float(R[0]), float(x[corner, 1])
        err = max(abs(b_num - ref["b"]) / ref["b"], abs(P_num - ref["P11"]) / ref["P11"])
        return dict(value=P_num, reference=ref["P11"], lateral_stretch=b_num, error=err)

    return Problem(b.pot, b.bc, _h(m), evaluate, steps=b.steps)


def build_shear(k, element):
    """Neo-Hookean simple shear (γ = 0.5): P₁₂ = μγ and Cauchy σ₁₁ = μγ² in every cell,
    interior nodes affine."""
    import jax
    import jax.numpy as jnp

    import jaxelastic as je

    b = bm.simple_shear(k, **rc.element_kw(element))
    m, P12, s11 = b.mesh, b.reference["P12"], b.reference["sigma11"]
    X = np.asarray(m.points)
    P_fn = jax.jit(jax.vmap(lambda F: je.first_piola(b.psi)(F, b.params)))

    def evaluate(x):
        F = np.asarray(je.kinematics.deformation_gradients(jnp.asarray(x), m)).reshape(-1, 3, 3)
        P = np.asarray(P_fn(jnp.asarray(F)))
        sig = np.einsum("cij,ckj->cik", P, F) / np.linalg.det(F)[:, None, None]
        e1 = np.abs(P[:, 0, 1] - P12).max() / P12
        e2 = np.abs(sig[:, 0, 0] - s11).max() / s11
        e3 = np.abs(x - X - b.exact(X)[0]).max()
        return dict(value=float(P[0, 0, 1]), reference=P12, error=max(e1, e2, e3))

    return Problem(b.pot, b.bc, _h(m), evaluate, steps=b.steps)


def build_patch(level, element):
    """Linear plane-stress MacNeal–Harder patch: σx = σy = 1333.3, τ = 400 in every
    element."""
    import jax.numpy as jnp

    import jaxelastic as je

    _p1_only(element, "MacNeal–Harder patch")
    b = bm.macneal_harder_patch()
    m, (mu, lam), ref = b.mesh, b.lame, b.reference
    exact = np.array([[ref["sxx"], ref["sxy"]], [ref["syx"], ref["syy"]]])

    def evaluate(x):
        F = np.asarray(je.kinematics.deformation_gradients(jnp.asarray(x), m))[:, 0]
        e = 0.5 * (F + np.swapaxes(F, 1, 2)) - np.eye(2)
        s = 2 * mu * e + lam * np.trace(e, axis1=1, axis2=2)[:, None, None] * np.eye(2)
        err = np.abs(s - exact).max() / 1333.3
        return dict(value=float(s[0, 0, 0]), reference=exact[0, 0], error=err)

    return Problem(b.pot, b.bc, 0.1, evaluate)


def build_patch_affine(model_index, element):
    """Nonlinear patch test: the boundary map x = F₀X + c must be reproduced exactly inside
    by every 2D built-in material (``level`` picks the model)."""
    import jaxelastic as je

    _p1_only(element, "MacNeal–Harder patch")
    models = [k for k in je.materials.BUILTIN if k != "stable_neo_hookean_log"]
    name = models[model_index]
    b = bm.affine_patch(name)
    X = np.asarray(b.mesh.points)
    xa = X + b.exact(X)[0]

    def evaluate(x):
        err = float(np.abs(x - xa).max() / 0.24)
        return dict(model=name, value=float(x[4, 0]), reference=float(xa[4, 0]), error=err)

    return Problem(b.pot, b.bc, 0.1, evaluate, steps=b.steps)


# ---- twist benchmark ------------------------------------------------------------------

_TWIST_REF: dict = {}


def twist_reference(n_ref: int):
    """Reference solution on a fine P2 mesh: ``(points, u, label)``."""
    if n_ref not in _TWIST_REF:
        import jaxelastic as je

        b = bm.twist(n_ref, order=2)
        r = je.solve(b.pot, b.bc, solver=je.Newton(rtol=1e-10, linear="amg"))
        X = np.asarray(b.mesh.points)
        _TWIST_REF[n_ref] = (X, np.asarray(r.x) - X, f"P2 n={n_ref}")
    return _TWIST_REF[n_ref]


def _match(Xc, Xf, tol=1e-9):
    """Index into Xf of each point of Xc (points must coincide)."""
    key = lambda P: np.round(P / tol).astype(np.int64)  # noqa: E731
    kf, kc = key(Xf), key(Xc)
    lookup = {tuple(k): i for i, k in enumerate(kf)}
    out = np.array([lookup.get(tuple(k), -1) for k in kc])
    if (out < 0).any():
        raise ValueError("coarse nodes are not nodes of the reference mesh")
    return out


def make_twist_case(n_ref: int):
    """The twist case's builder: vertex displacements against the fine reference."""

    def build(n, element):
        b = bm.twist(n, **rc.element_kw(element))
        Xr, ur, label = twist_reference(n_ref)
        X = np.asarray(b.mesh.points)
        # compare at the corner (vertex) nodes of the coarse mesh, which the fine one has
        verts = np.unique(np.asarray(b.mesh.cells)[:, :4])
        idx = _match(X[verts], Xr)
        scale = np.abs(ur).max()
        rms_ref = float(np.sqrt(np.mean(np.sum(ur[idx] ** 2, axis=1))))

        def evaluate(x):
            u = x[verts] - X[verts]
            d = np.linalg.norm(u - ur[idx], axis=1)
            # the max is set at the edges where the turned face meets the free surface (a
            # corner singularity): it converges slowly; the RMS is the headline error
            return dict(
                error=float(np.sqrt(np.mean(d**2)) / rms_ref),
                error_max=float(d.max() / scale),
                reference=label,
            )

        return Problem(b.pot, b.bc, _h(b.mesh), evaluate)

    return build


# --------------------------------------------------------------------------------------
# the case table
# --------------------------------------------------------------------------------------


def _cook_cases() -> list[Case]:
    """Cook's membrane, compressible and nearly incompressible (linear and neo-Hookean)."""
    return [
        Case(
            "cook",
            "Cook's membrane, linear plane stress",
            build_cook,
            {"P1": ((4, 8, 16, 32, 64, 128), (16, 32, 64)), "P2": ((2, 4, 8, 16, 32), (4, 8))},
            ("direct", "amg", "cg", "cg-jacobi", "cg-loose"),
            ("direct", "cg"),
            "|u_y(48,52) − 23.96| / 23.96",
            "23.96 (Cook 1974)",
        ),
        Case(
            "cook_nh",
            "Nearly incompressible neo-Hookean Cook (plane strain)",
            build_cook_nh,
            {
                "P1": ((4, 8, 16, 32), (8, 16)),
                "P2": ((2, 4, 8, 16), (4, 8)),
                "P2-Fbar": ((2, 4, 8, 16), (8, 16)),
                "P1-Fbar": ((2, 4, 8, 16), (8, 16)),
            },
            ("direct", "amg"),
            ("direct",),
            "|u_y(48,60) − 6.91| / 6.91",
            "6.91 (de Souza Neto et al. 1996)",
        ),
        Case(
            "cook_incompressible",
            "Nearly incompressible linear Cook (plane strain)",
            build_cook_incompressible,
            {
                "P1": ((4, 8, 16, 32, 64), (16, 32)),
                "P2": ((2, 4, 8, 16), (4, 8)),
                "P2-Bbar": ((2, 4, 8, 16), (4, 8)),
                "P1-Bbar": ((2, 4, 8, 16), (4, 8)),
            },
            ("direct", "amg", "cg"),
            ("direct",),
            "|u_y(48,52) − 16.43| / 16.43",
            "16.43 (Richardson-extrapolated)",
        ),
    ]


def _beam_cases() -> list[Case]:
    """The 2D Timoshenko–Goodier cantilever and the 3D tet cantilever."""
    return [
        Case(
            "timoshenko",
            "Timoshenko–Goodier cantilever, plane stress",
            build_timoshenko,
            {
                "P1": ((1, 2, 4, 8, 16, 32), (8, 16, 32)),
                "P2": ((1, 2, 4, 8, 16, 32, 64), (16, 32, 64)),
            },
            ("direct", "amg", "cg"),
            ("direct",),
            "relative energy-norm error",
            "exact field (Timoshenko & Goodier 1970)",
        ),
        Case(
            "cantilever3d",
            "3D tet cantilever 10×1×1 vs Timoshenko beam",
            build_cantilever3d,
            {"P1": ((1, 2, 4, 8), (1, 2)), "P2": ((1, 2, 4), (1, 2)), "P2-Bbar": ((1, 2), ())},
            ("amg", "cg"),
            ("direct",),
            "|1 − δ_FE/δ_beam|",
            "δ = PL³/(3EI) + PL/(κGA)",
        ),
    ]


def _exact_cases() -> list[Case]:
    """Homogeneous states and patch tests: exact up to round-off (no Pareto plot)."""

    def exact(name, title, build, levels, label, reference):
        return Case(
            name, title, build, levels, ("direct",), ("direct",), label, reference, pareto=False
        )

    return [
        exact(
            "uniaxial",
            "Neo-Hookean uniaxial tension (a = 1.5)",
            build_uniaxial,
            {"P1": ((1, 2, 3), (2,)), "P2": ((1, 2), (1,))},
            "max rel. error of lateral stretch and P₁₁",
            "closed form",
        ),
        exact(
            "shear",
            "Neo-Hookean simple shear (γ = 0.5)",
            build_shear,
            {"P1": ((2, 3), (2,)), "P2": ((1, 2), (1,))},
            "max rel. error of P₁₂ = μγ, σ₁₁ = μγ²",
            "closed form",
        ),
        exact(
            "patch",
            "MacNeal–Harder membrane patch (linear)",
            build_patch,
            {"P1": ((1,), (1,))},
            "max |σ − σ_exact| / 1333",
            "σx = σy = 1333.3, τ = 400",
        ),
        exact(
            "patch_affine",
            "Affine patch test, every 2D material",
            build_patch_affine,
            {"P1": (tuple(range(7)), tuple(range(7)))},
            "max |x − x_affine| / 0.24",
            "x = F₀X + c exactly",
        ),
    ]


def _twist_case(quick: bool) -> Case:
    """The JAX-FEM twist against a fine P2 reference (n = 8 quick, 16 full)."""
    twist_ref = 8 if quick else 16
    return Case(
        "twist",
        f"Twist benchmark vs fine reference (n = {twist_ref})",
        make_twist_case(twist_ref),
        {"P1": ((2, 4, 8), (2, 4)), "P2": ((2, 4), (2,))},
        ("direct", "amg", "cg", "cg-loose"),
        ("direct", "cg"),
        "RMS nodal |u − u_ref| / RMS |u_ref|",
        "fine-mesh solution",
    )


_CASE_ORDER = (
    "cook",
    "timoshenko",
    "cantilever3d",
    "uniaxial",
    "shear",
    "patch",
    "patch_affine",
    "twist",
    "cook_nh",
    "cook_incompressible",
)


def cases(quick: bool) -> dict:
    """Every case by name, in the report's order."""
    table = {c.name: c for c in _cook_cases() + _beam_cases() + _exact_cases()}
    table["twist"] = _twist_case(quick)
    return {name: table[name] for name in _CASE_ORDER}


# --------------------------------------------------------------------------------------
# report: run, rates, table, plots
# --------------------------------------------------------------------------------------


def run(
    out: str | Path = "out/report_accuracy",
    *,
    quick: bool = False,
    case_names=None,
    elements=None,
    solvers=None,
    levels=None,
    plots: bool = True,
    verbose: bool = True,
) -> dict:
    """Run the report and write its files; returns ``{"rows": [...], "rates": [...], ...}``.

    Args:
        out: output folder. quick: the smallest settings (the test suite's).
        case_names / elements / solvers: restrict the study (default: all of the mode).
        levels: override the refinement levels, ``{element: [levels]}`` or one list for all.
        plots: also write the PNG figures.
    """
    import jax

    jax.config.update("jax_enable_x64", True)
    table = cases(quick)
    names = list(table) if case_names is None else list(case_names)
    bad = [n for n in names if n not in table]
    if bad:
        raise ValueError(f"unknown case(s) {bad}; choose from {sorted(table)}")
    rows, skipped = [], []
    for name in names:
        case = table[name]
        for element, (full, quick_levels) in case.levels.items():
            if elements is not None and element not in elements:
                continue
            for solver in case.quick_solvers if quick else case.solvers:
                if solvers is not None and solver not in solvers:
                    continue
                lv = quick_levels if quick else full
                if levels is not None:
                    lv = levels.get(element, lv) if isinstance(levels, dict) else levels
                for level in lv:
                    r = run_row(case, level, element, solver)
                    rows.append(r)
                    if verbose:
                        _print_row(r)
        # partial results after every case (a long run interrupted keeps what it measured)
        rc.write_json(Path(out) / "accuracy.partial.json", dict(machine=rc.machine(), rows=rows))
    rates = convergence_rates(rows)
    result = dict(
        machine=rc.machine(),
        timing="run_s: warm second call (compile excluded); compile_s = cold − warm",
        quick=quick,
        cases={
            n: dict(title=table[n].title, error=table[n].error_label, reference=table[n].reference)
            for n in names
        },
        rows=rows,
        rates=rates,
        skipped=skipped,
    )
    out = Path(out)
    rc.write_json(out / "accuracy.json", result)
    (out / "accuracy.partial.json").unlink(missing_ok=True)
    rc.write_csv(out / "accuracy.csv", rows)
    if plots:
        result["figures"] = plot_all(result, out, table)
    if verbose:
        print("\nobserved rates (least squares over the levels of each sequence):")
        for r in rates:
            print(
                f"  {r['case']:<14} {r['element']:<8} {r['solver']:<10} {r['norm']:<8} "
                f"{r['rate']:6.2f} (levels {r['levels']})"
            )
        print(f"\nwrote {out / 'accuracy.json'}, {out / 'accuracy.csv'}")
    return result


_HDR = (
    f"{'case':<20} {'elem':<8} {'lvl':>4} {'solver':<10} {'dofs':>7} {'h':>8} {'error':>10} "
    f"{'value':>10} {'status':<9} {'newton':>6} {'lin':>6} {'compile s':>9} {'run s':>8}"
)
_printed_header = [False]


def _print_row(r):
    if not _printed_header[0]:
        print(_HDR)
        _printed_header[0] = True
    if r.get("status") in ("SKIPPED", "ERROR"):
        print(f"{r['case']:<20} {r['element']:<8} {r['level']:>4} {r['status']}: {r['reason']}")
        return
    val = r.get("value", float("nan"))
    val = val if isinstance(val, float) else float("nan")
    print(
        f"{r['case']:<20} {r['element']:<8} {r['level']:>4} {r['solver']:<10} {r['dofs']:>7} "
        f"{r['h']:>8.3g} {r.get('error', float('nan')):>10.3e} {val:>10.4g} "
        f"{r['status']:<9} {r['newton']:>6} {r['linear_its']:>6} {r['compile_s']:>9.2f} "
        f"{r['run_s']:>8.3f}"
    )


def convergence_rates(rows) -> list[dict]:
    """Observed rates d log(error)/d log(h) per (case, element, solver, norm)."""
    out = []
    groups: dict = {}
    for r in rows:
        if r.get("status") != "SUCCESS" or "error" not in r:
            continue
        groups.setdefault((r["case"], r["element"], r["solver"]), []).append(r)
    for (case, element, solver), rs in groups.items():
        if len(rs) < 2 or case.startswith("patch") or case in ("uniaxial", "shear"):
            continue
        norms = ["error_L2", "error_energy"] if "error_L2" in rs[0] else ["error"]
        for norm in norms:
            h = [r["h"] for r in rs]
            e = [r[norm] for r in rs]
            last = rc.rate(h[-2:], e[-2:])
            out.append(
                dict(
                    case=case,
                    element=element,
                    solver=solver,
                    norm=norm.replace("error_", "") or "error",
                    rate=rc.rate(h, e),
                    rate_last=last,
                    levels=[r["level"] for r in rs],
                )
            )
    return out


_MARKERS = {
    "direct": "o",
    "amg": "s",
    "cg": "^",
    "cg-jacobi": "v",
    "cg-loose": "D",
    "direct-loose": "P",
}
_COLORS = {
    "P1": "C0",
    "P2": "C3",
    "P2-Fbar": "C2",
    "P1-Fbar": "C1",
    "P2-Bbar": "C2",
    "P1-Bbar": "C1",
}


def _pareto_axes(ax, rows, title, ylabel, machine):
    good = [r for r in rows if r.get("status") == "SUCCESS" and np.isfinite(r.get("error", np.nan))]
    series: dict = {}
    for r in good:
        series.setdefault((r["element"], r["solver"]), []).append(r)
    for (el, sv), rs in sorted(series.items()):
        rs = sorted(rs, key=lambda r: r["h"], reverse=True)
        t = [r["run_s"] for r in rs]
        e = [max(r["error"], 1e-16) for r in rs]
        ax.loglog(
            t,
            e,
            marker=_MARKERS.get(sv, "o"),
            color=_COLORS.get(el, "k"),
            lw=0.8,
            ms=5,
            alpha=0.85,
            label=f"{el} {sv}",
        )
    if good:
        t = np.array([r["run_s"] for r in good])
        e = np.array([max(r["error"], 1e-16) for r in good])
        f = rc.pareto(t, e)
        if f.size:
            # a wide grey band under the series: the front runs along their points, and a
            # thin line on top of them would hide (or be hidden by) the series' lines
            ax.step(
                t[f],
                e[f],
                where="post",
                color="0.55",
                lw=7,
                alpha=0.4,
                zorder=0,
                solid_capstyle="round",
                label="Pareto front",
            )
    from matplotlib.ticker import NullFormatter

    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("warm wall time [s] (compile excluded)")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize="medium")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize="x-small", ncol=2)


def plot_all(result, out: Path, table) -> list[str]:
    """One error-vs-time PNG per case with a discretisation error, plus a summary grid."""
    from jaxelastic.plot import new_axes

    machine = result["machine"]
    names = [n for n in result["cases"] if table[n].pareto]
    files = []
    for name in names:
        rows = [r for r in result["rows"] if r["case"] == name]
        if not any(r.get("status") == "SUCCESS" for r in rows):
            continue
        fig, ax = new_axes(1, figsize=(6.4, 4.6))
        _pareto_axes(ax, rows, table[name].title, table[name].error_label, machine)
        fig.text(0.01, -0.02, f"{machine}; compile time excluded (warm second call)", fontsize=7)
        path = out / f"error_vs_time_{name}.png"
        rc.save_figure(fig, path)
        files.append(str(path))
    shown = [
        n
        for n in names
        if any(r["case"] == n and r.get("status") == "SUCCESS" for r in result["rows"])
    ]
    if shown:
        ncol = min(3, len(shown))
        nrow = -(-len(shown) // ncol)
        from matplotlib.figure import Figure

        fig = Figure(figsize=(5.2 * ncol, 4.0 * nrow))
        axs = fig.subplots(nrow, ncol, squeeze=False)
        for ax, name in zip(axs.ravel(), shown, strict=False):
            rows = [r for r in result["rows"] if r["case"] == name]
            _pareto_axes(ax, rows, table[name].title, table[name].error_label, machine)
        for ax in axs.ravel()[len(shown) :]:
            ax.set_visible(False)
        fig.suptitle(f"Error against run time — {machine}; compile time excluded", fontsize=10)
        fig.tight_layout()
        path = out / "error_vs_time_summary.png"
        rc.save_figure(fig, path)
        files.append(str(path))
    return files


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", default="out/report_accuracy")
    ap.add_argument("--quick", action="store_true", help="smallest settings (as the tests)")
    ap.add_argument("--cases", default=None, help="comma-separated case names")
    ap.add_argument(
        "--elements", default=None, help="comma-separated: P1,P2,P2-Fbar,P1-Fbar,P2-Bbar,P1-Bbar"
    )
    ap.add_argument("--solvers", default=None, help=f"comma-separated: {','.join(SOLVERS)}")
    ap.add_argument("--no-plots", action="store_true")
    a = ap.parse_args(argv)
    split = lambda s: None if s is None else [v.strip() for v in s.split(",") if v.strip()]  # noqa: E731
    run(
        a.out,
        quick=a.quick,
        case_names=split(a.cases),
        elements=split(a.elements),
        solvers=split(a.solvers),
        plots=not a.no_plots,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
