"""Stability report: extreme starts, stiff materials, huge and tiny time steps, large twists.

A table scenes × materials × integrators with the outcome

* ``recovered``: the body came back to a proper rigid motion of its rest shape;
* ``completed``: a loaded scene ran to its end (every step/increment converged);
* ``at rest, not recovered``: every step converged but the body rests in another state
  (the reason says which: a mirror image with zero energy, total collapse, a tangle);
* ``refused``: a solve returned a failure status (INVERTED, LINE_SEARCH_FAILED, ...) and the
  state was not advanced — the reason is the library's own;
* ``failed``: an exception, or a non-finite number without a failure status (a library
  bug: the report counts these as ``silent_nans``; there must be none),

with Newton iterations (max, mean per step/increment), line-search cut-backs, whether the
total energy decreased monotonically (required of backward Euler on an unloaded body, whose
incremental potential dissipates), the volume error ``Σ J|T| / Σ |T| − 1`` at the end, and
the wall time (run only: each material × integrator × mesh compiles its step once, in a
warm-up from the rest shape whose time is the ``compile_s`` column).

Scenes (robustness scenes of the graphics literature: Smith, de Goes & Kim 2018, §7;
Kim & Eberle 2022, §"Robustness"): a free cube released from all vertices crushed to 1 %,
reflected through a plane, inflated ×2, random positions (backward Euler h = 1 s, which
regularises the rigid modes); a clamped beam released under gravity (the "drop") with
ν = 0.45 / 0.49 / 0.499; a static beam under gravity with E from 1e3 to 1e9 Pa (load
stepping); time steps h from 1e-4 s to 1 s; a 2π twist of a bar by load stepping; a thin
sheet folding under gravity; a single tet collapsed to a line and to a point.

Outputs in ``--out``: ``stability.json``, ``stability.csv``, ``stability.md`` (scenes ×
materials, backward Euler / static), ``stability_shapes.png`` (a grid of final shapes) and a
printed table.

Usage::

    python scripts/report_stability.py --quick --out out/report_stability_quick
    python scripts/report_stability.py --out out/report_stability
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
import time
from pathlib import Path

import _report_common as rc
import numpy as np

ALL_MODELS = (
    "stable_neo_hookean_log",
    "stable_neo_hookean",
    "fixed_corotated",
    "corotated",
    "arap",
    "neo_hookean",
    "stvk",
)
QUICK_MODELS = ("stable_neo_hookean_log", "fixed_corotated", "neo_hookean", "stvk")
INVERTIBLE = ("stable_neo_hookean_log", "fixed_corotated", "corotated", "arap")
INTEGRATORS = ("backward_euler", "bdf2")

E_RELAX, NU_RELAX, RHO_RELAX = 1.0e4, 0.3, 100.0
G = np.array([0.0, 0.0, -9.81])


def _settings(**kw):
    """The report's Newton solver (``je.Newton``) with ``kw`` overriding its defaults."""
    import jaxelastic as je

    # forces of the relax scenes are ~1e3 N with a round-off floor ~1e-11 N (atol); a random
    # start can need ~200 Newton iterations in its first step (tests/test_robustness.py)
    base = dict(max_steps=400, atol=1e-8)
    base.update(kw)
    return je.Newton(**base)


@functools.cache
def _step_fn():
    """``step(base, state, bc, h, solver, method)`` jitted with a *traced* ``h`` (one
    compile for every time step size)."""
    import jax

    from jaxelastic import dynamics as D

    def step(base, state, bc, h, solver, method):
        return D.step(base, state, bc, D.Integrator(h, method), solver=solver)

    return jax.jit(step, static_argnames=("solver", "method"))


@dataclasses.dataclass
class Outcome:
    outcome: str
    reason: str
    statuses: list
    newton: list
    cutbacks: int
    energies: list
    x: np.ndarray
    wall: float
    silent_nan: bool = False
    compile_s: float = 0.0


_WARMED: dict = {}


def _warm_key(pot, kind, settings):
    m = pot.mesh
    return (pot.psi, m.points.shape, m.cells.shape, pot.f_ext is None, kind, settings)


