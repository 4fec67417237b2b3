"""Material-identification studies: recovery, no inverse crime, noise, identifiability,
two-material bar.

Problem: a neo-Hookean cantilever (2D plane strain: 4 × 1; 3D: 4 × 1 × 1), clamped at
x = 0, with two load cases on the end face x = 4: *bend* (shear traction) and *stretch*
(normal traction). True material E* = 1 MPa, ν* = 0.3; every fit starts from
(3E*, ν* − 0.15) and uses :func:`jaxelastic.fitting.fit` (optax L-BFGS, implicit-adjoint
gradients, warm-started solves). Errors are relative: |E − E*|/E*, |ν − ν*|/ν*.

Studies (each prints a table and goes into ``report_fit.json``):

1. ``recovery``: targets on the fitting mesh itself (2D and 3D), all nodes observed or
   10 % random marker nodes; required: E and ν within 0.1 %.
2. ``no_inverse_crime``: 2D targets solved on a fine P2 (quadratic) mesh (128 × 32),
   observed at the fitting mesh's nodes (nested meshes: every coarse node is a fine node),
   fitted on sequences of P1 and of P2 meshes. Also reported: the forward
   discretisation error (relative displacement misfit of the fitting mesh at the *true*
   parameters, i.e. √loss(E*, ν*)), and the fit's final √loss and gradient norm: the
   optimiser converges (gradient ≈ 0, √loss at the fit ≤ √loss at the truth), so the
   remaining parameter error is the discretisation's.
3. ``noise``: 1 % Gaussian observation noise (σ = 1 % of the RMS displacement), several
   seeds, bend alone vs bend + stretch, all nodes or 10 % markers: mean ± std of the errors.
4. ``identifiability``: loss landscape over (E, ν) for bend alone and bend + stretch, and
   the loss Hessian in (ln E, ν) at the truth: ν's variance inflation 1/(1 − ρ²) from its
   correlation ρ with E (Bard 1974, *Nonlinear Parameter Estimation*, §7-5).
5. ``two_material``: a 2D bar whose left and right halves have different (E, ν), both
   cases, 10 % markers; per-region E and ν fitted (piecewise-constant field); also with
   1 % noise (required: both moduli within 2 %).

Usage::

    python scripts/report_fit.py --out out/report_fit            # full (about 7 min here)
    python scripts/report_fit.py --quick --out /tmp/report_fit   # small meshes, 2-4 min
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from jaxelastic.io import write_atomic, write_json

E_TRUE, NU_TRUE = 1.0e6, 0.3
LENGTH = 4.0
T_BEND, T_STRETCH = 2.0e3, 5.0e4  # [Pa]


def _savefig(fig, path: str) -> None:
    write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))


class Beam:
    """Cantilever mesh, clamp and the two end-face load vectors."""

    def __init__(self, n, order: int = 1):
        import jax.numpy as jnp

        import jaxelastic as je
        from jaxelastic import loads

        self.n = tuple(n)
        self.dim = len(n)
        self.order = order
        kw = {} if order == 1 else dict(order=order)
        if self.dim == 2:
            self.mesh = je.rectangle(*n, size=(LENGTH, 1.0), **kw)
        else:
            self.mesh = je.box(*n, size=(LENGTH, 1.0, 1.0), **kw)
        self.bc = loads.fix(self.mesh, loads.nodes_on_plane(self.mesh, 0, 0.0))
        end = loads.facets_where(self.mesh, lambda X: np.isclose(X[:, 0], LENGTH))
        d = self.dim
        tb = np.zeros(d)
        tb[-1] = -T_BEND
        ts = np.zeros(d)
        ts[0] = T_STRETCH
        self.f = dict(
            bend=jnp.asarray(loads.traction_load(self.mesh, end, tb)),
            stretch=jnp.asarray(loads.traction_load(self.mesh, end, ts)),
        )

    def params(self, E, nu):
        from jaxelastic.materials import Lame, lame

        mu, lam = lame(np.asarray(E), np.asarray(nu), dim=self.dim)
        return Lame(mu, lam)

    def pot(self, load, params):
        import jaxelastic as je

        return je.Potential(
            mesh=self.mesh, params=params, f_ext=self.f[load], psi=je.materials.neo_hookean
        )

    def solve(self, load, E, nu, labels=None):
        """Equilibrium positions ``(n_nodes, dim)`` at (E, ν) (per-cell via ``labels``)."""
        import jaxelastic as je

        if labels is not None:
            E, nu = np.asarray(E)[labels], np.asarray(nu)[labels]
        res = je.solve(
            self.pot(load, self.params(E, nu)),
            self.bc,
            solver=je.Newton(rtol=1e-12, linear="direct"),
        )
        return np.asarray(res.x)

    def cases(self, loads_, observed, nodes=None):
        import jax.numpy as jnp

        from jaxelastic.fitting import LoadCase

        out = []
        for load, xo in zip(loads_, observed, strict=True):
            xo = np.asarray(xo)
            out.append(
                LoadCase(
                    pot=self.pot(load, self.params(E_TRUE, NU_TRUE)),
                    bc=self.bc,
                    observed=jnp.asarray(xo if nodes is None else xo[nodes]),
                    nodes=None if nodes is None else jnp.asarray(nodes),
                )
            )
        return out


def _fit(cases, E0=3.0 * E_TRUE, nu0=NU_TRUE - 0.15, **kw):
    import jaxelastic as je
    from jaxelastic.fitting import Material, fit

    kw.setdefault("max_iter", 80)
    kw.setdefault("solver", je.Newton(rtol=1e-11))
    return fit(cases, Material(E0, nu0), **kw)


def _errs(E, nu, E_true=E_TRUE, nu_true=NU_TRUE):
    return abs(float(E) - E_true) / E_true, abs(float(nu) - nu_true) / abs(nu_true)


def _markers(beam: Beam, fraction: float, seed: int = 0):
    from jaxelastic.fitting import choose_markers

    return choose_markers(np.asarray(beam.bc.mask), fraction, seed)


# --------------------------------------------------------------------------------------
# studies
# --------------------------------------------------------------------------------------


def study_recovery(sizes: dict, log) -> list:
    rows = []
    for dim, n in sizes.items():
        beam = Beam(n)
        obs = [beam.solve(c, E_TRUE, NU_TRUE) for c in ("bend", "stretch")]
        for label, frac in (("all nodes", 1.0), ("10 % markers", 0.1)):
            nodes = None if frac == 1.0 else _markers(beam, frac)
            t = time.perf_counter()
            r = _fit(beam.cases(("bend", "stretch"), obs, nodes))
            eE, enu = _errs(r.E, r.nu)
            rows.append(
                dict(
                    dim=dim,
                    mesh=list(n),
                    n_cells=beam.mesh.n_cells,
                    n_nodes=beam.mesh.n_nodes,
                    observed=label,
                    n_observed=beam.mesh.n_nodes if nodes is None else int(nodes.size),
                    E=float(r.E),
                    nu=float(r.nu),
                    E_rel_error=eE,
                    nu_rel_error=enu,
                    iterations=int(r.iterations),
                    stop_reason=r.stop_reason,
                    wall_incl_compile=time.perf_counter() - t,
                    within_0p1_percent=bool(eE <= 1e-3 and enu <= 1e-3),
                )
            )
            log(f"recovery {dim}D {label}: E err {eE:.1e}, nu err {enu:.1e}")
    return rows


def study_no_inverse_crime(fit_sizes: dict, target: tuple, log) -> dict:
    """``fit_sizes``: element order → list of fitting meshes; ``target``: the P2 mesh of
    the targets (nested: every fitting-mesh node is a target-mesh node)."""
    from jaxelastic.fitting import nested_nodes

    fine = Beam(target, order=2)
    obs_fine = {c: fine.solve(c, E_TRUE, NU_TRUE) for c in ("bend", "stretch")}
    rows = []
    for order, sizes in fit_sizes.items():
        prev = None
        for n in sizes:
            beam = Beam(n, order=order)
            idx = nested_nodes(fine.mesh.points, beam.mesh.points)
            obs = [obs_fine[c][idx] for c in ("bend", "stretch")]
            X = np.asarray(beam.mesh.points)
            # forward discretisation error at the true parameters (per case, relative)
            fwd = []
            for c, xo in zip(("bend", "stretch"), obs, strict=True):
                x = beam.solve(c, E_TRUE, NU_TRUE)
                fwd.append(float(np.linalg.norm(x - xo) / np.linalg.norm(xo - X)))
            t = time.perf_counter()
            r = _fit(beam.cases(("bend", "stretch"), obs))
            eE, enu = _errs(r.E, r.nu)
            row = dict(
                element=f"P{order}",
                mesh=list(n),
                h=1.0 / n[1],
                n_cells=beam.mesh.n_cells,
                n_nodes=beam.mesh.n_nodes,
                E=float(r.E),
                nu=float(r.nu),
                E_rel_error=eE,
                nu_rel_error=enu,
                forward_error_bend=fwd[0],
                forward_error_stretch=fwd[1],
                sqrt_loss_at_truth=float(np.sqrt(sum(e * e for e in fwd))),
                sqrt_loss_at_fit=float(np.sqrt(r.loss)),
                final_grad_norm=float(r.grad_norm_history[-1]),
                iterations=int(r.iterations),
                stop_reason=r.stop_reason,
                wall_incl_compile=time.perf_counter() - t,
            )
            if prev is not None:
                row["E_rate"] = float(
                    np.log(prev["E_rel_error"] / eE) / np.log(prev["h"] / row["h"])
                )
            rows.append(row)
            prev = row
            log(f"no inverse crime P{order} {n}: E err {eE:.2e}, nu err {enu:.2e}, fwd err {fwd}")
    return dict(
        target_mesh=list(fine.n), target_element="P2", target_nodes=fine.mesh.n_nodes, rows=rows
    )


def study_noise(n, seeds: int, log, fractions=(1.0, 0.1)) -> list:
    import jax
    import jax.numpy as jnp

    from jaxelastic.fitting import add_noise

    beam = Beam(n)
    X = np.asarray(beam.mesh.points)
    clean = {c: beam.solve(c, E_TRUE, NU_TRUE) for c in ("bend", "stretch")}
    rows = []
    for frac in fractions:
        nodes = None if frac == 1.0 else _markers(beam, frac)
        for loads_ in (("bend",), ("bend", "stretch")):
            errs = []
            for s in range(seeds):
                obs = []
                for i, c in enumerate(loads_):
                    xo = clean[c] if nodes is None else clean[c][nodes]
                    ref = X if nodes is None else X[nodes]
                    key = jax.random.fold_in(jax.random.PRNGKey(s), i)
                    noisy = np.asarray(add_noise(jnp.asarray(xo), jnp.asarray(ref), 0.01, key))
                    full = np.array(clean[c])
                    if nodes is None:
                        full = noisy
                    else:
                        full[nodes] = noisy
                    obs.append(full)
                r = _fit(beam.cases(loads_, obs, nodes))
                errs.append(_errs(r.E, r.nu))
            e = np.array(errs)
            rows.append(
                dict(
                    mesh=list(n),
                    loads=" + ".join(loads_),
                    observed="all nodes" if nodes is None else f"{nodes.size} markers (10 %)",
                    seeds=seeds,
                    E_rel_error_mean=float(e[:, 0].mean()),
                    E_rel_error_std=float(e[:, 0].std()),
                    nu_rel_error_mean=float(e[:, 1].mean()),
                    nu_rel_error_std=float(e[:, 1].std()),
                    E_rel_error_max=float(e[:, 0].max()),
                    nu_rel_error_max=float(e[:, 1].max()),
                )
            )
            log(f"noise {rows[-1]['loads']} {rows[-1]['observed']}: {e.mean(0)} ± {e.std(0)}")
    return rows


def study_identifiability(n, grid: int, log) -> dict:
    from jaxelastic.fitting import Material, loss_hessian, loss_landscape

    beam = Beam(n)
    obs = {c: beam.solve(c, E_TRUE, NU_TRUE) for c in ("bend", "stretch")}
    Es = E_TRUE * np.geomspace(0.7, 1 / 0.7, grid)  # odd grid: the truth is a grid point
    nus = np.linspace(0.1, 0.45, grid) if grid > 5 else np.linspace(0.2, 0.4, grid)
    out = dict(mesh=list(n), E_values=Es, nu_values=nus)
    for name, loads_ in (("bend", ("bend",)), ("bend_stretch", ("bend", "stretch"))):
        cases = beam.cases(loads_, [obs[c] for c in loads_])
        L = loss_landscape(cases, Es, nus)
        H = loss_hessian(cases, Material(E_TRUE, NU_TRUE))
        rho = H[0, 1] / np.sqrt(H[0, 0] * H[1, 1])
        ev = np.linalg.eigvalsh(H)
        out[name] = dict(
            landscape=L,
            hessian_lnE_nu=H,
            correlation=float(-rho),  # of the (Gauss-Newton) parameter covariance
            nu_variance_inflation=float(1.0 / (1.0 - rho * rho)),
            condition_number=float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf"),
            # loss rise for ν off by 0.05 with E re-optimised (Schur complement)
            loss_rise_nu_0p05=float(0.5 * (H[1, 1] - H[0, 1] ** 2 / H[0, 0]) * 0.05**2),
        )
        log(f"identifiability {name}: rho {rho:.4f}, cond {out[name]['condition_number']:.3g}")
    return out


def study_two_material(n, log, noise_seeds: int = 0) -> dict:
    beam = Beam(n)
    cx = np.asarray(beam.mesh.points)[np.asarray(beam.mesh.cells)].mean(axis=1)[:, 0]
    labels = (cx > LENGTH / 2).astype(np.int32)
    E_t, nu_t = np.array([1.0e6, 2.5e6]), np.array([0.3, 0.4])
    obs = [beam.solve(c, E_t, nu_t, labels) for c in ("bend", "stretch")]
    nodes = _markers(beam, 0.1)
    t = time.perf_counter()
    r = _fit(
        beam.cases(("bend", "stretch"), obs, nodes),
        E0=np.full(2, 3.0 * E_TRUE),
        nu0=np.full(2, NU_TRUE - 0.15),
        regions=labels,
    )
    E, nu = np.asarray(r.E), np.asarray(r.nu)
    res = dict(
        mesh=list(n),
        n_markers=int(nodes.size),
        E_true=E_t,
        nu_true=nu_t,
        E=E,
        nu=nu,
        E_rel_error=np.abs(E - E_t) / E_t,
        nu_rel_error=np.abs(nu - nu_t) / nu_t,
        iterations=int(r.iterations),
        stop_reason=r.stop_reason,
        wall_incl_compile=time.perf_counter() - t,
    )
    res["within_2_percent"] = bool(np.all(res["E_rel_error"] <= 0.02))
    log(f"two-material: E {E}, nu {nu}")
    if noise_seeds:  # the same fit with 1 % noise, on the markers and on all nodes
        import jax
        import jax.numpy as jnp

        from jaxelastic.fitting import add_noise

        X = np.asarray(beam.mesh.points)
        all_nodes = np.arange(beam.mesh.n_nodes)
        res["noise_1_percent"] = []
        for label, sel in (("markers", nodes), ("all nodes", None)):
            idx = all_nodes if sel is None else sel
            errs = []
            for s in range(noise_seeds):
                noisy = []
                for i, xo in enumerate(obs):
                    key = jax.random.fold_in(jax.random.PRNGKey(s), i)
                    full = np.array(xo)
                    full[idx] = np.asarray(
                        add_noise(jnp.asarray(xo[idx]), jnp.asarray(X[idx]), 0.01, key)
                    )
                    noisy.append(full)
                rn = _fit(
                    beam.cases(("bend", "stretch"), noisy, sel),
                    E0=np.full(2, 3.0 * E_TRUE),
                    nu0=np.full(2, NU_TRUE - 0.15),
                    regions=labels,
                )
                errs.append(np.abs(np.asarray(rn.E) - E_t) / E_t)
            errs = np.array(errs)
            res["noise_1_percent"].append(
                dict(
                    observed=label,
                    seeds=noise_seeds,
                    E_rel_error_mean=errs.mean(0),
                    E_rel_error_max=errs.max(0),
                )
            )
            log(
                f"two-material, 1 % noise, {label}: E errors mean {errs.mean(0)}, max {errs.max(0)}"
            )
    return res


# --------------------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------------------


def _tables(rep: dict) -> str:
    L = []
    if "recovery" in rep:
        L.append("1. recovery on the target's own mesh (start E x3, nu - 0.15; bend + stretch)")
        L.append(f"{'dim':>3} {'mesh':>12} {'observed':>14} {'E err':>9} {'nu err':>9} {'its':>4}")
        for r in rep["recovery"]:
            L.append(
                f"{r['dim']:>3} {str(r['mesh']):>12} {r['observed']:>14} "
                f"{r['E_rel_error']:9.1e} {r['nu_rel_error']:9.1e} {r['iterations']:4d}"
            )
    if "no_inverse_crime" in rep:
        s = rep["no_inverse_crime"]
        L.append(
            f"\n2. no inverse crime: targets on P2 {s['target_mesh']} ({s['target_nodes']} nodes), "
            "observed at the fitting mesh's nodes"
        )
        L.append(
            f"{'el':>2} {'mesh':>10} {'h':>7} {'E err':>9} {'nu err':>9} {'rate E':>6} "
            f"{'fwd err bend':>12} {'fwd err str':>11} {'sqrt L(true)':>12} {'sqrt L(fit)':>11} "
            f"{'|g| end':>8}"
        )
        for r in s["rows"]:
            L.append(
                f"{r['element']:>2} {str(r['mesh']):>10} {r['h']:7.4f} {r['E_rel_error']:9.2e} "
                f"{r['nu_rel_error']:9.2e} {r.get('E_rate', float('nan')):6.2f} "
                f"{r['forward_error_bend']:12.2e} {r['forward_error_stretch']:11.2e} "
                f"{r['sqrt_loss_at_truth']:12.2e} {r['sqrt_loss_at_fit']:11.2e} "
                f"{r['final_grad_norm']:8.1e}"
            )
    if "noise" in rep:
        L.append("\n3. 1 % observation noise (mean ± std over seeds)")
        L.append(f"{'loads':>16} {'observed':>22} {'E err':>19} {'nu err':>19}")
        for r in rep["noise"]:
            L.append(
                f"{r['loads']:>16} {r['observed']:>22} "
                f"{r['E_rel_error_mean']:9.2e}±{r['E_rel_error_std']:8.1e} "
                f"{r['nu_rel_error_mean']:9.2e}±{r['nu_rel_error_std']:8.1e}"
            )
    if "identifiability" in rep:
        s = rep["identifiability"]
        L.append(f"\n4. identifiability on {s['mesh']}: loss Hessian in (ln E, nu) at the truth")
        L.append(f"{'loads':>14} {'corr(lnE,nu)':>12} {'nu var. infl.':>13} {'cond':>9}")
        for k in ("bend", "bend_stretch"):
            r = s[k]
            L.append(
                f"{k:>14} {r['correlation']:12.4f} {r['nu_variance_inflation']:13.3g} "
                f"{r['condition_number']:9.3g}"
            )
    if "two_material" in rep:
        r = rep["two_material"]
        L.append(f"\n5. two-material bar {r['mesh']}, {r['n_markers']} markers")
        for i in range(2):
            L.append(
                f"  region {i}: E {r['E'][i]:.6g} (true {r['E_true'][i]:.3g}, err "
                f"{r['E_rel_error'][i]:.1e}), nu {r['nu'][i]:.5f} (true {r['nu_true'][i]}, "
                f"err {r['nu_rel_error'][i]:.1e})"
            )
        for nz in r.get("noise_1_percent", []):
            L.append(
                f"  with 1 % noise ({nz['observed']}, {nz['seeds']} seeds): E errors mean "
                f"{np.round(nz['E_rel_error_mean'], 4).tolist()}, max "
                f"{np.round(nz['E_rel_error_max'], 4).tolist()}"
            )
    return "\n".join(L)


def _plots(rep: dict, out: str) -> list:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    if "no_inverse_crime" in rep:
        allrows = rep["no_inverse_crime"]["rows"]
        fig, ax = plt.subplots(figsize=(6, 4.2))
        for el, color in (("P1", "C0"), ("P2", "C3")):
            rows = [r for r in allrows if r["element"] == el]
            if not rows:
                continue
            h = np.array([r["h"] for r in rows])
            for key, lab, m in (
                ("E_rel_error", "E error", "o-"),
                ("nu_rel_error", "ν error", "s-"),
                ("forward_error_bend", "fwd error at truth, bend", "^:"),
            ):
                v = np.maximum([r[key] for r in rows], 1e-16)
                ax.loglog(h, v, m, color=color, label=f"{el} {lab}", alpha=0.9)
        ax.axhline(0.01, color="k", lw=0.7, ls=":", label="1 %")
        ax.set(
            xlabel="fitting-mesh size h (elements through the depth: 1/h)",
            ylabel="relative error",
            title="Fit against a finer-mesh target (2D)",
        )
        ax.invert_xaxis()
        ax.legend(fontsize=7)
        fig.tight_layout()
        p = os.path.join(out, "no_inverse_crime.png")
        _savefig(fig, p)
        plt.close(fig)
        paths.append(p)
    if "identifiability" in rep:
        s = rep["identifiability"]
        fig, axs = plt.subplots(1, 2, figsize=(10, 4))
        for ax, k, title in zip(
            axs, ("bend", "bend_stretch"), ("bend only", "bend + stretch"), strict=True
        ):
            # colour floor at 1e-5: show the valley, not the exact zero at the truth
            Lg = np.log10(np.maximum(np.asarray(s[k]["landscape"], float), 1e-5))
            cs = ax.contourf(np.asarray(s["nu_values"]), np.asarray(s["E_values"]) / 1e6, Lg, 20)
            fig.colorbar(cs, ax=ax, label="log10 loss")
            ax.plot(NU_TRUE, E_TRUE / 1e6, "r*", ms=12)
            ax.set(
                xlabel="ν",
                ylabel="E [MPa]",
                title=f"{title}: corr(ln E, ν) = {s[k]['correlation']:.3f}",
            )
        fig.tight_layout()
        p = os.path.join(out, "identifiability.png")
        _savefig(fig, p)
        plt.close(fig)
        paths.append(p)
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/report_fit")
    ap.add_argument("--quick", action="store_true", help="small meshes and few seeds")
    ap.add_argument(
        "--studies",
        default="recovery,no_inverse_crime,noise,identifiability,two_material",
        help="comma-separated subset (default: all)",
    )
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)

    def log(msg):
        print(f"[report_fit] {msg}", file=sys.stderr, flush=True)

    q = args.quick
    studies = set(args.studies.split(","))
    t0 = time.perf_counter()
    rep: dict = dict(quick=q, E_true=E_TRUE, nu_true=NU_TRUE, start=[3 * E_TRUE, NU_TRUE - 0.15])
    if q:
        plan = dict(
            recovery=lambda: study_recovery({2: (8, 2), 3: (4, 1, 1)}, log),
            no_inverse_crime=lambda: study_no_inverse_crime(
                {1: [(4, 1), (8, 2)], 2: [(4, 1)]}, (16, 4), log
            ),
            noise=lambda: study_noise((8, 2), 2, log, fractions=(1.0,)),
            identifiability=lambda: study_identifiability((8, 2), 5, log),
            two_material=lambda: study_two_material((8, 2), log),
        )
    else:
        plan = dict(
            recovery=lambda: study_recovery({2: (16, 4), 3: (12, 3, 3)}, log),
            no_inverse_crime=lambda: study_no_inverse_crime(
                {1: [(8, 2), (16, 4), (32, 8), (64, 16)], 2: [(4, 1), (8, 2), (16, 4), (32, 8)]},
                (128, 32),
                log,
            ),
            noise=lambda: study_noise((16, 4), 5, log),
            identifiability=lambda: study_identifiability((16, 4), 15, log),
            two_material=lambda: study_two_material((16, 4), log, noise_seeds=3),
        )
    unknown = studies - set(plan)
    if unknown:
        ap.error(f"unknown studies {sorted(unknown)} (valid: {', '.join(plan)})")
    rep["timings"] = {}
    for name, run in plan.items():
        if name in studies:
            t = time.perf_counter()
            rep[name] = run()
            rep["timings"][name] = time.perf_counter() - t
    rep["wall_time"] = time.perf_counter() - t0
    print(_tables(rep))
    os.makedirs(args.out, exist_ok=True)
    rep["figures"] = _plots(rep, args.out)
    write_json(os.path.join(args.out, "report_fit.json"), rep, indent=1, nonfinite="null")
    print(f"wrote {args.out}/report_fit.json ({rep['wall_time']:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
