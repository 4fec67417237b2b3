"""Treloar's (1944) uniaxial data fitted through a finite-element specimen.

A unit cube of tetrahedra in uniaxial tension (symmetry planes x = 0, y = 0, z = 0 held
normally, the face x = 1 pulled to every measured stretch in turn: one load level per data
point) deforms homogeneously, so its support force on the pulled face is the nominal
stress times the unit area. Fitting Mooney–Rivlin (c10, c01) through it at a bulk modulus
of 1e5 MPa (≈ 2.5e5 times the shear modulus) must give the parameters of an independent
closed-form least-squares fit of the incompressible formula
``P = 2 (λ − λ⁻²)(c10 + c01/λ)`` (Ogden 1984, *Non-linear Elastic Deformations*, §7.2)
to ≤ 1e-4 relative.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares

import jaxelastic as je
from jaxelastic import fitting as F
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.verification.treloar import TRELOAR_UNIAXIAL


def _closed_form(lam, P):
    def r(c):
        return 2.0 * (lam - lam**-2) * (c[0] + c[1] / lam) - P

    return least_squares(r, [0.2, 0.02], xtol=1e-15, ftol=1e-15, gtol=1e-15).x


@pytest.mark.extended
def test_mooney_rivlin_fit_through_a_specimen_matches_the_closed_form():
    lam, P = TRELOAR_UNIAXIAL.stretch, TRELOAR_UNIAXIAL.stress
    ref = _closed_form(lam, P)
    mesh = je.box(1, 1, 1)
    sym = [L.fix(mesh, L.nodes_on_plane(mesh, a, 0.0), components=(a,)) for a in range(3)]
    pulled = L.nodes_on_plane(mesh, 0, 1.0)
    d = float(lam[-1] - 1.0)
    bc = L.combine(*sym, L.fix(mesh, pulled, components=(0,), displacement=[d, 0.0, 0.0]))
    kappa = 1e5
    pot = je.Potential(mesh, M.MooneyRivlin(0.2, 0.02, kappa), psi=M.mooney_rivlin)
    obs = (F.Reaction(jnp.asarray(pulled), jnp.asarray([1.0, 0.0, 0.0]), jnp.asarray(P), 1.0),)
    case = F.LoadPathCase(pot, bc, (lam - 1.0) / d, obs)
    tr = M.MooneyRivlin(F.Positive(), F.Free(scale=0.02), F.Fixed())
    # rtol 1e-9: at λ = 7.6 and κ/μ ≈ 2.5e5 the residual's round-off floor is above 1e-11
    newton = je.Newton(rtol=1e-9)
    res = F.fit([case], M.MooneyRivlin(0.2, 0.02, kappa), transforms=tr, solver=newton)
    assert res.converged, res.stop_reason
    fitted = np.array([res.params.c10, res.params.c01])
    np.testing.assert_allclose(fitted, ref, rtol=1e-4)
