"""The Jacobian of a fit's residuals by one forward-mode pass (all tangents of a level in
one multi-right-hand-side solve) matches central finite differences, with the device CG
and with the host sparse Cholesky; Levenberg–Marquardt reuses its Jacobian at the optimum
for the uncertainty (no further pass through the solves) and gets the same uncertainty as
a fresh linearisation there.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import fitting as F
from jaxelastic import materials as M
from jaxelastic.fitting import specimens as S


def _case(noise: float = 0.0):
    mesh = S.plate_with_hole(8, 4, 1)
    test = S.hole_test(mesh, 0.3)
    truth = M.Lame.from_E_nu(1000.0, 0.3, dim=3)
    pot = je.Potential(mesh, truth, psi=M.neo_hookean)
    factors = np.array([0.5, 1.0])
    pts = S.dic_points(test, 8, 0, margin=0.3)
    _, data = S.synthetic_measurements(test, pot, factors, pts, noise, 0, F.FIT_SOLVER)
    e = jnp.asarray([1.0, 0.0, 0.0])
    sf = 0.01 * float(np.sqrt(np.mean(data["force"] ** 2)))
    su = 0.01 * float(np.sqrt(np.mean(data["displacements"] ** 2)))
    obs = (
        F.Reaction(jnp.asarray(test.pulled), e, jnp.asarray(data["force"]), sf),
        F.Points.at(mesh, pts, data["displacements"], su, components=("x", "y")),
    )
    return F.LoadPathCase(pot, test.bc, factors, obs)


@pytest.mark.extended
@pytest.mark.parametrize("linear", ["cg", "direct"])
def test_jacobian_of_one_forward_pass_matches_finite_differences(linear):
    case = _case()
    solver = F.FIT_SOLVER.replace(linear=linear)
    obj = F.make_objective([case], F.Material(800.0, 0.25), solver=solver)
    r, J, auxs = obj.linearize(obj.z0)
    assert r is not None and J is not None and bool(auxs[0].ok)
    assert J.shape == (r.shape[0], 2)
    h = 1e-5
    for j in range(2):
        dz = np.zeros(2)
        dz[j] = h
        rp, _, _ = obj.linearize(obj.z0 + dz)
        rm, _, _ = obj.linearize(obj.z0 - dz)
        fd = (np.asarray(rp) - np.asarray(rm)) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-6, atol=1e-6 * np.max(np.abs(fd)))


@pytest.mark.extended
def test_levenberg_marquardt_reuses_its_jacobian_for_the_uncertainty(monkeypatch):
    case = _case(noise=0.01)
    calls = []
    original = F.Objective.linearize

    def counted(self, z, warms=None):
        calls.append(np.asarray(z))
        return original(self, z, warms)

    monkeypatch.setattr(F.Objective, "linearize", counted)
    res = F.fit([case], F.Material(700.0, 0.2), optimizer="lm")
    assert res.converged, res.stop_reason
    assert res.uncertainty is not None
    # the optimum was linearised once, as a trial point, and not again for the uncertainty
    assert sum(np.array_equal(c, res.z) for c in calls) == 1
    obj = F.make_objective([case], F.Material(700.0, 0.2))
    fresh, _, _, r = obj.uncertainty(res.z, res.solutions)
    np.testing.assert_allclose(res.residuals, r, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.uncertainty.covariance, fresh.covariance, rtol=1e-6)
