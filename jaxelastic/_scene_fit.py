"""Material identification from a scene: the ``[fit]`` section, ``jaxelastic fit SCENE``.

A static scene with a ``[fit]`` section describes one or more load cases (the scene itself,
plus ``[[fit.case]]`` entries that override scene keys, e.g. a second traction), where the
observed deformed positions come from (a file per case, or a synthetic target solved at
given "true" parameters, optionally on a refined mesh), which nodes are observed (all, or a
random fraction as markers), observation noise, the initial guess and the optimiser.
:func:`run_fit` fits (E, ν) with :func:`jaxelastic.fitting.fit` and writes
``summary.json``, ``fit.png`` (loss and parameter trajectories) and ``observed.npz``.

Scene keys (``[material]`` E/ν are the initial guess unless ``[fit].initial`` is given)::

    [fit]
    target = { E = 1e6, nu = 0.3, refine = 1 }  # synthetic observations: solve the scene at
                                  # these parameters (refine = r: on a mesh with r× the cells
                                  # per axis, observed at the fitting mesh's nodes, which are
                                  # also fine-mesh nodes; generator meshes only)
    # observed = "obs.npz"        # ... or a file of observed positions for the scene's case:
                                  # .npy (n_nodes, dim) all nodes, .npz with "positions"
                                  # (n_obs, dim) and optional "nodes" (n_obs,), or .csv rows
                                  # "node, x, y[, z]"
    initial = { E = 3e6, nu = 0.15 }  # default: [material].E and .nu
    regions = ["x < 1.0"]         # piecewise-constant E, ν: region i = cells whose centroid
                                  # satisfies the i-th expression (first match), the last
                                  # region the rest; target/initial E, ν then take one value
                                  # per region (R = len(regions) + 1) or one for all
    fields = ["E", "nu"]          # which parameters are fitted (the others stay at initial)
    markers = 1.0                 # fraction of the mesh's nodes observed (random, among nodes
                                  # not fully clamped; the same markers in every case)
    noise = 0.0                   # relative Gaussian noise (σ = noise × RMS displacement)
    seed = 0                      # markers and noise
    optimizer = "lbfgs"           # or "adam" (with learning_rate)
    learning_rate = 0.05
    max_iter = 100
    gtol = 1e-10                  # stop when the gradient norm (unconstrained vars) is below

    [[fit.case]]                  # more load cases: scene overrides (dotted keys), weight,
    set = { "traction.0.traction" = [2e4, 0, 0] }   # and (file targets) observed = "..."
    weight = 1.0
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any

import numpy as np

from ._fit_data import (
    _per_region,
    _read_observed,
    choose_markers,
    nested_nodes,
    region_labels,
)
from .io import _write_atomic
from .scenes import _V, Scene, SceneError, _parse_where, load_scene

__all__ = [
    "FIT_KEYS",
    "CASE_KEYS",
    "check_fit",
    "run_fit",
    "nested_nodes",
    "choose_markers",
    "region_labels",
]

FIT_KEYS = (
    "target",
    "observed",
    "initial",
    "fields",
    "markers",
    "noise",
    "seed",
    "optimizer",
    "learning_rate",
    "max_iter",
    "gtol",
    "regions",
    "case",
)
CASE_KEYS = ("set", "observed", "weight")
_TARGET_KEYS = ("E", "nu", "refine")
_OUTPUTS = ("summary.json", "fit.png", "observed.npz")


# ----------------------------------------------------------------------------------------
# validation (called by jaxelastic.scenes while loading a scene)
# ----------------------------------------------------------------------------------------


def _E_nu(v: _V, key: str, x, required=("E", "nu"), extra=()) -> dict:
    """E and ν: numbers, or arrays of numbers (one per region)."""
    t = v.table(key, x, ("E", "nu", *extra), required)
    out = {}
    for k, bounds in (("E", dict(gt=0)), ("nu", dict(gt=-1, lt=0.5))):
        if k not in t:
            continue
        val = t[k]
        if isinstance(val, (list, tuple)):
            if not val:
                raise v.err(f"{key}.{k} must be a number or a non-empty array of numbers")
            out[k] = [v.number(f"{key}.{k}[{i}]", a, **bounds) for i, a in enumerate(val)]
        else:
            out[k] = v.number(f"{key}.{k}", val, **bounds)
    return out | {k: t[k] for k in extra if k in t}


def _n_values(x) -> int:
    return len(x) if isinstance(x, (list, tuple)) else 1


def check_fit(v: _V, x, data: dict) -> dict:
    """Validate a ``[fit]`` table (``data``: the scene validated so far); returns it with
    defaults filled in. Raises :class:`SceneError` naming the offending key."""
    t = v.table("[fit]", x, FIT_KEYS)
    out: dict[str, Any] = {}
    if ("target" in t) == ("observed" in t):
        raise v.err("[fit] needs exactly one of target = { E, nu } (synthetic) or observed")
    if "target" in t:
        out["target"] = _E_nu(v, "[fit].target", t["target"], extra=("refine",))
        if "refine" in out["target"]:
            r = v.integer("[fit].target.refine", out["target"]["refine"], ge=1)
            if r > 1 and "generator" not in data["mesh"]:
                raise v.err("[fit].target.refine needs a [mesh].generator (not a mesh file)")
    else:
        out["observed"] = v.string("[fit].observed", t["observed"])
    mat = data["material"]
    if "initial" in t:
        out["initial"] = _E_nu(v, "[fit].initial", t["initial"], required=())
    else:
        out["initial"] = {}
    for k in ("E", "nu"):
        if k not in out["initial"]:
            if k not in mat:
                raise v.err(f"[fit].initial.{k} is required ([material] has no {k})")
            out["initial"][k] = mat[k]
    fields = t.get("fields", ["E", "nu"])
    if not isinstance(fields, (list, tuple)) or not fields:
        raise v.err(f"[fit].fields must be a non-empty array of 'E', 'nu', got {fields!r}")
    out["fields"] = [v.string(f"[fit].fields[{i}]", f, ("E", "nu")) for i, f in enumerate(fields)]
    if len(set(out["fields"])) != len(out["fields"]):
        raise v.err(f"[fit].fields has duplicates: {fields!r}")
    regions = t.get("regions", [])
    if not isinstance(regions, (list, tuple)):
        raise v.err(f"[fit].regions must be an array of 'where' expressions, got {regions!r}")
    for i, expr in enumerate(regions):
        _parse_where(v, f"[fit].regions[{i}]", v.string(f"[fit].regions[{i}]", expr))
    out["regions"] = list(regions)
    n_reg = len(regions) + 1 if regions else 1
    for sec in ("target", "initial"):
        for k, val in out.get(sec, {}).items():
            if k in ("E", "nu") and _n_values(val) not in (1, n_reg):
                raise v.err(
                    f"[fit].{sec}.{k} must have 1 or {n_reg} values (one per region), "
                    f"got {_n_values(val)}"
                )
    out["markers"] = v.number("[fit].markers", t.get("markers", 1.0), gt=0, le=1)
    out["noise"] = v.number("[fit].noise", t.get("noise", 0.0), ge=0)
    out["seed"] = v.integer("[fit].seed", t.get("seed", 0), ge=0)
    out["optimizer"] = v.string("[fit].optimizer", t.get("optimizer", "lbfgs"), ("lbfgs", "adam"))
    out["learning_rate"] = v.number("[fit].learning_rate", t.get("learning_rate", 0.05), gt=0)
    out["max_iter"] = v.integer("[fit].max_iter", t.get("max_iter", 100), ge=0)
    out["gtol"] = v.number("[fit].gtol", t.get("gtol", 1e-10), gt=0)
    cases = t.get("case", [])
    if not isinstance(cases, (list, tuple)):
        raise v.err(f"[[fit.case]] must be an array of tables, got {cases!r}")
    out["case"] = []
    for i, c in enumerate(cases):
        key = f"[fit.case][{i}]"
        c = v.table(key, c, CASE_KEYS)
        cc = {"set": dict(v.table(f"{key}.set", c.get("set", {}), tuple(c.get("set", {}))))}
        for path in cc["set"]:
            if path.split(".")[0] in ("mesh", "fit", "integrator"):
                raise v.err(f"{key}.set: {path!r} cannot be changed per load case")
        cc["weight"] = v.number(f"{key}.weight", c.get("weight", 1.0), gt=0)
        if "observed" in c:
            if "target" in out:
                raise v.err(f"{key}.observed: not with a synthetic [fit].target")
            cc["observed"] = v.string(f"{key}.observed", c["observed"])
        elif "observed" in out:
            raise v.err(f"{key}.observed is required (the scene's targets come from files)")
        out["case"].append(cc)
    if data["integrator"]["type"] != "static":
        raise v.err("[fit] needs a static scene ([integrator].type = 'static')")
    return out


# ----------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------


def _case_scenes(scene: Scene) -> list[Scene]:
    base = scene.to_dict()
    base.pop("fit")
    out = []
    for c in [{"set": {}}] + list(scene["fit"]["case"]):
        out.append(load_scene(base, overrides=dict(c["set"]), base_dir=scene.base_dir))
    return out


def _log(progress: bool, msg: str) -> None:
    if progress:
        print(f"[jaxelastic fit] {msg}", file=sys.stderr, flush=True)


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
            for t in np.atleast_1d(truth[name]):
                ax[j + 1].axhline(t, color="k", ls="--", lw=0.8)
        fitted = "fitted" if name in fields else "held fixed"
        ax[j + 1].set(xlabel="iteration", ylabel=lab, title=f"{lab.split()[0]} ({fitted})")
        ax[j + 1].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


# ----------------------------------------------------------------------------------------
# run
# ----------------------------------------------------------------------------------------


def run_fit(scene, out_dir, progress: bool = True) -> dict:
    """Fit (E, ν) as the scene's ``[fit]`` section says; write the outputs into ``out_dir``.

    Writes (atomically) ``summary.json`` (scene, cases, target, initial guess, fitted
    values and their relative errors when the truth is known, stop reason, loss /
    parameter / gradient-norm / Newton histories, timings), ``fit.png`` and
    ``observed.npz`` (``nodes``, and ``positions_<i>`` per case: a file target for reruns).

    Raises:
        SceneError: invalid scene, no ``[fit]`` section, bad observation files.
        SolveError / GradientError: the target solve or a fit solve failed (the summary is
            still written with ``"status": "failed"``).
    """
    import jax
    import jax.numpy as jnp

    from . import _scene_run as sr
    from .fitting import GradientError, LoadCase, Material, add_noise, fit
    from .solvers.newton import SolveError

    t_start = time.perf_counter()
    scene = load_scene(scene)
    if scene.get("fit") is None:
        raise SceneError(f"scene {scene.label!r} has no [fit] section")
    cfg = scene["fit"]
    v = _V(scene.label)
    out = sr._prepare_out(out_dir, scene)
    inputs = [scene.source] + [
        os.path.join(scene.base_dir, c["observed"]) for c in [cfg, *cfg["case"]] if "observed" in c
    ]
    for name in _OUTPUTS:
        p = os.path.join(out, name)
        if any(q and os.path.abspath(q) == p for q in inputs):
            raise SceneError(f"refusing to overwrite the input {p!r}; choose another --out")
    summary: dict[str, Any] = dict(
        scene=scene.to_dict(), scene_file=scene.source, status="running", timings={}
    )
    summary_path = os.path.join(out, "summary.json")
    try:
        t0 = time.perf_counter()
        scenes = _case_scenes(scene)
        builts = [sr.build(s) for s in scenes]
        b0 = builts[0]
        mesh, dim = b0.mesh, b0.mesh.dim
        plane = scene["material"].get("plane", "strain")
        summary["mesh"] = dict(
            dim=dim, n_nodes=mesh.n_nodes, n_cells=mesh.n_cells, element=mesh.element
        )
        summary["timings"]["build"] = time.perf_counter() - t0
        n_reg = len(cfg["regions"]) + 1 if cfg["regions"] else 1
        labels = None
        if cfg["regions"]:
            labels = region_labels(mesh, cfg["regions"])
            counts = np.bincount(labels, minlength=n_reg)
            if not counts.all():
                i = int(np.flatnonzero(counts == 0)[0])
                what = f"[fit].regions[{i}]" if i < n_reg - 1 else "the rest (no region matched)"
                raise v.err(f"{what} contains no cell (regions are tried in order)")
            summary["regions"] = dict(expressions=list(cfg["regions"]), cells=counts)

        # observations: synthetic (optionally on a refined mesh) or from files
        t0 = time.perf_counter()
        truth = None
        observed, avail = [], None
        if "target" in cfg:
            truth = dict(cfg["target"])
            r = int(truth.get("refine", 1))
            from .materials import Lame, lame

            _log(
                progress,
                f"synthetic target at E = {_fmt(truth['E'])}, nu = {_fmt(truth['nu'])}"
                + (f" on a {r}x refined mesh" if r > 1 else ""),
            )
            for s in scenes:
                if r > 1:
                    n = s["mesh"]["n"]
                    n = [k * r for k in n] if isinstance(n, (list, tuple)) else n * r
                    s = load_scene(s, overrides={"mesh.n": n})
                bt = sr.build(s)
                E_t, nu_t = truth["E"], truth["nu"]
                if labels is not None:  # per-cell values of the piecewise-constant truth
                    lab = labels if r == 1 else region_labels(bt.mesh, cfg["regions"])
                    E_t, nu_t = _per_region(E_t, n_reg)[lab], _per_region(nu_t, n_reg)[lab]
                p = Lame(*lame(jnp.asarray(E_t), jnp.asarray(nu_t), dim=dim, plane=plane))
                bt = bt._replace(params=p, potential=bt.potential.replace(params=p))
                x, _, _ = sr._static_solve(bt, progress, what="target solve")
                idx = (
                    np.arange(mesh.n_nodes) if r == 1 else nested_nodes(bt.mesh.points, mesh.points)
                )
                observed.append(np.asarray(x)[idx])
            avail = np.arange(mesh.n_nodes)
            sources = ["synthetic"] * len(scenes)
        else:
            files = [cfg["observed"]] + [c["observed"] for c in cfg["case"]]
            keys = ["[fit].observed"] + [f"[fit.case][{i}].observed" for i in range(len(files) - 1)]
            sources = [os.path.join(scene.base_dir, f) for f in files]
            node_sets = []
            for key, path in zip(keys, sources, strict=True):
                pos, nodes = _read_observed(v, key, path, mesh.n_nodes, dim)
                full = np.full((mesh.n_nodes, dim), np.nan)
                full[nodes] = pos
                observed.append(full)
                node_sets.append(nodes)
            avail = node_sets[0]
            for ns in node_sets[1:]:
                avail = np.intersect1d(avail, ns)
        markers = choose_markers(b0.bc.mask, cfg["markers"], cfg["seed"], avail)
        if markers.size == 0:
            raise v.err("[fit]: no observed node is free (all observed nodes are clamped)")
        X = np.asarray(mesh.points)
        cases, obs_arrays = [], {}
        for i, (b, xo) in enumerate(zip(builts, observed, strict=True)):
            xo_m = jnp.asarray(xo[markers])
            if cfg["noise"] > 0:
                key = jax.random.fold_in(jax.random.PRNGKey(cfg["seed"]), i)
                xo_m = add_noise(xo_m, jnp.asarray(X[markers]), cfg["noise"], key)
            obs_arrays[f"positions_{i}"] = np.asarray(xo_m)
            weight = 1.0 if i == 0 else cfg["case"][i - 1]["weight"]
            nodes = None if markers.size == mesh.n_nodes else jnp.asarray(markers)
            cases.append(
                LoadCase(
                    pot=b.potential,
                    bc=b.bc,
                    observed=xo_m,
                    nodes=nodes,
                    weight=weight,
                    linear=b.linear,
                )
            )
        summary["timings"]["target"] = time.perf_counter() - t0
        summary["cases"] = [
            dict(overrides=dict(c["set"]), weight=c.get("weight", 1.0), observed=src)
            for c, src in zip([{"set": {}}] + list(cfg["case"]), sources, strict=True)
        ]
        summary["observations"] = dict(
            n_markers=int(markers.size),
            fraction_of_nodes=markers.size / mesh.n_nodes,
            noise=cfg["noise"],
            seed=cfg["seed"],
        )
        summary["target"] = truth
        summary["initial"] = dict(cfg["initial"])

        # the fit
        _log(
            progress,
            f"fitting {', '.join(cfg['fields'])} on {len(cases)} load case(s), "
            f"{markers.size} observed nodes (the first iterations include compilation) ...",
        )
        t0 = time.perf_counter()
        settings = b0.settings._replace(rtol=min(b0.settings.rtol, 1e-10))
        init = Material(E=cfg["initial"]["E"], nu=cfg["initial"]["nu"])
        if labels is not None:
            init = Material(_per_region(init.E, n_reg), _per_region(init.nu, n_reg))
        res = fit(
            cases,
            init,
            regions=labels,
            fields=tuple(cfg["fields"]),
            plane=plane,
            optimizer=cfg["optimizer"],
            learning_rate=cfg["learning_rate"],
            max_iter=cfg["max_iter"],
            gtol=cfg["gtol"],
            settings=settings,
            progress=progress,
        )
        summary["timings"]["fit_incl_compile"] = time.perf_counter() - t0
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
        summary["result"] = result
        P = np.asarray(res.param_history)
        summary["history"] = dict(
            loss=res.loss_history,
            E=P[:, 0],
            nu=P[:, 1],
            grad_norm=res.grad_norm_history,
            newton_steps=res.newton_steps,
            linear_iterations=res.linear_iterations,
        )

        t0 = time.perf_counter()
        png = os.path.join(out, "fit.png")
        fig = _figure(res.loss_history, P, cfg["fields"], truth, f"{scene.name}: fit of (E, ν)")
        sr._save_png(fig, png)
        npz = os.path.join(out, "observed.npz")
        _write_atomic(npz, lambda tmp: _savez(tmp, nodes=markers, **obs_arrays))
        summary["outputs"] = dict(directory=out, summary=summary_path, png=[png], observed=npz)
        summary["timings"]["outputs"] = time.perf_counter() - t0
    except (SolveError, GradientError) as e:
        summary["status"] = "failed"
        summary["error"] = f"{type(e).__name__}: {e}"
        summary["timings"]["total"] = time.perf_counter() - t_start
        sr._write_json(summary_path, summary)
        raise
    summary["status"] = "ok"
    summary["timings"]["total"] = time.perf_counter() - t_start
    sr._write_json(summary_path, summary)
    return sr._jsonable(summary)


def _savez(tmp: str, **arrays) -> None:
    with open(tmp, "wb") as f:  # a file object: np.savez would append ".npz" to a name
        np.savez(f, **arrays)


def _fmt(x) -> str:
    return ", ".join(f"{a:.6g}" for a in np.atleast_1d(x))


def highlights(s: dict) -> str:
    """A few lines summarising a fit summary (for the command line)."""
    r = s["result"]
    lines = [
        f"fit of scene {s['scene']['name']!r}: {s['status']} ({r['stop_reason']}, "
        f"{r['iterations']} iterations, loss {r['loss']:.3e})"
    ]
    t = s.get("target")
    for k, name in (("E", "E "), ("nu", "nu")):
        err = ""
        if t:
            e = ", ".join(f"{a:.2e}" for a in np.atleast_1d(r[k + "_rel_error"]))
            err = f"  (true {_fmt(t[k])}, rel. error {e})"
        lines.append(f"  {name} = {_fmt(r[k])}{err}")
    o = s["observations"]
    lines.append(
        f"  {len(s['cases'])} load case(s), {o['n_markers']} observed nodes "
        f"({100 * o['fraction_of_nodes']:.1f} %), noise {o['noise']:g}"
    )
    lines.append(f"  total {s['timings']['total']:.1f} s; outputs in {s['outputs']['directory']}")
    return "\n".join(lines)
