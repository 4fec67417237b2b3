"""Accuracy against known answers, and error against run time.

For every case: a refinement sequence × element variant (P1, P2, F-bar; see
``_report_common.ELEMENT_KW``) × solver setting (linear solver, preconditioner, Newton
tolerance), with the error, mesh size h, dofs, wall time split into compilation (cold call
minus warm call) and run (the warm second call, same compiled code), Newton and linear
iterations. Cases (REFERENCES in the README section "Accuracy, error against run time,
stability"):

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
* ``twist``: the twist benchmark of ``scripts/bench_solvers.py`` against a fine reference.
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

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _report_common as rc  # noqa: E402

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


def _solve_twice(prob: Problem, spec: SolverSpec):
    """Cold and warm solves; returns (x, stats) with the warm call's statistics."""
    from jaxelastic.solvers.continuation import solve_incremental
    from jaxelastic.solvers.newton import NewtonSettings, Status, make_linear, solve

    settings = NewtonSettings(
        rtol=spec.rtol, preconditioner=spec.preconditioner, max_steps=prob.max_steps
    )
    linear = make_linear(prob.pot.mesh, prob.bc, spec.linear)  # pattern analysis: cold only

    def go():
        if prob.steps:
            r = solve_incremental(
                prob.pot, prob.bc, steps=prob.steps, settings=settings, linear=linear, throw=False
            )
            hist = r.history
            return r.x, dict(
                status=Status(r.status).name,
                newton=sum(h["newton_steps"] for h in hist),
                linear_its=sum(h["linear_iterations"] for h in hist),
                increments=len(hist),
            )
        r = solve(prob.pot, prob.bc, settings=settings, linear=linear, throw=False)
        return r.x, dict(
            status=Status(int(r.status)).name,
            newton=int(r.steps),
            linear_its=int(r.linear_iterations),
            increments=1,
        )

    t0 = time.perf_counter()
    go()
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    x, st = go()
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
# helpers: probes, consistent 2D edge loads, error norms by quadrature
# --------------------------------------------------------------------------------------


def _node_at(mesh, point, tol=1e-8) -> int:
    X = np.asarray(mesh.points)
    d = np.linalg.norm(X - np.asarray(point, float), axis=1)
    i = int(np.argmin(d))
    if d[i] > tol * max(1.0, float(np.ptp(X))):
        raise ValueError(f"no node at {point} (nearest {X[i]})")
    return i


def _gauss01(n):
    p, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (p + 1.0), 0.5 * w


def _edge_load_2d(mesh, facets, t_fn, n_gauss=5) -> np.ndarray:
    """Consistent nodal forces ∫ N_a t(X) ds of a traction field on 2D boundary facets.

    Facets are ``(m, 2)`` (P1), ``(m, 3)`` (corner, corner, mid: P2, or composite P1 whose
    field is linear on each half). Gauss–Legendre per (half-)edge; ``t_fn(X (k, 2)) ->
    (k, 2)`` [force/length].
    """
    X = np.asarray(mesh.points)
    facets = np.asarray(facets)
    f = np.zeros_like(X)
    s, w = _gauss01(n_gauss)
    composite = mesh.element_type.is_composite if facets.shape[1] == 3 else False
    if facets.shape[1] == 2:
        segs = [(s, w, np.stack([1 - s, s], 1))]
    elif composite:
        a, b = 0.5 * s, 0.5 + 0.5 * s
        z = np.zeros_like(s)
        segs = [
            (a, 0.5 * w, np.stack([1 - 2 * a, z, 2 * a], 1)),
            (b, 0.5 * w, np.stack([z, 2 * b - 1, 2 - 2 * b], 1)),
        ]
    else:
        segs = [(s, w, np.stack([(1 - s) * (1 - 2 * s), s * (2 * s - 1), 4 * s * (1 - s)], 1))]
    A, B = X[facets[:, 0]], X[facets[:, 1]]
    length = np.linalg.norm(B - A, axis=1)
    for sq, wq, N in segs:
        for k in range(sq.size):
            Xq = A + sq[k] * (B - A)
            t = np.asarray(t_fn(Xq), float)
            for a in range(facets.shape[1]):
                np.add.at(f, facets[:, a], (wq[k] * N[k, a] * length)[:, None] * t)
    return f


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
    from jaxelastic.elements import get_element

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