def _compile_time(key, fn) -> float:
    """Run ``fn`` once per ``key`` (a compile-only warm-up) and return its time (0 after)."""
    if key in _WARMED:
        return 0.0
    t0 = time.perf_counter()
    fn()
    _WARMED[key] = time.perf_counter() - t0
    return _WARMED[key]


def _volume_error(mesh, x) -> float:
    import jax.numpy as jnp

    from jaxelastic.mechanics.kinematics import deformation_gradients

    F = np.asarray(deformation_gradients(jnp.asarray(x), mesh, fbar=False))
    J = np.linalg.det(F)
    w = np.asarray(mesh.weights)
    return float(np.sum(J * w) / np.sum(w) - 1.0)


def _run_dynamic(base, x0, bc, h, method, n_steps, settings, energy_base=None) -> Outcome:
    """Host loop over the jitted step; stops at the first failed step."""
    import jax
    import jax.numpy as jnp

    from jaxelastic import dynamics as D
    from jaxelastic.solvers import Status

    step = _step_fn()
    rest = D.init_state(base.mesh.points)
    h = jnp.asarray(h)  # traced: one compilation for every time step size
    compile_s = _compile_time(
        _warm_key(base, method, settings),
        lambda: jax.block_until_ready(step(base, rest, bc, h, settings, method)),
    )
    state = D.init_state(jnp.asarray(x0))
    eb = base if energy_base is None else energy_base
    energies = [float(D.total_energy(eb, state))]
    statuses, newton, cuts = [], [], 0
    t0 = time.perf_counter()
    reason = ""
    silent = False
    for _ in range(n_steps):
        new, res = step(base, state, bc, h, settings, method)
        jax.block_until_ready(new)
        st = Status(int(res.status))
        statuses.append(st.name)
        newton.append(int(res.stats["steps"]))
        cuts += int(res.stats["line_search_cutbacks"])
        finite = bool(np.isfinite(np.asarray(new.x)).all())
        if st != Status.SUCCESS:
            reason = f"{st.name}: {res.reason}"
            if not np.isfinite(np.asarray(new.x)).all():
                silent = True  # a failure status must leave the state finite
            break
        if not finite:
            silent = True
            break
        state = new
        energies.append(float(D.total_energy(eb, state)))
    wall = time.perf_counter() - t0
    x = np.asarray(state.x)
    return Outcome("", reason, statuses, newton, cuts, energies, x, wall, silent, compile_s)


def _rigid_fit(x, X):
    """Best orthogonal fit x ≈ Q X + t: the sign of det Q (−1: a mirror image), the misfit
    with the best proper rotation, and the misfit with the best orthogonal map."""
    xc, Xc = x - x.mean(0), X - X.mean(0)
    U, _, Vt = np.linalg.svd(xc.T @ Xc)
    sign = np.sign(np.linalg.det(U @ Vt))
    D = np.eye(X.shape[1])
    D[-1, -1] = sign
    R = U @ D @ Vt
    Q = U @ Vt
    return sign, float(np.abs(xc - Xc @ R.T).max()), float(np.abs(xc - Xc @ Q.T).max())


