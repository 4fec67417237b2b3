"""Fits of load paths with measurement σ: trial solves that fail are reported (case,
status, parameters) and never counted as convergence; a case that is not a pytree is
refused with what to do; a plate pulled in three levels, observed by its support reaction
and by in-plane DIC points with 1 % noise, gives back (E, ν) within the Gauss–Newton
standard errors.
"""

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import fitting as F
from jaxelastic import loads as L
from jaxelastic import materials as M
from jaxelastic.solvers import Status


class P(NamedTuple):
    c01: object


@dataclasses.dataclass(frozen=True)
class Unstable(F.Case):
    """A case without solves whose 'solve' fails for c01 > 1.5, with its optimum at 2."""

    mesh_: object = None
    weight: float = 1.0

    @property
    def mesh(self):
        return self.mesh_

    def initial_warm(self):
        return jnp.zeros(())

    def bind(self, solver):
        return None  # no solves

    def evaluate(self, params, warm, solver, adjoint):
        p = params.c01
        ok = p < 1.5
        loss = 1.0 + 1e-4 * (p - 2.0) ** 2
        st = jnp.where(ok, 0, int(Status.LINE_SEARCH_FAILED)).astype(jnp.int32)
        aux = F.CaseAux(warm, ok, jnp.int32(1), jnp.int32(1), st, jnp.int32(-1))
        return jnp.where(ok, loss, jnp.nan), aux


jax.tree_util.register_dataclass(Unstable, data_fields=["weight"], meta_fields=["mesh_"])


@dataclasses.dataclass(frozen=True)
class NotRegistered(Unstable):
    pass


def test_failed_trial_solves_are_reported_and_not_converged():
    with pytest.warns(RuntimeWarning, match=r"case 0: LINE_SEARCH_FAILED .*at c01 = 1\.5"):
        res = F.fit([Unstable()], P(1.0), max_iter=50)
    assert res.stop_reason == "solve_failed"
    assert not res.converged
    f = res.failures[-1]
    assert f["case"] == 0 and f["status"] == "LINE_SEARCH_FAILED" and f["level"] is None
    assert f["params"]["c01"] >= 1.5


@dataclasses.dataclass(frozen=True)
class UnstableResiduals(Unstable):
    """The same with residuals ``(1, 0.01 (c01 − 2))`` for Levenberg–Marquardt."""

    def residuals(self, params, warm, solver, adjoint):
        loss, aux = self.evaluate(params, warm, solver, adjoint)
        r = jnp.stack([jnp.ones_like(loss), 1e-2 * (params.c01 - 2.0)])
        return jnp.where(aux.ok, r, jnp.nan), aux


jax.tree_util.register_dataclass(UnstableResiduals, data_fields=["weight"], meta_fields=["mesh_"])


def test_levenberg_marquardt_rejects_failed_trials_and_never_converges_on_them():
    with pytest.warns(RuntimeWarning, match=r"case 0: LINE_SEARCH_FAILED .*at c01 = 1\.5"):
        res = F.fit([UnstableResiduals()], P(1.0), optimizer="lm", max_iter=200)
    assert res.stop_reason == "solve_failed" and not res.converged
    assert res.failures and all(f["params"]["c01"] >= 1.5 for f in res.failures)
    assert 1.0 < res.material.c01 < 1.5  # accepted points only, the loss decreasing
    assert np.all(np.diff(res.loss_history) < 0)
    assert res.loss_history.shape == (res.iterations + 1,)
    # a case without residuals, or a regulariser, is refused with the alternative
    with pytest.raises(ValueError, match=r"case 0 \(Unstable\) defines no residuals"):
        F.fit([Unstable()], P(1.0), optimizer="lm")


def test_a_case_that_is_not_a_pytree_gets_advice():
    with pytest.raises(TypeError, match=r"NotRegistered.*register_dataclass"):
        F.fit([NotRegistered()], P(1.0))