# --------------------------------------------------------------------------------------
# cases
# --------------------------------------------------------------------------------------


def _cook_problem(n, element, *, psi, params, total, point, ref, steps=0):
    """Cook's membrane: clamped on x = 0, uniform vertical shear totalling ``total`` on
    x = 48; the score is u_y at ``point`` against ``ref``."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads

    m = rc.make_mesh(je.mesh.cook_membrane, n, element=element)
    facets = loads.facets_where(m, lambda X: np.abs(X[:, 0] - 48.0) < 1e-9)
    f = loads.traction_load(m, facets, [0.0, total / 16.0])
    bc = loads.fix(m, loads.nodes_on_plane(m, 0, 0.0))
    pot = je.Potential(mesh=m, params=params, f_ext=jnp.asarray(f), psi=psi)
    i = _node_at(m, point)
    X = np.asarray(m.points)

    def evaluate(x):
        v = float(x[i, 1] - X[i, 1])
        return dict(value=v, reference=ref, error=abs(v - ref) / ref)

    return Problem(pot, bc, _h(m), evaluate, steps=steps)


def build_cook(n, element):
    """Cook's membrane, linear, plane stress; u_y(48, 52) against 23.96."""
    import jaxelastic as je

    p = je.Lame(*je.lame(1.0, 1.0 / 3.0, dim=2, plane="stress"))
    return _cook_problem(
        n, element, psi=je.materials.linear, params=p, total=1.0, point=(48, 52), ref=23.96
    )


def build_cook_incompressible(n, element):
    """Nearly incompressible linear Cook (plane strain, G = 0.375, λ = 7500): u_y(48, 52)
    against 16.43. The locking-free variants here are B-bar (Hughes 1980), the small-strain
    form of F-bar: F-bar's kinematics are nonlinear, and u ≈ 16 on a 48-long body is a large
    rotation, so F-bar with the linear ψ answers a different (geometrically nonlinear)
    question."""
    import jaxelastic as je

    p = je.Lame(0.375, 7500.0)
    return _cook_problem(
        n, element, psi=je.materials.linear, params=p, total=1.0, point=(48, 52), ref=16.43
    )


def build_cook_nh(n, element):
    """Nearly incompressible neo-Hookean Cook (plane strain, G = 80.1938, K = 40.0942e4,
    λ = K − 2G/3, load 100): u_y(48, 60) against 6.91."""
    import jaxelastic as je

    G, K = 80.1938, 40.0942e4
    p = je.Lame(G, K - 2.0 * G / 3.0)
    return _cook_problem(
        n,
        element,
        psi=je.materials.neo_hookean,
        params=p,
        total=100.0,
        point=(48, 60),
        ref=6.91,
        steps=2,
    )


TG = dict(L=48.0, D=12.0, E=3.0e7, nu=0.3, P=1000.0)


def timoshenko_exact(X, L=48.0, D=12.0, E=3.0e7, nu=0.3, P=1000.0):
    """Exact plane-stress displacement ``(k, 2)`` and gradient ``(k, 2, 2)`` of the
    end-loaded cantilever (Timoshenko & Goodier 1970, §21), origin at the mid-depth of
    x = 0, load P upward at x = L."""
    x, y = X[:, 0], X[:, 1]
    I = D**3 / 12.0
    c = P / (6.0 * E * I)
    ux = -c * y * ((6 * L - 3 * x) * x + (2 + nu) * (y**2 - D**2 / 4))
    uy = c * (3 * nu * y**2 * (L - x) + (4 + 5 * nu) * D**2 * x / 4 + (3 * L - x) * x**2)
    g = np.empty((x.size, 2, 2))
    g[:, 0, 0] = -c * y * (6 * L - 6 * x)
    g[:, 0, 1] = -c * ((6 * L - 3 * x) * x + (2 + nu) * (3 * y**2 - D**2 / 4))
    g[:, 1, 0] = c * (-3 * nu * y**2 + (4 + 5 * nu) * D**2 / 4 + 6 * L * x - 3 * x**2)
    g[:, 1, 1] = c * 6 * nu * y * (L - x)
    return np.stack([ux, uy], 1), g