def _classify_relax(mesh, psi, params, x0, o: Outcome) -> Outcome:
    import jax.numpy as jnp

    import jaxelastic as je

    if o.silent_nan:
        o.outcome, o.reason = "failed", "non-finite state without a failure status"
        return o
    if o.reason:
        o.outcome = "refused"
        return o
    X = np.asarray(mesh.points)
    e0 = float(je.energy(psi, jnp.asarray(x0), mesh, params))
    e = float(je.energy(psi, jnp.asarray(o.x), mesh, params))
    sign, misfit, misfit_q = _rigid_fit(o.x, X)
    F = np.asarray(je.kinematics.deformation_gradients(jnp.asarray(o.x), mesh)).reshape(-1, 3, 3)
    J = np.linalg.det(F)
    size = float(np.ptp(X, axis=0).max())
    if sign > 0 and misfit < 1e-3 * size and abs(e) <= 1e-8 * max(abs(e0), 1.0):
        o.outcome, o.reason = "recovered", "rigid motion of the rest shape"
    else:
        o.outcome = "at rest, not recovered"
        if sign < 0 and misfit_q < 1e-3 * size:
            o.reason = (
                f"mirror image of the rest shape with energy {e:.1e} (reflection = zero energy)"
            )
        elif abs(e) <= 1e-8 * max(abs(e0), 1.0) and J.min() < 0:
            o.reason = (
                f"zero-energy fold: C = I in every cell, {int((J < 0).sum())} of {J.size} cells "
                "mirrored (J = −1)"
            )
        elif np.abs(F).max() < 1e-3:
            o.reason = f"collapsed to a point (F ≈ 0 is an equilibrium), E = {e:.3g}"
        elif np.ptp(o.x, axis=0).min() < 1e-3 * size:
            o.reason = f"collapsed to a plane/line (E = {e:.3g})"
        else:
            o.reason = f"other equilibrium: min J = {J.min():.2f}, E/E0 = {e / max(e0, 1e-300):.2g}"
    return o


def _start(X, name, seed=0):
    c = X.mean(0)
    if name == "crush":
        return c + 0.01 * (X - c)
    if name == "reflect":
        return X * np.array([1.0, -1.0, 1.0])
    if name == "inflate":
        return c + 2.0 * (X - c)
    if name == "random":
        return np.random.default_rng(seed).uniform(0.0, 1.0, X.shape) * np.ptp(X, 0) + X.min(0)
    if name == "line":  # every vertex projected onto the x axis
        return np.stack([X[:, 0], 0 * X[:, 0], 0 * X[:, 0]], 1)
    if name == "point":
        return np.broadcast_to(c, X.shape).copy()
    raise ValueError(name)


def _min_J(mesh, x):
    import jax.numpy as jnp

    from jaxelastic.mechanics.kinematics import deformation_gradients

    if not np.isfinite(x).all() or x.shape != np.asarray(mesh.points).shape:
        return None
    F = np.asarray(deformation_gradients(jnp.asarray(x), mesh, fbar=False))
    return float(np.linalg.det(F).min())


def _row(scene, model, integrator, o: Outcome, mesh, t_extra=None, **extra) -> dict:
    steps = o.newton
    en = np.asarray(o.energies)
    mono = (
        bool(np.all(np.diff(en) <= 1e-9 * max(np.abs(en).max(), 1e-300))) if en.size > 1 else None
    )
    r = dict(
        scene=scene,
        material=model,
        integrator=integrator,
        outcome=o.outcome,
        reason=o.reason,
        steps=len(steps),
        newton_max=int(max(steps)) if steps else 0,
        newton_mean=float(np.mean(steps)) if steps else 0.0,
        ls_cutbacks=int(o.cutbacks),
        energy_monotone=mono,
        energy_first=float(en[0]) if en.size else None,
        energy_last=float(en[-1]) if en.size else None,
        volume_error=_volume_error(mesh, o.x) if np.isfinite(o.x).all() else None,
        min_J=_min_J(mesh, o.x),
        time_s=o.wall,
        compile_s=o.compile_s,
        silent_nan=o.silent_nan,
        statuses=sorted(set(o.statuses)),
    )
    r.update(extra)
    return r


# --------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------


