"""Throughput of the per-element kernels and of the assembly, in 2D and 3D.

Measures, for each material model, dimension (``rectangle`` triangles / ``box`` tets) and
mesh size (about 10k, 100k and 1M elements), in float64 on the default JAX device:

* ``energy``            total energy (``jaxelastic.mechanics.kernels.energy``);
* ``forces``            autodiff forces (``jaxelastic.forces``: P = ∂ψ/∂F by autodiff,
                        element forces, ``assemble`` over the node→slot incidence table);
* ``forces_handP``      the same machinery with P from ``reference.HAND_P[model]`` (injected
                        as the gradient of a ``custom_vjp`` pseudo-ψ, so only P changes);
* ``forces_handP_cof``  neo-Hookean only: a hand P written with ``cof F / J`` instead of
                        ``jnp.linalg.inv`` (the reference P's LAPACK inverse is slow on CPU);
* ``elem_forces``       ``element_forces`` alone, ``(n_cells, k, d)``: gather of x + arithmetic,
                        no assembly (the "per-element arithmetic alone");
* ``elem_kernel``       the element kernel on pre-gathered ``x[cells]`` (pure arithmetic);
* ``forces_gather_dense`` element forces + the previous assembly (gather a
                        ``(n_nodes, valence, d)`` array from the incidence table, then sum);
* ``forces_scatter``    element forces + unsorted ``.at[].add`` scatter;
* ``forces_segsum``     element forces + ``jax.ops.segment_sum`` on sorted indices
                        (host-precomputed permutation);
* ``forces_jaxgrad``    ``-jax.grad(energy)`` (JAX's own transpose/scatter path);
* ``hvp``               Hessian-vector product; ``elem_hess`` / ``elem_hess_psd`` element
                        Hessians without / with PSD projection;
* ``asm_incidence`` / ``asm_gather_dense`` / ``asm_scatter`` / ``asm_segsum``  the assembly
                        alone of a given ``(n_cells, k, d)`` array (model independent,
                        measured once per mesh).

Every kernel is ``jax.jit``-ed with the mesh (and all other arrays) as *arguments* — never
closed over, so nothing is constant-folded; the size of the lowered (StableHLO) text is
reported as evidence (kB, independent of the mesh size when nothing is folded in).
Compile time (lower + compile) is reported separately; run time is the median (and min) of
several warm repeats after one warm-up call, synchronised with ``jax.block_until_ready``.
Throughput is elements per second. Ratios reported: ``forces / forces_handP`` (target
≤ 1.1) and ``forces / elem_forces`` (target ≤ 1.25). The machine load average is recorded:
other processes on a small machine make timings noisy (compare the min column then).

Elements (``--elements``, default ``p1``): ``p2`` (``tri6``/``tet10``), ``p2fbar`` (P2 with
the F-bar formulation) and ``composite`` (``tri3x4``/``tet4x8`` with F-bar). For those only
``energy``, ``forces``, ``hvp``, ``elem_hess`` and ``asm_incidence`` are timed (the other
variants are P1 studies); the size is the number of cells (patches for ``composite``), and
throughput is also reported per degree of freedom (``dofs_per_s``), the fair comparison
across element orders at equal accuracy-relevant resolution.

Usage::

    python scripts/bench_kernels.py [--sizes small|medium|all] [--models neo_hookean,...]
                                    [--dims 2,3] [--elements p1,p2,p2fbar,composite]
                                    [--out DIR]

Element-Hessian targets (``--hessian-targets``): tet4 / tet10 / tet10 F-bar at
about 100k cells (``--hessian-cells``), for neo-Hookean and corotated (an SVD-based model
with custom JVPs), each row in its own subprocess so that its peak RSS is its own:
``contracted`` (``je.mechanics.element_hessians``: Kₑ = Σ_q B_qᵀ Ĉ_q B_q), ``previous`` (the former
implementation: the ``"q,qkb,qabcd,qld->kalc"`` einsum for P1/P2, ``jax.hessian`` of the
element energy over the element coordinates for F-bar; at ``--previous-cells`` where that
is slow) and ``C_only`` (``vmap(jax.hessian(ψ))`` over all quadrature points, the share
of C). Min of 3 warm calls, CPU seconds, peak RSS; JSON to ``--out``
(``bench_kernels_hessians.json``)::

    python scripts/bench_kernels.py --hessian-targets --out out/bench

``--sizes small`` is 10k elements only, ``medium`` 10k and 100k, ``all`` adds 1M. A kernel
whose run time, extrapolated from the previous size, exceeds ``--budget`` seconds per
measurement is skipped with the reason printed (e.g. PSD projection at 1M).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxelastic as je
from jaxelastic import materials
from jaxelastic.io import write_json
from jaxelastic.materials import reference
from jaxelastic.mechanics import cell_params_axes, element_gradient_kernel, kinematics

SIZES = {"small": (10_000,), "medium": (10_000, 100_000), "all": (10_000, 100_000, 1_000_000)}


# --------------------------------------------------------------------------- meshes


ELEMENT_KW = {
    "p1": {},
    "p2": {"order": 2},
    "p2fbar": {"order": 2, "formulation": "fbar"},
    "composite": {"order": 1, "formulation": "fbar"},
}
P2_KERNELS = ("energy", "forces", "hvp", "elem_hess")


def make_mesh(dim: int, target: int, element: str = "p1") -> je.Mesh:
    """Structured mesh of the unit square/cube with about ``target`` cells."""
    kw = ELEMENT_KW[element]
    if dim == 2:
        n = max(1, round((target / 2) ** 0.5))
        return je.rectangle(n, n, **kw)
    n = max(1, round((target / 6) ** (1 / 3)))
    return je.box(n, n, n, **kw)


def deformed(mesh: je.Mesh, seed: int = 0) -> tuple[jax.Array, jax.Array]:
    """A smooth stretch plus small noise (no inverted element) and a random direction v."""
    rng = np.random.default_rng(seed)
    X = np.asarray(mesh.points)
    d = X.shape[1]
    h = 1.0 / round(mesh.n_nodes ** (1 / d))  # ≈ grid spacing of the unit square/cube
    A = np.eye(d) + 0.1 * np.triu(np.ones((d, d)))
    x = X @ A.T + 0.05 * h * rng.standard_normal(X.shape)
    v = rng.standard_normal(X.shape)
    return jnp.asarray(x), jnp.asarray(v)


# --------------------------------------------------------------------------- kernels


def psi_with_P(psi, P):
    """A pseudo-ψ whose autodiff gradient is exactly ``P`` (to reuse the energy machinery)."""

    @jax.custom_vjp
    def f(F, p):
        return psi(F, p)

    def fwd(F, p):
        return psi(F, p), (P(F, p), p)

    def bwd(res, g):
        PF, p = res
        return g * PF, jax.tree_util.tree_map(jnp.zeros_like, p)

    f.defvjp(fwd, bwd)
    return f


def P_neo_hookean_cof(F, p):
    """Neo-Hookean ``P = μ(F − F⁻ᵀ) + λ ln J F⁻ᵀ`` with ``F⁻ᵀ = cof F / J`` (no LAPACK)."""
    J = kinematics.det(F)
    FinvT = kinematics.cofactor(F) / J
    return p.mu * (F - FinvT) + p.lam * jnp.log(J) * FinvT


FAST_HAND_P = {"neo_hookean": P_neo_hookean_cof}


def scatter_add(mesh, pe):
    """Unsorted scatter-add assembly of ``(n_cells, k, d)`` into ``(n_nodes, d)``."""
    d = pe.shape[-1]
    return jnp.zeros((mesh.n_nodes, d), pe.dtype).at[mesh.cells.reshape(-1)].add(pe.reshape(-1, d))


def gather_dense(mesh, pe):
    """The previous ``assemble``: gather ``(n_nodes, valence, d)`` from the incidence table,
    then sum over the valence axis (padding slot = an appended zero row)."""
    c, k, d = pe.shape
    flat = jnp.concatenate([pe.reshape(c * k, d), jnp.zeros((1, d), pe.dtype)])
    return flat[mesh.incidence].sum(axis=1)


def segsum_sorted(mesh, pe, perm, seg):
    """``segment_sum`` over slots sorted by node (``perm``: slot order, ``seg``: node ids)."""
    d = pe.shape[-1]
    return jax.ops.segment_sum(
        pe.reshape(-1, d)[perm], seg, num_segments=mesh.n_nodes, indices_are_sorted=True
    )


def sorted_slots(mesh) -> tuple[jax.Array, jax.Array]:
    """Host-precomputed ``(perm, node_of_sorted_slot)`` for :func:`segsum_sorted`."""
    flat = np.asarray(mesh.cells).ravel()
    perm = np.argsort(flat, kind="stable")
    return jnp.asarray(perm, dtype=jnp.int32), jnp.asarray(flat[perm], dtype=jnp.int32)


def model_kernels(name: str, psi) -> dict:
    """Kernel name → ``fn(x, v, mesh, params, perm, seg)`` for one material model."""
    hand = psi_with_P(psi, reference.HAND_P[name])

    def elem_kernel(x, v, m, p, perm, seg):
        fe = jax.vmap(
            element_gradient_kernel(psi), in_axes=(0, 0, 0, cell_params_axes(p, m.n_cells))
        )
        return fe(x[m.cells], m.dN, m.weights, p)

    ks = {
        "energy": lambda x, v, m, p, perm, seg: je.energy(psi, x, m, p),
        "forces": lambda x, v, m, p, perm, seg: je.forces(psi, x, m, p),
        "forces_handP": lambda x, v, m, p, perm, seg: je.forces(hand, x, m, p),
    }
    if name in FAST_HAND_P:
        fast = psi_with_P(psi, FAST_HAND_P[name])
        ks["forces_handP_cof"] = lambda x, v, m, p, perm, seg: je.forces(fast, x, m, p)
    ks.update(
        {
            "elem_forces": lambda x, v, m, p, perm, seg: je.mechanics.element_gradients(
                psi, x, m, p
            ),
            "elem_kernel": elem_kernel,
            "forces_gather_dense": lambda x, v, m, p, perm, seg: (
                -gather_dense(m, je.mechanics.element_gradients(psi, x, m, p))
            ),
            "forces_scatter": lambda x, v, m, p, perm, seg: (
                -scatter_add(m, je.mechanics.element_gradients(psi, x, m, p))
            ),
            "forces_segsum": lambda x, v, m, p, perm, seg: (
                -segsum_sorted(m, je.mechanics.element_gradients(psi, x, m, p), perm, seg)
            ),
            "forces_jaxgrad": lambda x, v, m, p, perm, seg: (
                -jax.grad(je.energy, argnums=1)(psi, x, m, p)
            ),
            "hvp": lambda x, v, m, p, perm, seg: je.mechanics.hvp(psi, x, v, m, p),
            "elem_hess": lambda x, v, m, p, perm, seg: je.mechanics.element_hessians(psi, x, m, p),
            "elem_hess_psd": lambda x, v, m, p, perm, seg: je.mechanics.element_hessians(
                psi, x, m, p, project=True
            ),
        }
    )
    return ks


ASSEMBLY = {
    "asm_incidence": lambda pe, m, perm, seg: je.mechanics.assemble(m, pe),
    "asm_gather_dense": lambda pe, m, perm, seg: gather_dense(m, pe),
    "asm_scatter": lambda pe, m, perm, seg: scatter_add(m, pe),
    "asm_segsum": lambda pe, m, perm, seg: segsum_sorted(m, pe, perm, seg),
}

FORCE_VARIANTS = (
    "forces_handP",
    "forces_gather_dense",
    "forces_handP_cof",
    "forces_scatter",
    "forces_segsum",
    "forces_jaxgrad",
)


# --------------------------------------------------------------------------- timing


def measure(fn, args, *, min_repeats: int, min_time: float, max_repeats: int = 50) -> dict:
    """Compile ``jax.jit(fn)`` for ``args`` and time warm calls; returns seconds."""
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    hlo_kb = len(lowered.as_text()) / 1024
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    out = jax.block_until_ready(compiled(*args))  # warm-up
    times: list[float] = []
    while len(times) < min_repeats or (sum(times) < min_time and len(times) < max_repeats):
        t = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t)
    return {
        "compile_s": compile_s,
        "hlo_kb": hlo_kb,
        "median_s": float(np.median(times)),
        "min_s": float(np.min(times)),
        "repeats": len(times),
        "out": out,
    }


def _rel_err(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def bench_case(
    models, dim: int, target: int, *, min_repeats, min_time, budget, rates, log, element="p1"
) -> tuple[list, list]:
    """Run every kernel on one mesh; ``rates`` carries s/element from the previous size."""
    t0 = time.perf_counter()
    mesh = make_mesh(dim, target, element)
    x, v = deformed(mesh)
    perm, seg = sorted_slots(mesh)
    c = mesh.n_cells
    log(
        f"\n== {dim}D {element} ({mesh.element}, {mesh.formulation}), {c} cells, "
        f"{mesh.n_nodes} nodes (mesh built in {time.perf_counter() - t0:.1f} s) =="
    )
    rows, skipped = [], []

    def run(model, kernel, fn, args, reference_out=None):
        key = (model, dim, kernel, element)
        if key in rates and rates[key] * c * (min_repeats + 1) > budget:
            why = (
                f"estimated {rates[key] * c:.1f} s per call from the previous size; "
                f"{min_repeats + 1} calls exceed --budget {budget:.0f} s"
            )
            log(f"  {model:>16s} {kernel:<17s} SKIPPED: {why}")
            skipped.append(
                {
                    "model": model,
                    "dim": dim,
                    "n_cells": c,
                    "kernel": kernel,
                    "reason": why,
                    "element": element,
                }
            )
            return None
        r = measure(fn, args, min_repeats=min_repeats, min_time=min_time)
        out = r.pop("out")
        if reference_out is not None:
            r["rel_err_vs_forces"] = _rel_err(out, reference_out)
        rates[key] = r["median_s"] / c
        r.update(
            model=model,
            dim=dim,
            n_cells=c,
            n_nodes=mesh.n_nodes,
            kernel=kernel,
            elems_per_s=c / r["median_s"],
            element=element,
            mesh_element=mesh.element,
            formulation=mesh.formulation,
            n_dofs=mesh.n_dofs,
            dofs_per_s=mesh.n_dofs / r["median_s"],
        )
        rows.append(r)
        extra = f"  err={r['rel_err_vs_forces']:.1e}" if "rel_err_vs_forces" in r else ""
        log(
            f"  {model:>16s} {kernel:<17s} {r['median_s'] * 1e3:10.2f} ms "
            f"(min {r['min_s'] * 1e3:9.2f})  {r['elems_per_s'] / 1e6:7.2f} Melem/s  "
            f"{r['dofs_per_s'] / 1e6:7.2f} Mdof/s  "
            f"compile {r['compile_s']:5.2f} s  hlo {r['hlo_kb']:6.0f} kB{extra}"
        )
        return out

    rng = np.random.default_rng(1)
    pe = jnp.asarray(rng.standard_normal((c, mesh.cells.shape[1], dim)))
    for kernel, fn in ASSEMBLY.items():
        if element == "p1" or kernel == "asm_incidence":
            run("-", kernel, fn, (pe, mesh, perm, seg))
    del pe

    params = je.Lame(jnp.asarray(1.0e3 / 2.6), jnp.asarray(1.0e3 * 0.3 / (1.3 * 0.4)))
    for name in models:
        if name == "stable_neo_hookean_log" and dim == 2:
            log(f"  {name}: 3D only, skipped in 2D")
            continue
        ref_out = None
        for kernel, fn in model_kernels(name, materials.BUILTIN[name]).items():
            if element != "p1" and kernel not in P2_KERNELS:
                continue
            args = (x, v, mesh, params, perm, seg)
            out = run(name, kernel, fn, args, ref_out if kernel in FORCE_VARIANTS else None)
            if kernel == "forces":
                ref_out = out
            del out
    return rows, skipped


RATIOS = (  # (printed label, numerator kernel, denominator kernel); "-" = assembly alone
    ("f/handP", "forces", "forces_handP"),
    ("f/handPcof", "forces", "forces_handP_cof"),
    ("f/elem", "forces", "elem_forces"),
    ("f/kernel", "forces", "elem_kernel"),
    ("f/dense", "forces", "forces_gather_dense"),
    ("f/scatter", "forces", "forces_scatter"),
    ("f/segsum", "forces", "forces_segsum"),
    ("f/jaxgrad", "forces", "forces_jaxgrad"),
    ("f/energy", "forces", "energy"),
    ("asm/dense", "-asm_incidence", "-asm_gather_dense"),
    ("asm/scat", "-asm_incidence", "-asm_scatter"),
    ("asm/seg", "-asm_incidence", "-asm_segsum"),
)


def ratios(rows) -> list[dict]:
    """The target ratios per (model, dim, size), from median and from min times.

    ``f/handP = forces / forces_handP`` (target ≤ 1.1), ``f/elem = forces / elem_forces``
    (target ≤ 1.25); ``asm/scat`` etc. compare the assembly alone (< 1: ``assemble`` faster).
    """
    by = {
        (r["model"], r["dim"], r["n_cells"], r["kernel"]): r
        for r in rows
        if r.get("element", "p1") == "p1"
    }
    out = []
    for model, dim, c, kernel in by:
        if kernel != "forces":
            continue

        def get(k, model=model, dim=dim, c=c):
            return by.get(("-", dim, c, k[1:]) if k.startswith("-") else (model, dim, c, k))

        entry = {"model": model, "dim": dim, "n_cells": c, "ratios": {}}
        for label, num, den in RATIOS:
            a, b = get(num), get(den)
            if a and b:
                entry["ratios"][label] = {
                    "median": a["median_s"] / b["median_s"],
                    "min": a["min_s"] / b["min_s"],
                    "of": f"{num.lstrip('-')} / {den.lstrip('-')}",
                }
        out.append(entry)
    return out


def format_tables(rows, rats) -> str:
    """Plain-text tables: median and min ms and Melem/s per kernel and size, and ratios."""
    lines = []
    for model, element in dict.fromkeys((r["model"], r.get("element", "p1")) for r in rows):
        for dim in sorted({r["dim"] for r in rows if r["model"] == model}):
            sel = [
                r
                for r in rows
                if r["model"] == model and r["dim"] == dim and r.get("element", "p1") == element
            ]
            if not sel:
                continue
            sizes = sorted({r["n_cells"] for r in sel})
            title = ("assembly alone" if model == "-" else model) + f" [{sel[0]['mesh_element']}"
            title += f", {sel[0]['formulation']}]"
            lines.append(
                f"\n{title}, {dim}D — per size: median ms, min ms, Melem/s (from the median);"
                " compile s at the largest size"
            )
            lines.append(f"{'kernel':<20s}" + "".join(f"{s:>28,d}" for s in sizes) + "   compile")
            for kernel in dict.fromkeys(r["kernel"] for r in sel):
                cells, comp = [], ""
                for s in sizes:
                    r = next((r for r in sel if r["n_cells"] == s and r["kernel"] == kernel), None)
                    if r is None:
                        cells.append(f"{'skipped':>28s}")
                    else:
                        cells.append(
                            f"{r['median_s'] * 1e3:10.2f}{r['min_s'] * 1e3:10.2f}"
                            f"{r['elems_per_s'] / 1e6:8.2f}"
                        )
                        comp = f"{r['compile_s']:10.2f}"
                lines.append(f"{kernel:<20s}" + "".join(cells) + comp)
    if any(r.get("element", "p1") != "p1" for r in rows):
        lines.append("\nper-dof throughput (median): model, element, dim, cells, dofs, kernel")
        for r in rows:
            if r["model"] == "-":
                continue
            lines.append(
                f"{r['model']:<16s}{r['mesh_element'] + '/' + r['formulation']:>16s}"
                f"{r['dim']:>3d}{r['n_cells']:>9d}{r['n_dofs']:>9d}  {r['kernel']:<12s}"
                f"{r['dofs_per_s'] / 1e6:9.3f} Mdof/s{r['elems_per_s'] / 1e6:9.3f} Melem/s"
            )
    if rats:
        lines.append(
            "\nratios, median (min) times; targets: f/handP = forces/forces_handP ≤ 1.1, "
            "f/elem = forces/elem_forces ≤ 1.25"
        )
        labels = [lab for lab, _, _ in RATIOS if any(lab in e["ratios"] for e in rats)]
        lines.append(
            f"{'model':<16s}{'dim':>4s}{'cells':>9s}" + "".join(f"{k:>14s}" for k in labels)
        )
        for e in rats:
            vals = []
            for k in labels:
                r = e["ratios"].get(k)
                vals.append(f"{r['median']:7.2f} ({r['min']:4.2f})" if r else f"{'-':>14s}")
            lines.append(f"{e['model']:<16s}{e['dim']:>4d}{e['n_cells']:>9d}" + "".join(vals))
    return "\n".join(lines)


# ------------------------------------------------------------- element-Hessian targets

HESSIAN_TARGETS = (("p1", 3.0), ("p2", 0.3), ("p2fbar", 0.1))  # (element, M el/s target)
HESSIAN_MODELS = ("neo_hookean", "corotated")


def _previous_element_hessians(psi, x, mesh, params):
    """The former implementation: einsum contraction for the standard formulation, and
    ``jax.hessian`` of the element energy over the element coordinates for F-bar/B-bar."""
    from jaxelastic.mechanics import element_hessians_reference

    if mesh.formulation != "standard":
        return element_hessians_reference(psi, x, mesh, params)
    u = x - mesh.points
    ue = u[mesh.cells]
    c, k, d = ue.shape
    F = jnp.einsum("cka,cqkb->cqab", ue, mesh.dN) + jnp.eye(d, dtype=x.dtype)
    H = jax.vmap(jax.vmap(jax.hessian(psi), in_axes=(0, None)), in_axes=(0, None))
    C = H(F, params)
    K = jnp.einsum("cq,cqkb,cqabxe,cqle->ckalx", mesh.weights, mesh.dN, C, mesh.dN)
    return K.reshape(c, k * d, k * d)


def _hessian_C_only(psi, x, mesh, params):
    """``∂²ψ/∂F²`` at every quadrature point (the autodiff share of Kₑ)."""
    F = je.kinematics.deformation_gradients(x, mesh, fbar=False)
    H = jax.vmap(jax.vmap(jax.hessian(psi), in_axes=(0, None)), in_axes=(0, None))
    return H(F, params)


HESSIAN_KERNELS = {
    "contracted": lambda psi: lambda x, m, p: je.mechanics.element_hessians(psi, x, m, p),
    "previous": lambda psi: lambda x, m, p: _previous_element_hessians(psi, x, m, p),
    "C_only": lambda psi: lambda x, m, p: _hessian_C_only(psi, x, m, p),
}


def hessian_row(element: str, model: str, kernel: str, target: int, repeats: int = 3) -> dict:
    """One element-Hessian row, timed in this process: compile, ``repeats`` warm calls."""
    import resource

    jax.config.update("jax_enable_x64", True)
    mesh = make_mesh(3, target, element)
    x, _ = deformed(mesh)
    params = je.Lame(jnp.asarray(1.0e3 / 2.6), jnp.asarray(1.0e3 * 0.3 / (1.3 * 0.4)))
    fn = jax.jit(HESSIAN_KERNELS[kernel](materials.BUILTIN[model]))
    t0 = time.perf_counter()
    compiled = fn.lower(x, mesh, params).compile()
    compile_s = time.perf_counter() - t0
    out = jax.block_until_ready(compiled(x, mesh, params))
    out_bytes = int(out.nbytes)
    del out
    walls, cpus = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(compiled(x, mesh, params))
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return {
        "element": element,
        "mesh_element": mesh.element,
        "formulation": mesh.formulation,
        "model": model,
        "kernel": kernel,
        "n_cells": mesh.n_cells,
        "compile_s": compile_s,
        "min_s": min(walls),
        "times_s": walls,
        "min_cpu_s": min(cpus),
        "melem_per_s": mesh.n_cells / min(walls) / 1e6,
        "out_mib": out_bytes / 2**20,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "load_average": os.getloadavg()[0],
    }


def hessian_targets(cells: int, previous_cells: int, out_dir: str | None, log) -> dict:
    """All element-Hessian target rows, each in a fresh subprocess (own peak RSS)."""
    import json
    import subprocess

    rows = []
    for element, goal in HESSIAN_TARGETS:
        for model in HESSIAN_MODELS:
            for kernel in HESSIAN_KERNELS:
                n = previous_cells if (kernel == "previous" and element != "p1") else cells
                cmd = [sys.executable, __file__, "--hessian-row", f"{element},{model},{kernel},{n}"]
                res = subprocess.run(cmd, capture_output=True, text=True)
                if res.returncode != 0:
                    log(f"  {element} {model} {kernel}: FAILED\n{res.stderr[-2000:]}")
                    rows.append(
                        {
                            "element": element,
                            "model": model,
                            "kernel": kernel,
                            "error": res.stderr[-2000:],
                        }
                    )
                    continue
                r = json.loads(res.stdout.strip().splitlines()[-1])
                r["target_melem_per_s"] = goal if kernel == "contracted" else None
                rows.append(r)
                log(
                    f"  {r['mesh_element']:>6s} {r['formulation']:<8s} {model:<12s} {kernel:<10s}"
                    f" {r['n_cells']:>7d} cells  min {r['min_s'] * 1e3:9.1f} ms (cpu "
                    f"{r['min_cpu_s'] * 1e3:8.1f})  {r['melem_per_s']:7.3f} M el/s"
                    + (f" (target {goal})" if kernel == "contracted" else "")
                    + f"  compile {r['compile_s']:5.1f} s  peak RSS {r['peak_rss_mib']:7.0f} MiB"
                    f"  load {r['load_average']:.1f}"
                )
    result = {
        "meta": {
            "command": " ".join([os.path.basename(sys.argv[0])] + sys.argv[1:]),
            "jax": jax.__version__,
            "cpu_count": os.cpu_count(),
            "machine": platform.machine(),
            "dtype": "float64",
            "repeats": 3,
            "timing": "min of 3 warm calls after compile + 1 call",
        },
        "results": rows,
    }
    if out_dir:
        path = os.path.join(out_dir, "bench_kernels_hessians.json")
        os.makedirs(out_dir, exist_ok=True)
        write_json(path, result, indent=1, nonfinite="string")
        log(f"wrote {path}")
    return result


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", choices=list(SIZES), default="all")
    ap.add_argument(
        "--models",
        default="neo_hookean",
        help="comma-separated names from jaxelastic.materials.BUILTIN",
    )
    ap.add_argument("--dims", default="2,3")
    ap.add_argument(
        "--elements",
        default="p1",
        help=f"comma-separated element choices from {sorted(ELEMENT_KW)}",
    )
    ap.add_argument("--out", default=None, help="directory for bench_kernels.json")
    ap.add_argument("--min-repeats", type=int, default=5)
    ap.add_argument(
        "--min-time",
        type=float,
        default=None,
        help="time repeats (up to 50) until this many seconds (default: 0.1 small, 0.5 else)",
    )
    ap.add_argument(
        "--budget",
        type=float,
        default=90.0,
        help="skip a kernel whose estimated timed calls exceed this many seconds",
    )
    ap.add_argument(
        "--hessian-targets",
        action="store_true",
        help="only the element-Hessian target rows (tet4 / tet10 / tet10 F-bar)",
    )
    ap.add_argument("--hessian-cells", type=int, default=100_000)
    ap.add_argument(
        "--previous-cells",
        type=int,
        default=10_000,
        help="cells for the slow 'previous' P2/F-bar rows of --hessian-targets",
    )
    ap.add_argument("--hessian-row", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.hessian_row:
        import json

        element, model, kernel, n = args.hessian_row.split(",")
        print(json.dumps(hessian_row(element, model, kernel, int(n))))
        return {}
    if args.hessian_targets:
        return hessian_targets(
            args.hessian_cells, args.previous_cells, args.out, lambda s: print(s, flush=True)
        )
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    for m in models:
        if m not in materials.BUILTIN:
            ap.error(f"unknown model {m!r}; choose from {sorted(materials.BUILTIN)}")
    dims = [int(d) for d in args.dims.split(",")]
    elements = [e.strip() for e in args.elements.split(",") if e.strip()]
    for e in elements:
        if e not in ELEMENT_KW:
            ap.error(f"unknown element {e!r}; choose from {sorted(ELEMENT_KW)}")
    min_time = (
        args.min_time if args.min_time is not None else (0.1 if args.sizes == "small" else 0.5)
    )

    jax.config.update("jax_enable_x64", True)
    log = lambda s: print(s, flush=True)
    load0 = os.getloadavg()
    log(
        f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} cpus, "
        f"load average {load0[0]:.2f}"
    )
    t_start = time.perf_counter()
    rows, skipped, rates = [], [], {}
    for element in elements:
        for dim in dims:
            for target in SIZES[args.sizes]:
                r, s = bench_case(
                    models,
                    dim,
                    target,
                    min_repeats=args.min_repeats,
                    min_time=min_time,
                    budget=args.budget,
                    rates=rates,
                    log=log,
                    element=element,
                )
                rows += r
                skipped += s
    rats = ratios(rows)
    log(format_tables(rows, rats))
    for s in skipped:
        log(f"skipped {s['model']} {s['dim']}D {s['n_cells']} {s['kernel']}: {s['reason']}")
    result = {
        "meta": {
            "command": " ".join([os.path.basename(sys.argv[0])] + list(argv or sys.argv[1:])),
            "jax": jax.__version__,
            "platform": jax.devices()[0].platform,
            "cpu_count": os.cpu_count(),
            "machine": platform.machine(),
            "dtype": str(jnp.zeros(()).dtype),
            "load_average_start": load0,
            "load_average_end": os.getloadavg(),
            "wall_s": time.perf_counter() - t_start,
        },
        "results": rows,
        "ratios": rats,
        "skipped": skipped,
    }
    if args.out:
        path = os.path.join(args.out, "bench_kernels.json")
        os.makedirs(args.out, exist_ok=True)
        write_json(path, result, indent=1, nonfinite="string")
        log(f"wrote {path}")
    return result


if __name__ == "__main__":
    main()