def build_timoshenko(k, element):
    """Timoshenko–Goodier cantilever on a 4k × k rectangle mesh; exact field on x = 0,
    parabolic shear traction τ = P/(2I)(D²/4 − y²) on x = L."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads

    L, D, E, nu, P = (TG[k_] for k_ in ("L", "D", "E", "nu", "P"))
    m = rc.make_mesh(je.mesh.rectangle, 4 * k, k, (L, D), (0.0, -D / 2), element=element)
    I = D**3 / 12.0
    facets = loads.facets_where(m, lambda X: np.abs(X[:, 0] - L) < 1e-9)

    def t(Xq):
        return np.stack([0 * Xq[:, 1], P / (2 * I) * (D**2 / 4 - Xq[:, 1] ** 2)], 1)

    f = _edge_load_2d(m, facets, t)
    bc = loads.fix(
        m, loads.nodes_on_plane(m, 0, 0.0), displacement=lambda X: timoshenko_exact(X)[0]
    )
    mu, lam = je.lame(E, nu, dim=2, plane="stress")
    pot = je.Potential(
        mesh=m, params=je.Lame(mu, lam), f_ext=jnp.asarray(f), psi=je.materials.linear
    )
    # u_y(L, y) of the exact field does not depend on y: score the mean over the end nodes
    tip = loads.nodes_on_plane(m, 0, L)
    X = np.asarray(m.points)
    tip_exact = float(timoshenko_exact(X[tip[:1]])[0][0, 1])

    def evaluate(x):
        l2, en = error_norms_2d(
            m, x, lambda Z: timoshenko_exact(Z)[0], lambda Z: timoshenko_exact(Z)[1], mu, lam
        )
        v = float(np.mean(x[tip, 1] - X[tip, 1]))
        return dict(value=v, reference=tip_exact, error=en, error_L2=l2, error_energy=en)

    return Problem(pot, bc, _h(m), evaluate)


CANTILEVER = dict(L=10.0, D=1.0, E=1000.0, nu=0.3, P=1.0)


def beam_deflection(L=10.0, D=1.0, E=1000.0, nu=0.3, P=1.0) -> float:
    """Timoshenko beam tip deflection of a square D × D section: PL³/(3EI) + PL/(κGA),
    κ = 10(1+ν)/(12+11ν) (Cowper 1966)."""
    I, A, G = D**4 / 12.0, D * D, E / (2 * (1 + nu))
    kappa = 10 * (1 + nu) / (12 + 11 * nu)
    return P * L**3 / (3 * E * I) + P * L / (kappa * G * A)


def build_cantilever3d(m_depth, element):
    """10 × 1 × 1 tet cantilever, cube cells, m_depth elements through the depth; clamped
    at x = 0, uniform shear traction totalling P on x = L; mean u_z of the end face.

    The material is ``linear`` (the tip deflection is 0.4 L, so any finite-strain kinematics,
    F-bar included, would answer a geometrically nonlinear question: use B-bar here)."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads

    L, D, E, nu, P = (CANTILEVER[k] for k in ("L", "D", "E", "nu", "P"))
    md = m_depth
    m = rc.make_mesh(je.mesh.box, int(round(L / D)) * md, md, md, (L, D, D), element=element)
    facets = loads.facets_where(m, lambda X: np.abs(X[:, 0] - L) < 1e-9)
    f = loads.traction_load(m, facets, [0.0, 0.0, -P / (D * D)])
    bc = loads.fix(m, loads.nodes_on_plane(m, 0, 0.0))
    mu, lam = je.lame(E, nu)
    pot = je.Potential(
        mesh=m, params=je.Lame(mu, lam), f_ext=jnp.asarray(f), psi=je.materials.linear
    )
    end = loads.nodes_on_plane(m, 0, L)
    X = np.asarray(m.points)
    delta = beam_deflection(L, D, E, nu, P)

    def evaluate(x):
        v = float(-np.mean(x[end, 2] - X[end, 2]))
        return dict(value=v, reference=delta, ratio=v / delta, error=abs(1 - v / delta))

    return Problem(pot, bc, _h(m), evaluate)