def relax_scenes(models, integrators, starts, n_steps, shapes):
    """Free cube released from a crushed / reflected / inflated / random start."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads
    from jaxelastic import materials as M

    mesh = je.box(2, 2, 2)
    params = M.Lame.from_E_nu(E_RELAX, NU_RELAX)
    X = np.asarray(mesh.points)
    rows = []
    for model in models:
        psi = M.BUILTIN[model]
        base = je.Potential(
            mesh=mesh, params=params, mass=jnp.asarray(loads.lumped_mass(mesh, RHO_RELAX)), psi=psi
        )
        for integ in integrators:
            for start in starts:
                x0 = _start(X, start, seed=1)
                o = _guard(
                    _run_dynamic,
                    base,
                    x0,
                    loads.no_dirichlet(mesh),
                    1.0,
                    integ,
                    n_steps,
                    _settings(),
                )
                if o.outcome != "failed":
                    o = _classify_relax(mesh, psi, params, x0, o)
                rows.append(_row(start, model, integ, o, mesh))
                shapes.append((start, model, integ, mesh, o.x))
    return rows


def collapse_scenes(models, integrators, n_steps, shapes):
    """A single tet with its vertices collapsed onto a line and onto a point."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads
    from jaxelastic import materials as M

    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    mesh = je.from_arrays(X, np.array([[0, 1, 2, 3]]), "tet4")
    params = M.Lame.from_E_nu(E_RELAX, NU_RELAX)
    rows = []
    for model in models:
        psi = M.BUILTIN[model]
        base = je.Potential(
            mesh=mesh, params=params, mass=jnp.asarray(loads.lumped_mass(mesh, RHO_RELAX)), psi=psi
        )
        for integ in integrators:
            for start in ("line", "point"):
                x0 = _start(X, start)
                o = _guard(
                    _run_dynamic,
                    base,
                    x0,
                    loads.no_dirichlet(mesh),
                    1.0,
                    integ,
                    n_steps,
                    _settings(),
                )
                if o.outcome != "failed":
                    o = _classify_relax(mesh, psi, params, x0, o)
                rows.append(_row(f"collapse to {start}", model, integ, o, mesh))
                shapes.append((f"collapse to {start}", model, integ, mesh, o.x))
    return rows


def _beam(E, nu, model, n=(6, 2, 2), size=(3.0, 0.5, 0.5), rho=1000.0, dynamic=True):
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads
    from jaxelastic import materials as M

    mesh = je.box(*n, size=size)
    params = M.Lame.from_E_nu(E, nu)
    kw = dict(mass=jnp.asarray(loads.lumped_mass(mesh, rho))) if dynamic else {}
    pot = je.Potential(
        mesh=mesh,
        params=params,
        f_ext=jnp.asarray(loads.gravity_load(mesh, rho, G)),
        psi=M.BUILTIN[model],
        **kw,
    )
    clamp = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    return mesh, pot, clamp


def _loaded_outcome(o: Outcome) -> Outcome:
    if o.silent_nan:
        o.outcome, o.reason = "failed", "non-finite state without a failure status"
    elif o.reason:
        o.outcome = "refused"
    else:
        o.outcome = "completed"
    return o


def _tip(mesh, x):
    X = np.asarray(mesh.points)
    tip = np.flatnonzero(np.isclose(X[:, 0], X[:, 0].max()))
    return float(np.mean(x[tip, 2] - X[tip, 2]))


def _beam_release(scene, model, mesh, pot, clamp, h, integ, n_steps):
    """Release the clamped beam under gravity for ``n_steps`` steps of ``h``: one table row."""
    o = _guard(_run_dynamic, pot, mesh.points, clamp, h, integ, n_steps, _settings(max_steps=100))
    if o.outcome != "failed":
        o = _loaded_outcome(o)
    return _row(scene, model, integ, o, mesh, tip_uz=_tip(mesh, o.x))


def drop_scenes(models, integrators, nus, n_steps, h=1.0 / 30.0):
    """Clamped beam released under gravity (E = 1e6 Pa) with ν → ½."""
    rows = []
    for model in models:
        for nu in nus:
            mesh, pot, clamp = _beam(1.0e6, nu, model)
            for integ in integrators:
                rows.append(
                    _beam_release(f"drop ν={nu}", model, mesh, pot, clamp, h, integ, n_steps)
                )
    return rows


def h_scenes(models, integrators, hs, n_steps):
    """The clamped beam under gravity with time steps from 1e-4 s to 1 s."""
    rows = []
    for model in models:
        mesh, pot, clamp = _beam(1.0e6, 0.3, model)
        for integ in integrators:
            for h in hs:
                rows.append(_beam_release(f"h={h:g} s", model, mesh, pot, clamp, h, integ, n_steps))
    return rows