@dataclasses.dataclass(frozen=True)
class DefaultBind(Unstable):
    def bind(self, solver):
        return F.Case.bind(self, solver)


jax.tree_util.register_dataclass(DefaultBind, data_fields=["weight"], meta_fields=["mesh_"])


def test_a_case_binding_no_solver_state_gets_advice():
    with pytest.raises(TypeError, match=r"DefaultBind\).bind returned Newton.*prepare_solver"):
        F.fit([DefaultBind()], P(1.0))


def _plate(E, nu, factors, rng=None, noise=0.0):
    mesh = je.rectangle(6, 3, size=(3.0, 1.0))
    left, right = L.nodes_on_plane(mesh, 0, 0.0), L.nodes_on_plane(mesh, 0, 3.0)
    bc = L.combine(L.fix(mesh, left), L.fix(mesh, right, components=(0,), displacement=0.15))
    params = M.Lame.from_E_nu(E, nu, dim=2)
    pot = je.Potential(mesh, params, psi=M.neo_hookean)
    return mesh, pot, bc, right


@pytest.mark.extended
def test_load_path_fit_recovers_E_nu_within_standard_errors():
    factors = np.array([1 / 3, 2 / 3, 1.0])
    mesh, pot, bc, right = _plate(1000.0, 0.3, factors)
    pts = np.random.default_rng(0).uniform([0.3, 0.1], [2.7, 0.9], size=(12, 2))
    e = jnp.asarray([1.0, 0.0])
    obs = (
        F.Reaction(jnp.asarray(right), e, jnp.zeros(3), 1.0),
        F.Points.at(mesh, pts, np.zeros((3, 12, 2)), 1.0),
    )
    case = F.LoadPathCase(pot, bc, factors, obs)
    truth = M.Lame.from_E_nu(1000.0, 0.3, dim=2)
    preds, _ = case.predictions(truth, case.initial_warm(), F.FIT_SOLVER, je.ImplicitAdjoint())
    rng = np.random.default_rng(1)
    noisy = []
    for o, p in zip(obs, preds, strict=True):
        p = np.asarray(p)
        sigma = 0.01 * np.sqrt(np.mean(p**2))  # 1 % of the signal's RMS
        d = p + sigma * rng.standard_normal(p.shape)
        noisy.append(dataclasses.replace(o, data=jnp.asarray(d), sigma=sigma))
    case = F.LoadPathCase(pot, bc, factors, tuple(noisy))
    res = F.fit([case], F.Material(700.0, 0.2))
    assert res.converged, res.stop_reason
    assert res.uncertainty is not None and res.names == ("E", "nu")
    se = res.uncertainty.standard_errors
    err = np.array([res.E - 1000.0, res.nu - 0.3])
    assert np.all(np.abs(err) <= 3.0 * se), (err, se)
    assert np.all(se < np.array([50.0, 0.05]))  # informative


def test_plate_with_hole_specimen_geometry():
    """The O-grid covers one eighth of the plate: its volume is (W² − πa²/4)·T up to the
    hole's chords (P1: the polygon's area; P2: the circle's, to the quadratic cells'
    accuracy), the symmetry planes and the grip hold the expected nodes."""
    from jaxelastic.fitting import specimens as S

    W, a, T = 2.0, 0.5, 0.2
    for order, n, tol in ((1, 8, None), (2, 6, 2e-4)):
        mesh = S.plate_with_hole(n, 4, 1, half_width=W, radius=a, half_thickness=T, order=order)
        vol = float(jnp.sum(mesh.weights))
        if tol is None:  # P1: the hole is the polygon with n chords
            hole = 0.5 * n * a * a * np.sin(np.pi / (2 * n))
            np.testing.assert_allclose(vol, (W * W - hole) * T, rtol=1e-12)
        else:
            np.testing.assert_allclose(vol, (W * W - np.pi * a * a / 4) * T, rtol=tol)
    test = S.hole_test(mesh, 0.1)
    X = np.asarray(mesh.points)
    np.testing.assert_allclose(X[test.pulled, 0], W)
    mask = np.asarray(test.bc.mask)
    assert mask[np.isclose(X[:, 0], 0.0), 0].all() and mask[np.isclose(X[:, 2], 0.0), 2].all()
    pts = S.dic_points(test, 20, 0, margin=0.3)
    assert np.all(np.linalg.norm(pts[:, :2], axis=1) >= a + 0.3) and np.allclose(pts[:, 2], T)