def build_uniaxial(k, element):
    """Neo-Hookean unit cube (k³ cubes), stretch a = 1.5 along x with symmetry planes and
    free lateral faces: lateral stretch b from μ(b² − 1) + λ ln(a b²) = 0 and nominal stress
    P₁₁ = μ(a − b²/a) from the reaction on x = 1."""
    from scipy.optimize import brentq

    import jaxelastic as je
    from jaxelastic import loads

    a = 1.5
    m = rc.make_mesh(je.mesh.box, k, k, k, element=element)
    mu, lam = je.lame(1000.0, 0.3)
    params = je.Lame(mu, lam)
    sym = [loads.fix(m, loads.nodes_on_plane(m, ax, 0.0), components=(ax,)) for ax in range(3)]
    pull = loads.fix(
        m, loads.nodes_on_plane(m, 0, 1.0), components=(0,), displacement=[a - 1, 0, 0]
    )
    bc = loads.combine(*sym, pull)
    pot = je.Potential(mesh=m, params=params, psi=je.materials.neo_hookean)
    b = brentq(lambda b: mu * (b * b - 1) + lam * np.log(a * b * b), 0.2, 1.0)
    P11 = mu * (a - b * b / a)
    corner = _node_at(m, (1.0, 1.0, 1.0))

    def evaluate(x):
        import jax.numpy as jnp

        R = loads.reaction_force(je.materials.neo_hookean, jnp.asarray(x), m, params, pull)
        P_num = float(R[0])
        b_num = float(x[corner, 1])
        err = max(abs(b_num - b) / b, abs(P_num - P11) / P11)
        return dict(value=P_num, reference=P11, lateral_stretch=b_num, error=err)

    return Problem(pot, bc, _h(m), evaluate, steps=2)


def build_shear(k, element):
    """Simple shear x = X + γ Y e₁ (γ = 0.5) on the boundary of a neo-Hookean unit cube:
    P₁₂ = μγ and Cauchy σ₁₁ = μγ² (Poynting effect) in every cell, interior nodes affine."""
    import jax
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads

    g = 0.5
    m = rc.make_mesh(je.mesh.box, k, k, k, element=element)
    mu, lam = je.lame(1000.0, 0.3)
    params = je.Lame(mu, lam)
    bnd = je.mesh.boundary_nodes(m)
    bc = loads.fix(
        m, bnd, displacement=lambda X: np.stack([g * X[:, 1], 0 * X[:, 1], 0 * X[:, 1]], 1)
    )
    pot = je.Potential(mesh=m, params=params, psi=je.materials.neo_hookean)
    X = np.asarray(m.points)
    P_fn = jax.jit(jax.vmap(lambda F: je.first_piola(je.materials.neo_hookean)(F, params)))

    def evaluate(x):
        F = np.asarray(je.deformation_gradients(jnp.asarray(x), m)).reshape(-1, 3, 3)
        P = np.asarray(P_fn(jnp.asarray(F)))
        sig = np.einsum("cij,ckj->cik", P, F) / np.linalg.det(F)[:, None, None]
        e1 = np.abs(P[:, 0, 1] - mu * g).max() / (mu * g)
        e2 = np.abs(sig[:, 0, 0] - mu * g * g).max() / (mu * g * g)
        e3 = np.abs(x[:, 0] - X[:, 0] - g * X[:, 1]).max()
        return dict(value=float(P[0, 0, 1]), reference=mu * g, error=max(e1, e2, e3))

    return Problem(pot, bc, _h(m), evaluate, steps=1)


MH_POINTS = np.array(
    [
        [0, 0],
        [0.24, 0],
        [0.24, 0.12],
        [0, 0.12],
        [0.04, 0.02],
        [0.18, 0.03],
        [0.16, 0.08],
        [0.08, 0.08],
    ]
)
MH_QUADS = [(0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7), (4, 5, 6, 7)]


