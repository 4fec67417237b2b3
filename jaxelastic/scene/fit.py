"""Material identification from a scene: the ``[fit]`` table, ``jaxelastic fit SCENE``.

A static scene with a ``[fit]`` table describes one or more load cases (the scene itself,
plus ``[[fit.case]]`` entries that override scene keys, e.g. a second traction), where the
observed deformed positions come from (a file per case, or a synthetic target solved at
given "true" parameters, optionally on a refined mesh), which nodes are observed (all, or a
random fraction as markers), observation noise, the initial guess and the optimiser.
:func:`run_fit` fits (E, ν) with :func:`jaxelastic.fitting.fit` and writes
``summary.json``, ``fit.png`` (loss and parameter trajectories) and ``observed.npz``.
Region labels of piecewise-constant fields come from where-expressions
(:func:`region_labels`).
"""

from __future__ import annotations

import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import fitting
from ..materials import FAMILIES, FAMILY_POSITIVE_KEYS, Lame
from ..solvers import GradientError, SolveError
from . import interrupt, memory
from .errors import SceneError
from .interrupt import Interrupted
from .load import Scene, load_scene
from .measurements import check_nodes, read_observation
from .outputs import (
    FIT_OUTPUTS,
    finish_summary,
    log,
    prepare_out,
    remove_temporaries,
    save_npz,
    save_png,
)
from .positions import check_positions
from .problem import Built, build, newton_of
from .run import static_solve
from .schema import FitCase, FitSpec
from .where import where_mask

__all__ = ["run_fit", "region_labels", "read_observed"]


# ----------------------------------------------------------------------------------------
# observations and regions
# ----------------------------------------------------------------------------------------


def _optimizer(cfg: FitSpec) -> Any:
    """The ``optimizer`` argument of :func:`~jaxelastic.fitting.fit` for ``[fit]``: its name,
    or for ``"lm"`` the Levenberg–Marquardt settings with the scene's ``atol``."""
    if cfg.optimizer == "lm":
        return fitting.LMSettings(atol=cfg.atol)
    return cfg.optimizer


def region_labels(mesh, regions) -> np.ndarray:
    """``(n_cells,)`` int labels: the first ``where`` expression a cell centroid satisfies,
    ``len(regions)`` for cells matching none."""
    X = np.asarray(mesh.points)[np.asarray(mesh.cells)].mean(axis=1)  # (n_cells, dim)
    labels = np.full(X.shape[0], len(regions), dtype=np.int32)
    for i, expr in reversed(list(enumerate(regions))):
        labels[where_mask(expr, X)] = i
    return labels


def _per_region(x, n: int) -> np.ndarray:
    return np.broadcast_to(np.asarray(x, float), (n,)).copy()


def _load_positions(scene: Scene, key: str, path: str, dim: int):
    """Raw ``(positions, nodes or None)`` of a .npy / .npz / .csv file."""
    if os.path.getsize(path) == 0:
        raise scene.error(f"{key}: {path!r} is empty")
    if path.endswith(".npy"):
        return np.load(path), None
    if path.endswith(".npz"):
        with np.load(path) as z:
            if "positions" not in z:
                have = ", ".join(z.files) or "no arrays: an empty file"
                raise scene.error(f"{key}: {path!r} has no array 'positions' (has {have})")
            return z["positions"], (z["nodes"] if "nodes" in z else None)
    if path.endswith((".csv", ".txt")):
        a = np.loadtxt(path, delimiter="," if path.endswith(".csv") else None, ndmin=2)
        if a.size == 0:
            raise scene.error(f"{key}: {path!r} has no data rows")
        if a.shape[1] != dim + 1:
            raise scene.error(
                f"{key}: {path!r} must have {dim + 1} columns node, x, y[, z]; got {a.shape[1]}"
            )
        return a[:, 1:], a[:, 0]
    raise scene.error(f"{key}: {path!r} must be a .npy, .npz or .csv file")