def _run_static(pot, bc, steps, min_increment=1.0 / 256) -> Outcome:
    """Load stepping (``je.solve_incremental``) of ``pot`` with Dirichlet data ``bc`` or a
    load path ``s -> Dirichlet``; the warm-up solves the unloaded problem once."""
    import jaxelastic as je

    cuts = [0]
    path = bc if callable(bc) else None
    bc0 = bc(0.0) if callable(bc) else bc
    pot0 = pot if pot.f_ext is None else pot.replace(f_ext=0.0 * pot.f_ext)
    bound = je.solvers.linear.resolve("direct", pot.mesh, bc0)
    solver = _settings(max_steps=60, linear=bound)
    compile_s = _compile_time(
        _warm_key(pot, "static", _settings(max_steps=60)),
        lambda: je.solve(pot0, bc0, solver=solver, throw=False),
    )

    def cb(s, res):
        cuts[0] += int(res.stats["line_search_cutbacks"])

    t0 = time.perf_counter()
    r = je.solve_incremental(
        pot,
        bc0,
        steps=steps,
        min_increment=min_increment,
        path=path,
        solver=solver,
        throw=False,
        callback=cb,
    )
    wall = time.perf_counter() - t0
    incs = r.stats["increments"]
    statuses = [h["status"] for h in incs]
    accepted_newton = [int(h["steps"]) for h in incs]
    x = np.asarray(r.x)
    silent = not np.isfinite(x).all()
    reason = ""
    load_factor = float(r.stats["load_factor"])
    if not bool(r.ok):
        st = je.Status(int(r.status))
        reason = f"{st.name} at load factor {load_factor:.3g}: {r.reason}"
    o = Outcome("", reason, statuses, accepted_newton, cuts[0], [], x, wall, silent, compile_s)
    o.load_factor = load_factor
    o.increments = len(incs)
    return _loaded_outcome(o)


def stiffness_scenes(models, Es):
    """Static clamped beam under gravity, E from 1e3 to 1e9 Pa (load stepping with cut-back)."""
    rows = []
    for model in models:
        for E in Es:
            mesh, pot, clamp = _beam(E, 0.3, model, dynamic=False)
            o = _guard(_run_static, pot, clamp, steps=1)
            rows.append(
                _row(
                    f"E={E:.0e} static",
                    model,
                    "static",
                    o,
                    mesh,
                    tip_uz=_tip(mesh, o.x),
                    load_factor=getattr(o, "load_factor", None),
                    increments=getattr(o, "increments", None),
                )
            )
    return rows


def twist_reason(mid_angle: float, turns: float, min_J) -> str:
    """Describe a finished twist: the mid-section should have turned by half the end's
    angle; a different angle means the bar unwound (snapped through) along the path."""
    want = (180.0 * turns) % 360
    txt = f"mid-section turned by {mid_angle:.0f}° (uniform: {want:.0f}°)"
    off = abs((mid_angle - want + 180) % 360 - 180)
    if off > 20:
        txt += "; the twist unwound along the load path (an equilibrium, not the twisted one)"
    if min_J is not None and min_J <= 0:
        txt += f"; inverted cells (min J = {min_J:.2f})"
    return txt