@pytest.mark.extended
def test_a_failing_level_is_retried_in_sub_steps_and_never_skipped():
    """A pull that Newton (5 steps at most) cannot reach from the rest shape converges in
    sub-steps; one it cannot reach even so makes the case fail, naming the level and the
    status (the level is not skipped)."""
    mesh = je.rectangle(4, 2, size=(2.0, 1.0))
    left, right = L.nodes_on_plane(mesh, 0, 0.0), L.nodes_on_plane(mesh, 0, 2.0)
    e = jnp.asarray([1.0, 0.0])
    newton = je.Newton(rtol=1e-10, max_steps=3)
    adj = je.ImplicitAdjoint()

    def case(pull, factors, cutbacks):
        bc = L.combine(L.fix(mesh, left), L.fix(mesh, right, displacement=[pull, 0.0]))
        pot = je.Potential(mesh, M.Lame.from_E_nu(100.0, 0.3, dim=2), psi=M.neo_hookean)
        obs = (F.Reaction(jnp.asarray(right), e, jnp.zeros(len(factors)), 1.0),)
        return F.LoadPathCase(pot, bc, factors, obs, max_cutbacks=cutbacks), pot, bc

    c, pot, bc = case(1.0, [0.5, 1.0], 4)
    direct = je.solve(pot, bc, solver=newton, throw=False)
    assert not bool(direct.ok)  # one step from the rest shape fails
    (force,), aux = c.predictions(
        pot.params, c.initial_warm(), c.bind(newton), je.ImplicitAdjoint()
    )
    assert bool(aux.ok) and int(aux.level) == -1 and np.all(np.diff(np.asarray(force)) > 0)
    c, pot, _ = case(2.0, [0.5, 1.0], 0)  # no sub-steps allowed: level 0 fails, named
    _, aux = c.predictions(pot.params, c.initial_warm(), c.bind(newton), adj)
    assert not bool(aux.ok) and int(aux.level) == 0
    assert Status(int(aux.status)) != Status.SUCCESS


@pytest.mark.extended
def test_first_evaluation_from_secant_predictions_matches_solves_from_rest():
    """The first evaluation of a load path starts each level from the secant through the
    two previous levels' solutions: every level's reaction is the one a solve of that
    level from the rest shape gives, in fewer Newton steps than solving each level from
    the previous one's solution."""
    factors = np.array([0.25, 0.5, 1.0])
    mesh, pot, bc, right = _plate(1000.0, 0.3, factors)
    e = jnp.asarray([1.0, 0.0])
    case = F.LoadPathCase(pot, bc, factors, (F.Reaction(jnp.asarray(right), e, jnp.zeros(3), 1.0),))
    newton = je.Newton(rtol=1e-11)
    (force,), aux = case.predictions(
        pot.params, case.initial_warm(), case.bind(newton), je.ImplicitAdjoint()
    )
    assert bool(aux.ok)
    x_prev, steps = mesh.points, 0
    for k, s in enumerate(factors):
        p, b = case.at(jnp.asarray(s), pot.params)
        x = je.solve(p, b, solver=newton).x
        R = -je.forces(p.psi, x, mesh, p.params)
        expect = float(jnp.sum(R[jnp.asarray(right), 0]))
        np.testing.assert_allclose(float(force[k]), expect, rtol=1e-9)
        sol = je.solve(p, b, x0=x_prev, solver=newton)
        x_prev, steps = sol.x, steps + int(sol.stats["steps"])
    assert int(aux.newton_steps) < steps