def read_observed(scene: Scene, key: str, path: str, n_nodes: int, dim: int, rest=None):
    """Observed positions ``(n_obs, dim)`` and their nodes ``(n_obs,)`` from a file.

    ``.npy``: ``(n_nodes, dim)`` all nodes; ``.npz``: ``positions`` and optional ``nodes``;
    ``.csv``: rows ``node, x, y[, z]``.

    Raises:
        SceneError: (naming ``key``, the file and the row) a missing, empty or unreadable
            file, wrong shapes, node indices out of range or repeated, non-finite
            positions, positions equal to the rest shape ``rest`` ``(n_nodes, dim)``.
    """
    if not os.path.isfile(path):
        raise scene.error(f"{key}: no such file {path!r}")
    try:
        pos, nodes = _load_positions(scene, key, path, dim)
    except (OSError, ValueError) as e:
        raise scene.error(f"{key}: cannot read {path!r}: {e}") from None
    pos = np.asarray(pos, float)
    where = f"{key} ({path!r})"
    if nodes is None:
        if pos.shape != (n_nodes, dim):
            raise scene.error(
                f"{where}: positions of all {n_nodes} nodes, shape ({n_nodes}, {dim}), "
                f"expected without 'nodes'; got shape {pos.shape}"
            )
        nodes = np.arange(n_nodes)
    nodes = check_nodes(scene, where, nodes, n_nodes)
    pos = check_positions(scene, where, pos, nodes, dim, rest)
    return pos, nodes


# ----------------------------------------------------------------------------------------
# the steps of a fit
# ----------------------------------------------------------------------------------------


def _stop_at_iterations(summary: dict, done: str):
    """The optimiser's per-iteration callback of a scene fit: past the first iteration (and
    its compilation) a signal stops the fit at the next one, and ``summary["completed"]``
    says how far it got (``done`` and the iterations)."""

    def at_iteration(k, params, loss) -> bool:
        interrupt.at_boundaries()
        summary["completed"] = f"{done} and {k} optimiser iteration(s)"
        return interrupt.requested() is not None

    return at_iteration


def _fit_spec(scene: Scene) -> FitSpec:
    """The scene's ``[fit]`` table; SceneError when it has none."""
    if scene.spec.fit is None:
        raise SceneError(f"scene {scene.label!r} has no [fit] section")
    return scene.spec.fit


def _case_scenes(scene: Scene) -> list[Scene]:
    base = scene.to_dict()
    base.pop("fit")
    cases = [{}] + [dict(c.set) for c in _fit_spec(scene).case]
    return [load_scene(base, overrides=c, base_dir=scene.base_dir) for c in cases]


def _regions(scene: Scene, mesh, summary: dict):
    """``(labels (n_cells,) or None, n_regions)``; refuses an empty region."""
    regions = _fit_spec(scene).regions
    if not regions:
        return None, 1
    n_reg = len(regions) + 1
    labels = region_labels(mesh, regions)
    counts = np.bincount(labels, minlength=n_reg)
    if not counts.all():
        i = int(np.flatnonzero(counts == 0)[0])
        what = f"[fit].regions[{i}]" if i < n_reg - 1 else "the rest (no region matched)"
        raise scene.error(f"{what} contains no cell (regions are tried in order)")
    summary["regions"] = dict(expressions=list(regions), cells=counts)
    return labels, n_reg


def _with_truth(bt: Built, truth: dict, labels, n_reg: int) -> Built:
    """``bt`` with the (per-cell, with regions) Lamé parameters of the true E, ν."""
    E_t, nu_t = truth["E"], truth["nu"]
    if labels is not None:
        E_t, nu_t = _per_region(E_t, n_reg)[labels], _per_region(nu_t, n_reg)[labels]
    plane = bt.scene.spec.material.plane or "strain"
    p = Lame.from_E_nu(jnp.asarray(E_t), jnp.asarray(nu_t), dim=bt.mesh.dim, plane=plane)
    return bt._replace(params=p, potential=bt.potential.replace(params=p))