def patch_mesh():
    """MacNeal & Harder (1985) membrane patch: 5 quadrilaterals split into 10 triangles."""
    import jaxelastic as je

    tris = [t for a, b, c, d in MH_QUADS for t in ((a, b, c), (a, c, d))]
    return je.from_arrays(MH_POINTS, np.array(tris), "tri3")


def build_patch(level, element):
    """Linear plane-stress patch test: u = 1e-3(x + y/2), v = 1e-3(y + x/2) on the outer
    corners gives σx = σy = 1333.3, τ = 400 in every element (E = 1e6, ν = 0.25)."""
    import jaxelastic as je
    from jaxelastic import loads

    if element != "P1":
        raise rc.Unavailable("the MacNeal–Harder patch is defined on P1 here")
    m = patch_mesh()
    mu, lam = je.lame(1.0e6, 0.25, dim=2, plane="stress")
    bc = loads.fix(
        m,
        [0, 1, 2, 3],
        displacement=lambda X: 1e-3 * np.stack([X[:, 0] + X[:, 1] / 2, X[:, 1] + X[:, 0] / 2], 1),
    )
    pot = je.Potential(mesh=m, params=je.Lame(mu, lam), psi=je.materials.linear)

    def evaluate(x):
        import jax.numpy as jnp

        F = np.asarray(je.deformation_gradients(jnp.asarray(x), m))[:, 0]
        e = 0.5 * (F + np.swapaxes(F, 1, 2)) - np.eye(2)
        s = 2 * mu * e + lam * np.trace(e, axis1=1, axis2=2)[:, None, None] * np.eye(2)
        exact = np.array([[4000.0 / 3.0, 400.0], [400.0, 4000.0 / 3.0]])
        return dict(
            value=float(s[0, 0, 0]), reference=exact[0, 0], error=np.abs(s - exact).max() / 1333.3
        )

    return Problem(pot, bc, 0.1, evaluate)


def build_patch_affine(model_index, element):
    """Nonlinear patch test: the boundary map x = F₀X + c on the MacNeal–Harder patch must
    be reproduced exactly inside by every 2D built-in material (``level`` picks the model)."""
    import jaxelastic as je
    from jaxelastic import loads

    if element != "P1":
        raise rc.Unavailable("the MacNeal–Harder patch is defined on P1 here")
    models = [k for k in je.materials.BUILTIN if k != "stable_neo_hookean_log"]
    name = models[model_index]
    m = patch_mesh()
    F0 = np.array([[1.3, 0.2], [-0.1, 0.8]])
    c = np.array([0.01, -0.02])

    def affine(X):
        return X @ F0.T + c

    bc = loads.fix(m, [0, 1, 2, 3], displacement=lambda X: affine(X) - X)
    pot = je.Potential(
        mesh=m, params=je.Lame(*je.lame(1.0e6, 0.25, dim=2)), psi=je.materials.BUILTIN[name]
    )
    X = np.asarray(m.points)

    def evaluate(x):
        return dict(
            model=name,
            value=float(x[4, 0]),
            reference=float(affine(X)[4, 0]),
            error=float(np.abs(x - affine(X)).max() / 0.24),
        )

    return Problem(pot, bc, 0.1, evaluate, steps=1)


# ---- twist benchmark ------------------------------------------------------------------

TWIST_THETA = np.pi / 3


def twist_u(X):
    """Prescribed displacement of the x = 0 face of the twist benchmark: half of a 60°
    rotation about the x axis through (y, z) = (0.5, 0.5) (as ``bench_solvers.py``)."""
    th = TWIST_THETA
    y, z = X[:, 1], X[:, 2]
    return np.stack(
        [
            0 * y,
            (0.5 + (y - 0.5) * np.cos(th) - (z - 0.5) * np.sin(th) - y) / 2,
            (0.5 + (y - 0.5) * np.sin(th) + (z - 0.5) * np.cos(th) - z) / 2,
        ],
        1,
    )


