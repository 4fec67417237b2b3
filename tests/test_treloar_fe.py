"""Treloar's (1944) data fitted through 3D finite-element specimens: a unit block in
uniaxial tension, an equibiaxial sheet and a pure-shear strip, each one cube of six P1
tets with symmetry (roller) supports on the planes x = 0, y = 0, z = 0.

With roller supports the homogeneous deformation F = diag(λ₁, λ₂, λ₃) satisfies every
boundary condition and equilibrium exactly, and P1 tets represent it exactly (one F in
every cell): the support reaction on the pulled face of unit rest area is the nominal
stress P₁₁ of the compressible homogeneous test at the same bulk modulus κ. Each level's
support force is observed with σ = |P_data| (relative weighting, the residual of
:func:`jaxelastic.fitting.fit_curves`), so the finite-element fit (:class:`LoadPathCase`,
Levenberg–Marquardt on forward-mode Jacobians through the solves) minimises the same χ²
as the homogeneous compressible fit and must find the same parameters (≤ 1e-4 relative),
from a start 5 % away from them. The gap to the exactly incompressible fit (the κ → ∞
limit) is O(1/κ).

Ogden's six constants sit in a flat valley of χ² (standard errors up to 80 % of μ₂): its
optimum is resolved to 1e-4 only when the cost is resolved to ~1e-10 relative, so its
specimens use the law's own κ = 1000 μ (a round-off floor of the forces 250 times lower
than at κ = 10⁵ MPa) and a Newton force floor of 1e-11 N.
"""

import time

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
import jaxelastic.materials as M
from jaxelastic import fitting as F
from jaxelastic import loads as L
from jaxelastic.verification import TRELOAR

KAPPA = 1e5  # MPa: ≈ 5·10⁵ times the fitted shear moduli

# Newton with an absolute force floor [N]: at κ = 10⁵ MPa the residual of the stretched
# sheet stagnates at round-off (~κ·eps) above rtol × a small warm-start residual
SOLVER = je.Newton(rtol=1e-11, atol=1e-8)

# library law, its default constants, the transforms (Mooney–Rivlin with c01 ≥ 0)
MODELS = {
    "mooney_rivlin": (
        M.mooney_rivlin,
        M.mooney_rivlin_params(kappa=KAPPA),
        M.MooneyRivlin(F.Positive(), F.Positive(), F.Fixed()),
    ),
    "yeoh": (
        M.yeoh,
        M.yeoh_params(kappa=KAPPA),
        M.Yeoh(F.Free(), F.Free(), F.Free(), F.Fixed()),
    ),
    "gent": (M.gent, M.gent_params(kappa=KAPPA), M.Gent(F.Positive(), F.Positive(), F.Fixed())),
    "arruda_boyce": (
        M.arruda_boyce,
        M.arruda_boyce_params(kappa=KAPPA),
        M.ArrudaBoyce(F.Positive(), F.Positive(), F.Fixed()),
    ),
    "ogden": (M.ogden, M.ogden_params(), M.Ogden(*[F.Free()] * 6, F.Fixed())),  # κ = 1000 μ
}
SOLVERS = {"ogden": je.Newton(rtol=1e-11, atol=1e-11)}  # κ = 414 MPa: a lower floor


def specimen(test, stretch, stress, psi, params):
    """A LoadPathCase of one Treloar curve: a unit cube pulled along x to each stretch
    (and along y too in equibiaxial tension; y held in pure shear), observed by the
    support force along x on the pulled face (rest area 1, so force = nominal stress)."""
    mesh = je.box(1, 1, 1)

    def on(axis, value):
        return L.nodes_on_plane(mesh, axis, value)

    lmax = float(np.max(stretch))
    bcs = [L.fix(mesh, on(a, 0.0), components=(a,)) for a in range(3)]  # symmetry planes
    pulled = on(0, 1.0)
    bcs.append(L.fix(mesh, pulled, components=(0,), displacement=[lmax - 1.0, 0.0, 0.0]))
    if test == "equibiaxial":
        bcs.append(L.fix(mesh, on(1, 1.0), components=(1,), displacement=[0.0, lmax - 1.0, 0.0]))
    elif test == "pure_shear":
        bcs.append(L.fix(mesh, on(1, 1.0), components=(1,)))  # lateral stretch held at 1
    pot = je.Potential(mesh, params, psi=psi)
    force = F.Reaction(
        jnp.asarray(pulled),
        jnp.asarray([1.0, 0.0, 0.0]),
        jnp.asarray(stress),
        jnp.asarray(np.abs(stress)),
    )
    factors = (np.asarray(stretch) - 1.0) / (lmax - 1.0)
    return F.LoadPathCase(pot, L.combine(*bcs), factors, (force,))


def fe_fit(model, optimizer="lm"):
    """(FE fit, homogeneous compressible fit, homogeneous incompressible fit, seconds)."""
    psi, init, tr = MODELS[model]
    curves = [F.stress_curve(c.test, c.stretch, c.stress) for c in TRELOAR]
    lm = F.LMSettings(rtol=1e-10)  # tighter stalls Ogden's flat optimum (cost at roundoff)
    sharp = F.FreeStretchNewton(xtol=1e-14)  # the free stretch to ~64 ulps
    comp = F.fit_curves(
        psi, init, curves, transforms=tr, incompressible=False, settings=lm, newton=sharp
    )
    inc = F.fit_curves(psi, init, curves, transforms=tr, settings=lm)
    assert comp.converged and inc.converged
    start = init._replace(**{k: 1.05 * v for k, v in comp.values.items()})  # 5 % away
    cases = [specimen(c.test, c.stretch, c.stress, psi, init) for c in curves]
    tic = time.perf_counter()
    opt = lm if optimizer == "lm" else optimizer
    solver = SOLVERS.get(model, SOLVER)
    res = F.fit(cases, start, transforms=tr, optimizer=opt, max_iter=300, gtol=1e-12, solver=solver)
    return res, comp, inc, curves, time.perf_counter() - tic


@pytest.mark.extended
@pytest.mark.parametrize("model", list(MODELS))
def test_treloar_fe_fit_matches_the_homogeneous_compressible_fit(model):
    res, comp, inc, curves, seconds = fe_fit(model)
    assert res.converged, res.stop_reason
    assert res.names == comp.names
    fe = np.array([getattr(res.material, k) for k in comp.names], dtype=float)
    hc = np.array([comp.values[k] for k in comp.names])
    hi = np.array([inc.values[k] for k in comp.names])
    to_comp, to_inc = fe / hc - 1.0, fe / hi - 1.0
    print(f"\n{model}: {dict(zip(comp.names, fe.tolist(), strict=True))}")
    print(f"  FE / homogeneous compressible - 1: {to_comp.tolist()}")
    print(f"  FE / homogeneous incompressible - 1: {to_inc.tolist()}")
    print(f"  FE fit: {res.iterations} iterations, {seconds:.1f} s ({res.stop_reason})")
    np.testing.assert_allclose(fe, hc, rtol=1e-4)
    # the specimens are homogeneous: the FE forces are the compressible homogeneous
    # stresses at the FE parameters (to the Newton tolerance: atol 1e-8 N on unit area)
    r, start = np.asarray(res.residuals), 0
    for c in curves:
        n = c.stress.size
        pred = c.stress + c.sigma * r[start : start + n]
        start += n
        ref = F.nominal_stress(
            MODELS[model][0], res.material, c.test, c.stretch, incompressible=False
        )
        np.testing.assert_allclose(pred, ref.stress, rtol=1e-8, atol=5e-8, err_msg=c.test)