def _synthetic_targets(scene: Scene, scenes, mesh, labels, n_reg: int, progress: bool):
    """Observed positions ``(n_nodes, dim)`` per case, solved at ``[fit].target``."""
    cfg = _fit_spec(scene)
    t = cfg.target
    assert t is not None  # called for a synthetic target
    truth = dict(E=t.E, nu=t.nu)
    fmt = lambda x: ", ".join(f"{a:.6g}" for a in np.atleast_1d(x))
    r = t.refine
    refined = f" on a {r}x refined mesh" if r > 1 else ""
    log(
        progress, f"synthetic target at E = {fmt(t.E)}, nu = {fmt(t.nu)}{refined}", "jaxelastic fit"
    )
    observed = []
    for s in scenes:
        if r > 1:
            n = s.spec.mesh.n
            s = load_scene(
                s, overrides={"mesh.n": [k * r for k in n] if isinstance(n, tuple) else n * r}
            )
        bt = build(s)
        lab = labels if (labels is None or r == 1) else region_labels(bt.mesh, cfg.regions)
        x, _, _ = static_solve(_with_truth(bt, truth, lab, n_reg), what="target solve")
        idx = (
            np.arange(mesh.n_nodes) if r == 1 else fitting.nested_nodes(bt.mesh.points, mesh.points)
        )
        observed.append(np.asarray(x)[idx])
    return observed, np.arange(mesh.n_nodes), ["synthetic"] * len(scenes)


def _file_targets(scene: Scene, mesh):
    """Observed positions (NaN where unobserved) per case from ``observed`` files, the nodes
    observed in every case, and the file paths."""
    cfg = _fit_spec(scene)
    files = [cfg.observed] + [c.observed for c in cfg.case]
    keys = ["[fit].observed"] + [f"[fit.case][{i}].observed" for i in range(len(cfg.case))]
    sources = []
    for f in files:
        assert f is not None  # FitSpec: every case has a file when there is no target
        sources.append(os.path.join(scene.base_dir, f))
    observed, avail = [], None
    for key, path in zip(keys, sources, strict=True):
        pos, nodes = read_observed(scene, key, path, mesh.n_nodes, mesh.dim, mesh.points)
        full = np.full((mesh.n_nodes, mesh.dim), np.nan)
        full[nodes] = pos
        observed.append(full)
        avail = nodes if avail is None else np.intersect1d(avail, nodes)
    return observed, avail, sources


def _load_cases(scene: Scene, builts: list[Built], observed, markers: np.ndarray):
    """The :class:`~jaxelastic.fitting.LoadCase` s (noise added) and the observed arrays."""
    cfg = _fit_spec(scene)
    mesh = builts[0].mesh
    X = np.asarray(mesh.points)
    cases, arrays = [], {}
    for i, (b, xo) in enumerate(zip(builts, observed, strict=True)):
        xo_m = jnp.asarray(xo[markers])
        if cfg.noise > 0:
            key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), i)
            xo_m = fitting.add_noise(xo_m, jnp.asarray(X[markers]), cfg.noise, key)
        arrays[f"positions_{i}"] = np.asarray(xo_m)
        nodes = None if markers.size == mesh.n_nodes else jnp.asarray(markers)
        weight = 1.0 if i == 0 else cfg.case[i - 1].weight
        cases.append(fitting.LoadCase(b.potential, b.bc, xo_m, nodes=nodes, weight=weight))
    return cases, arrays