def twist_problem(n, element="P1"):
    """(mesh, pot, bc) of the twist benchmark; P1 is ``bench_solvers._twist_problem``."""
    import bench_solvers

    from jaxelastic import loads, mesh

    _, pot1, bc1 = bench_solvers._twist_problem(n if element == "P1" else 1)
    if element == "P1":
        return pot1.mesh, pot1, bc1
    m = rc.make_mesh(mesh.box, n, n, n, element=element)
    bc = loads.combine(
        loads.fix(m, loads.nodes_on_plane(m, 0, 1.0)),
        loads.fix(m, loads.nodes_on_plane(m, 0, 0.0), displacement=twist_u),
    )
    return m, pot1.replace(mesh=m), bc


_TWIST_REF: dict = {}


def twist_reference(n_ref: int):
    """Reference solution on a fine mesh (P2 when available, else P1): ``(points, u)``."""
    if n_ref not in _TWIST_REF:
        from jaxelastic.solvers.newton import NewtonSettings, solve

        element = "P2" if rc.element_support()[0] else "P1"
        m, pot, bc = twist_problem(n_ref, element)
        r = solve(pot, bc, settings=NewtonSettings(rtol=1e-10), linear="amg")
        X = np.asarray(m.points)
        _TWIST_REF[n_ref] = (X, np.asarray(r.x) - X, f"{element} n={n_ref}")
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
    def build(n, element):
        m, pot, bc = twist_problem(n, element)
        Xr, ur, label = twist_reference(n_ref)
        X = np.asarray(m.points)
        # compare at the corner (vertex) nodes of the coarse mesh, which the fine one has
        verts = np.unique(np.asarray(m.cells)[:, :4])
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

        return Problem(pot, bc, _h(m), evaluate)

    return build


# --------------------------------------------------------------------------------------
# the case table
# --------------------------------------------------------------------------------------

_ALL_ELEMENTS = ("P1", "P2", "P2-Fbar", "P1-Fbar")


def cases(quick: bool) -> dict:
    twist_ref = 8 if quick else 16
    return {
        c.name: c
        for c in [
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
            Case(
                "uniaxial",
                "Neo-Hookean uniaxial tension (a = 1.5)",
                build_uniaxial,
                {"P1": ((1, 2, 3), (2,)), "P2": ((1, 2), (1,))},
                ("direct",),
                ("direct",),
                "max rel. error of lateral stretch and P₁₁",
                "closed form",
                pareto=False,
            ),
            Case(
                "shear",
                "Neo-Hookean simple shear (γ = 0.5)",
                build_shear,
                {"P1": ((2, 3), (2,)), "P2": ((1, 2), (1,))},
                ("direct",),
                ("direct",),
                "max rel. error of P₁₂ = μγ, σ₁₁ = μγ²",
                "closed form",
                pareto=False,
            ),
            Case(
                "patch",
                "MacNeal–Harder membrane patch (linear)",
                build_patch,
                {"P1": ((1,), (1,))},
                ("direct",),
                ("direct",),
                "max |σ − σ_exact| / 1333",
                "σx = σy = 1333.3, τ = 400",
                pareto=False,
            ),
            Case(
                "patch_affine",
                "Affine patch test, every 2D material",
                build_patch_affine,
                {"P1": (tuple(range(7)), tuple(range(7)))},
                ("direct",),
                ("direct",),
                "max |x − x_affine| / 0.24",
                "x = F₀X + c exactly",
                pareto=False,
            ),
            Case(
                "twist",
                f"Twist benchmark vs fine reference (n = {twist_ref})",
                make_twist_case(twist_ref),
                {"P1": ((2, 4, 8), (2, 4)), "P2": ((2, 4), (2,))},
                ("direct", "amg", "cg", "cg-loose"),
                ("direct", "cg"),
                "RMS nodal |u − u_ref| / RMS |u_ref|",
                "fine-mesh solution",
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
    }


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
    avail, why = rc.element_support()
    for name in names:
        case = table[name]
        for element, (full, quick_levels) in case.levels.items():
            if elements is not None and element not in elements:
                continue
            if element != "P1" and not avail:
                skipped.append(dict(case=name, element=element, reason=why))
                if verbose:
                    print(f"[skip] {name} {element}: {why}")
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
            ax.step(t[f], e[f], where="post", color="k", lw=1.5, alpha=0.6, label="Pareto front")
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