def twist_scenes(models, shapes, turns=1.0, increments=16):
    """A 4 × 1 × 1 bar clamped at x = 0 whose end x = 4 is turned by 2π·turns about the bar
    axis (Dirichlet data rotated by the load factor: s ↦ R(2π s)), by load stepping."""
    import jaxelastic as je
    from jaxelastic import loads
    from jaxelastic import materials as M

    mesh = je.box(8, 2, 2, size=(4.0, 1.0, 1.0))
    X = np.asarray(mesh.points)
    clamp = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
    end = loads.nodes_on_plane(mesh, 0, 4.0)

    def bc_fn(s):
        th = 2 * np.pi * turns * s

        def u(P):
            y, z = P[:, 1] - 0.5, P[:, 2] - 0.5
            c, sn = np.cos(th), np.sin(th)
            return np.stack(
                [0 * y, 0.5 + c * y - sn * z - P[:, 1], 0.5 + sn * y + c * z - P[:, 2]], 1
            )

        return loads.combine(clamp, loads.fix(mesh, end, displacement=u))

    rows = []
    for model in models:
        pot = je.Potential(mesh=mesh, params=M.Lame.from_E_nu(1.0e6, 0.3), psi=M.BUILTIN[model])
        o = _guard(_run_static, pot, bc_fn, steps=increments)
        if o.outcome == "completed":
            # the mid-section x = 2 must have turned by half the end's angle (not unwound)
            mid = loads.nodes_on_plane(mesh, 0, 2.0)
            r0, r1 = X[mid, 1:] - 0.5, o.x[mid, 1:] - o.x[mid, 1:].mean(0)
            ang = np.angle(np.sum((r1[:, 0] + 1j * r1[:, 1]) * (r0[:, 0] - 1j * r0[:, 1])))
            o.mid_angle = float(np.degrees(ang) % 360)
            o.reason = twist_reason(o.mid_angle, turns, _min_J(mesh, o.x))
        rows.append(
            _row(
                f"twist {360 * turns:.0f}°",
                model,
                "static",
                o,
                mesh,
                load_factor=getattr(o, "load_factor", None),
                increments=getattr(o, "increments", None),
                mid_angle_deg=getattr(o, "mid_angle", None),
            )
        )
        shapes.append((f"twist {360 * turns:.0f}°", model, "static", mesh, o.x))
    return rows


def sheet_scenes(models, integrators, n_steps, shapes, h=0.02):
    """A 1 × 1 × 0.01 sheet (elements 12.5:1) held along the edge x = 0, folding down
    under gravity (E = 1e5 Pa, ρ = 500)."""
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import loads
    from jaxelastic import materials as M

    mesh = je.box(8, 8, 1, size=(1.0, 1.0, 0.01))
    X = np.asarray(mesh.points)
    hold = loads.fix(mesh, loads.nodes_where(mesh, lambda P: P[:, 0] < 1e-9))
    rows = []
    for model in models:
        pot = je.Potential(
            mesh=mesh,
            params=M.Lame.from_E_nu(1.0e5, 0.3),
            f_ext=jnp.asarray(loads.gravity_load(mesh, 500.0, G)),
            mass=jnp.asarray(loads.lumped_mass(mesh, 500.0)),
            psi=M.BUILTIN[model],
        )
        for integ in integrators:
            o = _guard(_run_dynamic, pot, X, hold, h, integ, n_steps, _settings(max_steps=100))
            if o.outcome != "failed":
                o = _loaded_outcome(o)
            rows.append(_row("sheet folding", model, integ, o, mesh, tip_uz=_tip(mesh, o.x)))
            shapes.append(("sheet folding", model, integ, mesh, o.x))
    return rows


def _guard(fn, *args, **kw) -> Outcome:
    """Run a scene; an exception becomes a ``failed`` outcome with its message."""
    try:
        return fn(*args, **kw)
    except Exception as e:  # noqa: BLE001 - the report records every failure
        return Outcome(
            "failed", f"{type(e).__name__}: {e}"[:300], [], [], 0, [], np.full((1, 3), np.nan), 0.0
        )


# --------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------


def _scene_group(s, quick, models, integ, starts, shapes) -> list[dict]:
    """The rows of one scene group (``relax``, ``collapse``, ``drop``, ...) at the quick or
    full settings; final shapes are appended to ``shapes``."""
    loaded = (
        ("stable_neo_hookean_log", "neo_hookean")
        if quick
        else ("stable_neo_hookean_log", "fixed_corotated", "neo_hookean", "stvk")
    )
    if s == "relax":
        st = starts or ("crush", "reflect", "inflate", "random")
        return relax_scenes(models, integ, st, 15 if quick else 30, shapes)
    if s == "collapse":
        return collapse_scenes(models, ("backward_euler",), 10, shapes)
    if s == "drop":
        nus = (0.499,) if quick else (0.45, 0.49, 0.499)
        return drop_scenes(loaded, integ, nus, 10 if quick else 30)
    if s == "stiffness":
        Es = (1e3, 1e6, 1e9) if quick else (1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9)
        return stiffness_scenes(loaded, Es)
    if s == "h":
        hs = (1e-4, 1e-2, 1.0) if quick else (1e-4, 1e-3, 1e-2, 1e-1, 1.0)
        return h_scenes(loaded, integ, hs, 3 if quick else 5)
    if s == "twist":
        tw = ("stable_neo_hookean_log",)
        if not quick:
            tw += ("fixed_corotated", "corotated", "neo_hookean", "stvk")
        return twist_scenes(tw, shapes, increments=16)
    sm = ("stable_neo_hookean_log",)
    if not quick:
        sm += ("fixed_corotated", "neo_hookean")
    return sheet_scenes(sm, integ, 10 if quick else 40, shapes)  # "sheet"