def _fit(scene: Scene, cases, labels, n_reg: int, progress: bool, callback=None):
    cfg, spec = _fit_spec(scene), scene.spec
    init = fitting.Material(E=cfg.initial.E, nu=cfg.initial.nu)
    if labels is not None:
        init = fitting.Material(_per_region(init.E, n_reg), _per_region(init.nu, n_reg))
    solver = newton_of(spec.solver)
    return fitting.fit(
        cases,
        init,
        regions=labels,
        fields=tuple(cfg.fields),
        plane=spec.material.plane or "strain",
        optimizer=_optimizer(cfg),
        learning_rate=cfg.learning_rate,
        max_iter=cfg.max_iter,
        gtol=cfg.gtol,
        solver=solver.replace(rtol=min(solver.rtol, 1e-10)),
        progress=progress,
        callback=callback,
    )


def _result(res: fitting.FitResult, truth, labels, n_reg: int) -> tuple[dict, dict]:
    """The summary's ``result`` and ``history``."""
    result = dict(
        E=np.asarray(res.E, float),
        nu=np.asarray(res.nu, float),
        loss=float(res.loss),
        converged=bool(res.converged),
        stop_reason=res.stop_reason,
        iterations=int(res.iterations),
    )
    if truth is not None:
        for k in ("E", "nu"):
            t = _per_region(truth[k], n_reg) if labels is not None else np.asarray(truth[k])
            result[f"{k}_rel_error"] = np.abs(result[k] - t) / np.abs(t)
    P = np.asarray(res.param_history)
    history = dict(
        loss=res.loss_history,
        E=P[:, 0],
        nu=P[:, 1],
        grad_norm=res.grad_norm_history,
        newton_steps=res.newton_steps,
        linear_iterations=res.linear_iterations,
    )
    return result, history


def _figure(hist_loss, hist_p, fields, truth, title):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.2))
    ax = fig.subplots(1, 3)
    it = np.arange(len(hist_loss))
    ax[0].semilogy(it, np.maximum(hist_loss, 1e-300), "o-", ms=3)
    ax[0].set(xlabel="iteration", ylabel="loss", title="loss")
    for j, (name, lab) in enumerate((("E", "E [Pa]"), ("nu", "ν"))):
        ax[j + 1].plot(it, hist_p[:, j], "o-", ms=3, label="fit")  # one line per region
        if truth is not None:
            for k, t in enumerate(np.atleast_1d(truth[name])):
                tl = "true value" if k == 0 else None  # one legend entry for all regions
                ax[j + 1].axhline(t, color="k", ls="--", lw=0.8, label=tl)
        fitted = "fitted" if name in fields else "held fixed"
        ax[j + 1].set(xlabel="iteration", ylabel=lab, title=f"{lab.split()[0]} ({fitted})")
        ax[j + 1].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


# ----------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------


def _prepare(scene: Scene, out_dir) -> str:
    """The output directory; refuses to overwrite the scene or an observation file."""
    cfg = _fit_spec(scene)
    obs = [os.path.join(scene.base_dir, c.observed) for c in (cfg, *cfg.case) if c.observed]
    out = prepare_out(out_dir, scene)
    for name in FIT_OUTPUTS:
        p = os.path.join(out, name)
        if any(q and os.path.abspath(q) == p for q in [scene.source, *obs]):
            raise scene.error(f"refusing to overwrite the input {p!r}; choose another --out")
    return out


def _observe(scene: Scene, builts, labels, n_reg, progress, summary):
    """Observations, marker nodes and load cases; fills the summary's case entries."""
    cfg, mesh = _fit_spec(scene), builts[0].mesh
    t0 = time.perf_counter()
    if cfg.target is not None:
        scenes = [b.scene for b in builts]
        observed, avail, sources = _synthetic_targets(scene, scenes, mesh, labels, n_reg, progress)
    else:
        observed, avail, sources = _file_targets(scene, mesh)
    markers = fitting.choose_markers(builts[0].bc.mask, cfg.markers, cfg.seed, avail)
    if markers.size == 0:
        raise scene.error("[fit]: no observed node is free (all observed nodes are clamped)")
    cases, arrays = _load_cases(scene, builts, observed, markers)
    summary["timings"]["target"] = time.perf_counter() - t0
    summary["cases"] = [
        dict(overrides=dict(c.set), weight=c.weight, observed=src)
        for c, src in zip([FitCase(), *cfg.case], sources, strict=True)
    ]
    summary["observations"] = dict(
        n_markers=int(markers.size),
        fraction_of_nodes=markers.size / mesh.n_nodes,
        noise=cfg.noise,
        seed=cfg.seed,
    )
    t = cfg.target
    summary["target"] = None if t is None else dict(E=t.E, nu=t.nu, refine=t.refine)
    summary["initial"] = dict(E=cfg.initial.E, nu=cfg.initial.nu)
    return cases, markers, arrays


def _fit_and_write(scene, out, cases, markers, arrays, labels, n_reg, progress, summary):
    cfg = scene.spec.fit
    log(
        progress,
        f"fitting {', '.join(cfg.fields)} on {len(cases)} load case(s), {markers.size} observed "
        "nodes (the first iterations include compilation) ...",
        "jaxelastic fit",
    )
    t0 = time.perf_counter()
    summary["completed"] = "the observations; interrupted during the optimiser"

    at_iteration = _stop_at_iterations(summary, "the observations")

    with interrupt.immediate():  # until the first iteration ends: no boundary to stop at
        res = _fit(scene, cases, labels, n_reg, progress, at_iteration)
    stopped = res.stop_reason == "callback"
    if not stopped:
        del summary["completed"]
    summary["timings"]["fit_incl_compile"] = time.perf_counter() - t0
    summary["result"], summary["history"] = _result(res, summary["target"], labels, n_reg)
    t0 = time.perf_counter()
    png, npz = os.path.join(out, "fit.png"), os.path.join(out, "observed.npz")
    P = np.asarray(res.param_history)
    title = f"{scene.name}: fit of (E, ν)"
    save_png(_figure(res.loss_history, P, cfg.fields, summary["target"], title), png)
    save_npz(npz, nodes=markers, **arrays)
    path = os.path.join(out, "summary.json")
    summary["outputs"] = dict(directory=out, summary=path, png=[png], observed=npz)
    summary["timings"]["outputs"] = time.perf_counter() - t0
    if stopped:  # the fitted values so far are written: now stop
        interrupt.check()


def run_fit(scene, out_dir, progress: bool = True) -> dict:
    """Fit (E, ν) as the scene's ``[fit]`` table says; write the outputs into ``out_dir``.

    Writes (atomically) ``summary.json`` (scene, cases, target, initial guess, fitted
    values and their relative errors when the truth is known, stop reason, loss /
    parameter / gradient-norm / Newton histories, timings), ``fit.png`` and
    ``observed.npz`` (``nodes``, and ``positions_<i>`` per case: a file target for reruns).

    Args:
        scene: a scene with a ``[fit]`` table (Scene, path, shipped name or dict);
            out_dir: output directory; progress: progress bars and messages.
    Raises:
        SceneError: invalid scene, no ``[fit]`` section, bad observation files,
            ``[solver] precision = "float32"`` (fits run in float64).
        SolveError / GradientError: the target solve or a fit solve failed (the summary is
            still written with ``"status": "failed"``).
        Interrupted: SIGINT/SIGTERM (under
            :func:`~jaxelastic.scene.interrupt.handle_signals`) or Ctrl-C: the build and
            the optimiser stop at once, a target solve at its next load increment; the
            summary says ``"interrupted": true`` and what was ``completed`` (no fitted
            values: :func:`jaxelastic.fitting.fit` has no stop callback yet).
    """
    t_start = time.perf_counter()
    scene = load_scene(scene)
    if scene.spec.solver.precision != "float64":
        raise scene.error(
            '[solver].precision = "float32" is not supported by a fit: the fit\'s '
            "parameters and adjoint solves (rtol 1e-10) are float64; remove the key or set "
            'precision = "float64"'
        )
    memory.check(scene)  # before the output directory is created
    out = _prepare(scene, out_dir)
    summary: dict[str, Any] = dict(
        scene=scene.to_dict(), scene_file=scene.source, status="running", timings={}
    )
    path = os.path.join(out, "summary.json")
    try:
        t0 = time.perf_counter()
        summary["completed"] = "nothing; interrupted during the build"
        measured = _fit_spec(scene).measured
        with interrupt.immediate():  # measured: the [[fit.case]] entries are the cases
            builts = [build(s) for s in _case_scenes(scene)[1 if measured else 0 :]]
        summary["completed"] = "the build; interrupted during the target solves"
        mesh = builts[0].mesh
        summary["mesh"] = dict(
            dim=mesh.dim, n_nodes=mesh.n_nodes, n_cells=mesh.n_cells, element=mesh.element
        )
        summary["timings"]["build"] = time.perf_counter() - t0
        if measured:
            _measured_fit(scene, out, builts, progress, summary)
            del summary["completed"]
            return finish_summary(path, summary, t_start, status="ok", interrupted=False)
        labels, n_reg = _regions(scene, mesh, summary)
        cases, markers, arrays = _observe(scene, builts, labels, n_reg, progress, summary)
        _fit_and_write(scene, out, cases, markers, arrays, labels, n_reg, progress, summary)
    except (SolveError, GradientError) as e:
        summary.pop("completed", None)
        error = f"{type(e).__name__}: {e}"
        finish_summary(path, summary, t_start, status="failed", error=error, interrupted=False)
        raise
    except KeyboardInterrupt as e:
        raise _interrupted(e, out, path, summary, t_start) from None
    return finish_summary(path, summary, t_start, status="ok", interrupted=False)