def run(
    out="out/report_stability",
    *,
    quick=False,
    scenes=None,
    models=None,
    starts=None,
    plots=True,
    verbose=True,
) -> dict:
    """Run the stability study and write its files; returns ``{"rows": [...], ...}``.

    Args:
        quick: small settings (fewer materials, one integrator where two are optional,
            fewer steps). scenes: subset of ``relax, collapse, drop, stiffness, h, twist,
            sheet`` (default all). models: override the materials of the relax and collapse
            scenes. starts: override the relax starts (crush, reflect, inflate, random).
    """
    import jax

    jax.config.update("jax_enable_x64", True)
    if models is None:
        models = QUICK_MODELS if quick else ALL_MODELS
    integ = ("backward_euler",) if quick else INTEGRATORS
    all_scenes = ("relax", "collapse", "drop", "stiffness", "h", "twist", "sheet")
    chosen = all_scenes if scenes is None else tuple(scenes)
    bad = [s for s in chosen if s not in all_scenes]
    if bad:
        raise ValueError(f"unknown scene group(s) {bad}; choose from {all_scenes}")
    rows, shapes = [], []
    t0 = time.perf_counter()
    for s in chosen:
        rows += _scene_group(s, quick, models, integ, starts, shapes)
        if verbose:
            _print_rows([r for r in rows if not r.get("_printed")])
            for r in rows:
                r["_printed"] = True
    for r in rows:
        r.pop("_printed", None)
    silent = sum(bool(r["silent_nan"]) for r in rows)
    result = dict(
        machine=rc.machine(),
        quick=quick,
        total_time_s=time.perf_counter() - t0,
        silent_nans=silent,
        outcomes={
            k: sum(r["outcome"] == k for r in rows) for k in sorted({r["outcome"] for r in rows})
        },
        rows=rows,
    )
    out = Path(out)
    rc.write_json(out / "stability.json", result)
    rc.write_csv(out / "stability.csv", rows)
    rc.write_text(out / "stability.md", markdown_table(rows))
    if plots and shapes:
        result["figures"] = [plot_shapes(shapes, out / "stability_shapes.png", rows)]
    if verbose:
        print(f"\noutcomes: {result['outcomes']}; silent NaNs: {silent}")
        print(f"wrote {out / 'stability.json'}, {out / 'stability.csv'}")
    return result


_SHORT = {
    "recovered": "recovered",
    "completed": "completed",
    "at rest, not recovered": "rest ≠ rest shape",
    "refused": "refused",
    "failed": "**FAILED**",
}


def _short(r) -> str:
    txt = _SHORT.get(r["outcome"], r["outcome"])
    reason = r["reason"]
    if r["outcome"] == "completed" and "unwound" in reason:
        txt += ", but unwound"
    if r["outcome"] == "completed" and "inverted" in reason:
        txt += ", inverted cells"
    if r["outcome"] == "refused":
        txt += f" ({reason.split(':')[0]})"
    elif r["outcome"] == "at rest, not recovered":
        for key, label in (
            ("mirror", "mirror image, E = 0"),
            ("zero-energy fold", "zero-energy fold"),
            ("point", "collapsed: point"),
            ("plane/line", "collapsed: line"),
            ("other", "tangled"),
        ):
            if key in reason:
                txt = f"rest: {label}"
                break
    return txt