def _interrupted(e: KeyboardInterrupt, out: str, path: str, summary: dict, t_start: float):
    """Write the summary of a stopped fit, remove temporaries; the Interrupted to raise."""
    name = e.signame if isinstance(e, Interrupted) else "KeyboardInterrupt"
    completed = summary.pop("completed", "nothing")
    with interrupt.shield():
        fields = dict(status="interrupted", interrupted=True, signal=name, completed=completed)
        finish_summary(path, summary, t_start, **fields)
        remove_temporaries(out)
    kept = "fitted values so far in summary.json" if "result" in summary else "no fitted values"
    return Interrupted(name, f"after {completed} ({kept})", out)


# ----------------------------------------------------------------------------------------
# measurements over load paths ([[fit.case.observation]])
# ----------------------------------------------------------------------------------------


def transform_of(name: str, value: float) -> fitting.Transform:
    """The transform of a rubber/tissue parameter by its meaning: moduli, bulk moduli and
    limits that must be positive (:data:`~jaxelastic.materials.FAMILY_POSITIVE_KEYS`,
    and ``k1``) are ``Positive``; the HGO dispersion is ``Bounded(0, 1/3)``; the others
    (``c01``, ``c20``, ``c30``, Ogden ``mu_i``, ``alpha_i``), whose sign the law does not
    fix, are ``Free`` with the initial magnitude as scale."""
    if name in FAMILY_POSITIVE_KEYS or name == "k1":
        return fitting.Positive()
    if name == "kappa_dispersion":
        return fitting.Bounded(0.0, 1.0 / 3.0)
    return fitting.Free(scale=abs(float(value)) or 1.0)


def _measured_init(scene: Scene, bt: Built):
    """``(init, transforms, fields)`` for :func:`jaxelastic.fitting.fit`."""
    cfg, model = _fit_spec(scene), scene.spec.material.model
    if model not in FAMILIES:
        E, nu = (float(np.atleast_1d(getattr(cfg.initial, k))[0]) for k in ("E", "nu"))
        return fitting.Material(E, nu), None, tuple(cfg.fields)
    vals = bt.params._asdict()
    for k in cfg.fields:
        vals[k] = float(getattr(cfg.initial, k))
    tr = {k: transform_of(k, v) if k in cfg.fields else fitting.Fixed() for k, v in vals.items()}
    kind = type(bt.params)
    return kind(**vals), kind(**tr), None


def _measured_cases(scene: Scene, builts: list[Built]) -> list:
    cfg = _fit_spec(scene)
    cases = []
    for i, (c, bt) in enumerate(zip(cfg.case, builts, strict=True)):
        key = f"[fit.case][{i}]"
        obs = tuple(
            read_observation(scene, f"{key}.observation[{j}]", o, c, bt)
            for j, o in enumerate(c.observation)
        )
        try:
            factors = np.asarray(c.load_factors, dtype=np.float64)
            cases.append(fitting.LoadPathCase(bt.potential, bt.bc, factors, obs, c.weight))
        except (ValueError, TypeError) as e:
            raise scene.error(f"{key}: {e}") from None
    return cases


def _observation_report(cases, residuals) -> tuple[list, list]:
    """Per case, per observation: kind, σ, RMS residual (data units), χ²; and the
    predictions ``(n_levels, ...)`` rebuilt from the residuals (``data + σ r``)."""
    reports, preds, i = [], [], 0
    for c in cases:
        rep, pr = [], []
        for o in c.observations:
            target = np.asarray(o.target(o.data))
            r = np.asarray(residuals[i : i + target.size]).reshape(target.shape)
            i += target.size
            sigma = float(o.sigma)
            rep.append(
                dict(
                    kind=o.kind,
                    sigma=sigma,
                    n_values=int(target.size),
                    rms=float(np.sqrt(np.mean((sigma * r) ** 2))),
                    chi2=float(np.sum(r * r)),
                )
            )
            pr.append(target + sigma * r)
        reports.append(rep)
        preds.append(pr)
    return reports, preds


def _measured_fit(scene: Scene, out: str, builts: list[Built], progress: bool, summary: dict):
    """Read the measurements, fit, write fit.png and the summary's result (in place)."""
    cfg, spec = _fit_spec(scene), scene.spec
    cases = _measured_cases(scene, builts)
    init, transforms, fields = _measured_init(scene, builts[0])
    n_levels = sum(len(c.factors) for c in cases)
    log(
        progress,
        f"fitting {', '.join(cfg.fields)} on {len(cases)} case(s), {n_levels} "
        "load levels (the first iterations include compilation) ...",
        "jaxelastic fit",
    )
    solver = newton_of(spec.solver)
    t0 = time.perf_counter()
    summary["completed"] = "the build; interrupted during the optimiser"

    at_iteration = _stop_at_iterations(summary, "the build")

    with interrupt.immediate():
        res = fitting.fit(
            cases, init, transforms=transforms, fields=fields,
            plane=spec.material.plane or "strain", optimizer=_optimizer(cfg),
            learning_rate=cfg.learning_rate, max_iter=cfg.max_iter, gtol=cfg.gtol,
            solver=solver.replace(rtol=min(solver.rtol, 1e-10)), progress=progress,
            callback=at_iteration, uncertainty=True,
        )  # fmt: skip
    summary["timings"]["fit_incl_compile"] = time.perf_counter() - t0
    _measured_summary(res, cases, cfg, summary)
    png = os.path.join(out, "fit.png")
    save_png(_measured_figure(res, cases, summary, f"{scene.name}: fit"), png)
    path = os.path.join(out, "summary.json")
    summary["outputs"] = dict(directory=out, summary=path, png=[png])
    if res.stop_reason == "callback":
        interrupt.check()