def markdown_table(rows, integrator=("backward_euler", "static")) -> str:
    """Scenes × materials matrix of short outcomes (one integrator), as Markdown."""
    rows = [r for r in rows if r["integrator"] in integrator]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    models = list(dict.fromkeys(r["material"] for r in rows))
    cell = {(r["scene"], r["material"]): _short(r) for r in rows}
    lines = ["| scene | " + " | ".join(models) + " |", "|---" * (len(models) + 1) + "|"]
    for sc in scenes:
        lines.append(f"| {sc} | " + " | ".join(cell.get((sc, m), "") for m in models) + " |")
    return "\n".join(lines) + "\n"


_printed_hdr = [False]


def _print_rows(rows):
    if not _printed_hdr[0]:
        print(
            f"{'scene':<18} {'material':<23} {'integrator':<15} {'outcome':<23} {'Nmax':>4} "
            f"{'Nmean':>6} {'cuts':>5} {'mono':>5} {'vol err':>9} {'s':>6}  reason"
        )
        _printed_hdr[0] = True
    for r in rows:
        ve = r["volume_error"]
        print(
            f"{r['scene']:<18} {r['material']:<23} {r['integrator']:<15} {r['outcome']:<23} "
            f"{r['newton_max']:>4} {r['newton_mean']:>6.1f} {r['ls_cutbacks']:>5} "
            f"{str(r['energy_monotone']):>5} {(ve if ve is not None else float('nan')):>9.2e} "
            f"{r['time_s']:>6.2f}  {r['reason'][:70]}"
        )


_OUTCOME_COLORS = {
    "recovered": "C2",
    "completed": "C2",
    "at rest, not recovered": "C1",
    "refused": "C0",
    "failed": "C3",
}


def plot_shapes(shapes, path: Path, rows) -> str:
    """A grid of final shapes: one row per scene, one column per material (backward Euler or
    static), framed by outcome colour."""
    from matplotlib.figure import Figure

    from jaxelastic.plot import shapes as draw

    shapes = [s for s in shapes if s[2] in ("backward_euler", "static")]
    scenes = list(dict.fromkeys(s[0] for s in shapes))
    models = list(dict.fromkeys(s[1] for s in shapes))
    outcome = {(r["scene"], r["material"], r["integrator"]): r for r in rows}
    fig = Figure(figsize=(2.3 * len(models), 2.1 * len(scenes)))
    axs = fig.subplots(len(scenes), len(models), squeeze=False)
    for ax in axs.ravel():
        ax.set_axis_off()
    for scene, model, integ, mesh, x in shapes:
        ax = axs[scenes.index(scene), models.index(model)]
        r = outcome.get((scene, model, integ), {})
        ax.set_axis_on()
        if np.isfinite(x).all() and x.shape == np.asarray(mesh.points).shape:
            draw(ax, mesh, {"rest": np.asarray(mesh.points), "final": x}, axes=(0, 2), wire=True)
            leg = ax.get_legend()
            if leg is not None:
                leg.remove()
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel("")
        ax.set_ylabel("")
        col = _OUTCOME_COLORS.get(r.get("outcome", ""), "k")
        for sp in ax.spines.values():
            sp.set_edgecolor(col)
            sp.set_linewidth(2.0)
        ax.set_title(f"{scene}\n{model}\n{r.get('outcome', '?')}", fontsize=6.5, color=col)
    fig.suptitle(
        "Final shapes (x–z view; dotted: rest; frame: green recovered/completed, orange "
        "at rest not recovered, blue refused, red failed)",
        fontsize=8,
    )
    fig.tight_layout()
    rc.save_figure(fig, path, dpi=90)
    return str(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", default="out/report_stability")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument(
        "--scenes",
        default=None,
        help="comma-separated: relax,collapse,drop,stiffness,h,twist,sheet",
    )
    ap.add_argument("--no-plots", action="store_true")
    a = ap.parse_args(argv)
    sc = None if a.scenes is None else [s.strip() for s in a.scenes.split(",") if s.strip()]
    run(a.out, quick=a.quick, scenes=sc, plots=not a.no_plots)
    return 0


if __name__ == "__main__":
    sys.exit(main())