def _measured_summary(res: fitting.FitResult, cases, cfg, summary: dict) -> None:
    values = [float(np.asarray(getattr(res.params, n))) for n in res.names]
    unc = res.uncertainty
    assert unc is not None and res.residuals is not None  # fit(..., uncertainty=True)
    reports, _ = _observation_report(cases, res.residuals)
    summary["fitted"] = dict(zip(res.names, values, strict=True))
    summary["standard_errors"] = dict(zip(res.names, unc.standard_errors.tolist(), strict=True))
    summary["correlation"] = unc.correlation.tolist()
    summary["uncertainty"] = dict(
        condition_number=unc.condition_number, rank=unc.rank, reduced_chi2=unc.reduced_chi2
    )
    summary["cases"] = [
        dict(load_factors=list(c.load_factors), overrides=dict(c.set), weight=c.weight,
             observations=[dict(file=o.file, **r) for o, r in zip(c.observation, rep, strict=True)])
        for c, rep in zip(cfg.case, reports, strict=True)
    ]  # fmt: skip
    summary["initial"] = {k: getattr(cfg.initial, k) for k in cfg.fields}
    summary["held"] = {  # e.g. the bulk modulus kappa: part of the model, held fixed
        k: float(v)
        for k, v in res.params._asdict().items()
        if k not in res.names and np.ndim(v) == 0
    }
    summary["result"] = dict(
        loss=float(res.loss),
        converged=bool(res.converged),
        stop_reason=res.stop_reason,
        iterations=int(res.iterations),
        failures=[fitting.describe_failure(f) for f in res.failures],
    )
    P = np.asarray(res.param_history)
    summary["history"] = dict(loss=res.loss_history, params=P, grad_norm=res.grad_norm_history)


def _measured_figure(res: fitting.FitResult, cases, summary: dict, title: str):
    """Each observation's data against the fitted model, and the loss history."""
    from matplotlib.figure import Figure

    _, preds = _observation_report(cases, res.residuals)
    panels = [(c, o, p) for c, pc in zip(cases, preds, strict=True)
              for o, p in zip(c.observations, pc, strict=True)]  # fmt: skip
    fig = Figure(figsize=(3.6 * (len(panels) + 1), 3.4))
    axes = fig.subplots(1, len(panels) + 1, squeeze=False)[0]
    for ax, (c, o, p) in zip(axes, panels, strict=False):
        _observation_panel(ax, c, o, np.asarray(p))
    ax = axes[-1]
    ax.semilogy(np.maximum(res.loss_history, 1e-300), "o-", ms=3)
    se = summary["standard_errors"]
    text = "\n".join(f"{k} = {v:.4g} ± {se[k]:.2g}" for k, v in summary["fitted"].items())
    ax.set(xlabel="iteration", ylabel="χ²", title="loss")
    ax.text(0.95, 0.95, text, transform=ax.transAxes, ha="right", va="top", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def _observation_panel(ax, case, o, pred) -> None:
    f = np.asarray(case.factors)
    data = np.asarray(o.target(o.data))
    if o.kind in ("reaction", "moment", "cavity_volume"):
        ax.plot(f, data, "o", label="measured")
        ax.plot(f, pred, "-", label="fitted model")
        unit = {"moment": "moment [N·m]", "cavity_volume": "cavity volume [m³]"}
        ax.set(xlabel="load factor", ylabel=unit.get(o.kind, "force [N]"), title=f"{o.kind}")
        ax.legend(fontsize=8)
        return
    if o.kind == "points":
        r = np.linalg.norm(pred[-1] - data[-1], axis=-1)
        X = np.asarray(o.rest)
        sc = ax.scatter(X[:, 0], X[:, 1], c=r, s=18, cmap="viridis")
        ax.figure.colorbar(sc, ax=ax, label="|residual| [m], last level")
        ax.set(xlabel="X [m]", ylabel="Y [m]", title="DIC points: residuals", aspect="equal")
        return
    if o.kind == "surface":
        ax.hist(np.ravel(pred), bins=30)
        ax.set(xlabel="distance to the fitted surface [m]", ylabel="points", title="surface")
        return
    ax.plot(np.ravel(data), np.ravel(pred), ".", ms=3)
    ax.set(xlabel="measured [m]", ylabel="fitted [m]", title=o.kind)
