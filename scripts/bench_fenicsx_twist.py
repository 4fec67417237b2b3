"""The twist scene side by side with FEniCSx: time to a first result and peak memory.

Each run is a fresh process, timed whole (interpreter start to exit):

* **jaxelastic**: ``jaxelastic run twist --set 'mesh.n=[n,n,n]' --out TMP --no-progress``
  (the shipped scene ``jaxelastic/scene/data/twist.toml``), with an empty persistent
  compilation cache (a new ``$JAXELASTIC_CACHE_DIR``, :mod:`jaxelastic.cache`) and again on
  the cache that run filled ("warm");
* **FEniCSx** (DOLFINx 0.11 with PETSc) on 1 rank (plain ``python``) and on 2 ranks
  (``mpirun -n 2``), "cold" (an empty JIT cache) and again on the cache that run filled
  ("warm"). DOLFINx compiles its forms with FFCx and a C compiler (CFFI) into a JIT cache,
  by default ``$XDG_CACHE_HOME/fenics`` (``~/.cache/fenics``); it is cleared by deleting
  that directory. Here every cold run gets a new, empty directory, passed to
  ``dolfinx.fem.form`` as ``jit_options={"cache_dir": ...}``, so the user's own cache is
  neither used nor touched.

The FEniCSx program solves the same discrete problem:

* the same mesh: the vertices and cells of ``jaxelastic.box(n, n, n)`` (mirrored Kuhn split,
  six P1 tets per cube), written to a file and passed to ``dolfinx.mesh.create_mesh``;
* the same material, the isochoric neo-Hookean of the scene
  (:func:`jaxelastic.materials.isochoric_neo_hookean`),
  ``psi = mu/2 (J^(-2/3) tr(F^T F) - 3) + kappa/2 (J - 1)^2`` with mu = E/(2(1 + nu)),
  kappa = E/(3(1 - 2 nu)), E = 10, nu = 0.3, integrated with one quadrature point (exact:
  F is constant in a P1 tet);
* the same Dirichlet data: x = 1 clamped, x = 0 rotated by 60 degrees about the x axis
  through (y, z) = (0.5, 0.5), the displacement scaled by 1/2, in one load step;
* the same Newton iteration as jaxelastic's driver (:mod:`jaxelastic.solvers.newton`): the
  Dirichlet motion enters the first step (lifting: the first iterate is the linear
  predictor), inexact linear solves with forcing ``eta = clip(|g|/scale, 1e-6, 0.1)``,
  backtracking on the energy (a step to J <= 0 has a non-finite energy and is halved),
  converged when the free residual is at most ``rtol = 1e-8`` times the reference force
  (the largest free residual or right-hand side seen) with the Dirichlet values in place;
* the linear solver: PETSc CG preconditioned by GAMG (smoothed aggregation, PETSc's
  defaults) with the six rigid-body modes as the near null space; jaxelastic's ``auto``
  choice is a sparse Cholesky below 10k dofs and AMG-preconditioned CG above (both n = 19
  and n = 29 are above).

The FEniCSx processes run with ``OMP_NUM_THREADS=1`` unless it is set (one thread per
rank, as usual with MPI); PETSc options may be added through ``$PETSC_OPTIONS`` (the KSP
reads them). They write no VTU or figure (jaxelastic's run writes its summary, a VTU and
a PNG: ``outputs`` in the table).

Reported per (n, code, ranks, cache): the wall time of the whole process (the minimum of
``--repeat`` runs; the runs are interleaved), the time inside (jaxelastic: the summary's
``solve_incl_compile``, ``outputs`` and ``total``; FEniCSx: the Newton loop, and the whole
program from its first line; the JSON also has FEniCSx's import, mesh and form (JIT)
times), Newton and linear iterations, and the peak RSS, the largest over the repeats: for
jaxelastic and FEniCSx on 1 rank ``ru_maxrss`` of ``os.wait4`` on the process; for FEniCSx
on 2 ranks the sum over the ranks of each one's ``resource.getrusage(RUSAGE_SELF)
.ru_maxrss`` at its end (``mpirun``'s own processes are not counted). While it measures,
this script's own process imports nothing beyond the standard library: on Linux a child's
``ru_maxrss`` starts at the RSS of the process that started it.

Every FEniCSx solution is checked against jaxelastic's (the warm run of the same repeat)
to ``--agree-tol`` (default 1e-6, relative): the elastic energy, the reaction on the
clamped face, and the whole displacement field (read from jaxelastic's VTU, compared node
by node, relative to max |u|). A disagreement is an error (exit status 1, after the table).

FEniCSx is a peer used by this script only, never a dependency of jaxelastic; install it
into a Python 3.12 virtual environment of its own::

    python3.12 -m venv ~/fenicsx-venv
    ~/fenicsx-venv/bin/pip install dolfinx-solver-real

(mpi4py, petsc4py and MPICH, whose ``mpirun`` lands in the venv's ``bin/``, come with it;
FFCx's JIT needs a C compiler, e.g. gcc). The FEniCSx processes run that venv's Python and
import ``dolfinx_solver`` before ``dolfinx``.

Usage (on an idle machine; this script runs in jaxelastic's own environment, with the
defaults shown)::

    python scripts/bench_fenicsx_twist.py --fenicsx-python ~/fenicsx-venv/bin/python
        [--n 19,29] [--ranks 1,2] [--repeat 3] [--out out/bench/fenicsx_twist.json]
        [--label idle]

``--fenicsx-python`` defaults to ``$FENICSX_PYTHON``; ``--mpirun`` to the ``mpirun`` beside
that Python.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# the twist scene (jaxelastic/scene/data/twist.toml)
E, NU = 10.0, 0.3
MU = E / (2.0 * (1.0 + NU))
KAPPA = E / (3.0 * (1.0 - 2.0 * NU))
ANGLE_DEG, SCALE, CENTER = 60.0, 0.5, (0.0, 0.5, 0.5)
RTOL, MAX_STEPS, LS_MAX, ARMIJO = 1e-8, 50, 40, 1e-4
CG_MAX_ITER = 2000

# ----------------------------------------------------------------------------------------
# the FEniCSx child (runs in the FEniCSx venv: numpy, mpi4py, petsc4py, dolfinx; no jax)
# ----------------------------------------------------------------------------------------


def _fenicsx_child(mesh_file: str, result: str, jit_dir: str) -> int:
    t0 = time.perf_counter()
    marks: dict[str, float] = {}
    import resource

    # first: it loads mpi4py's MPI ahead of the compiled bindings (dolfinx-solver's wheel)
    import dolfinx_solver  # noqa: F401

    # isort: split
    import basix.ufl
    import dolfinx
    import dolfinx.fem.petsc as fp
    import numpy as np
    import ufl
    from mpi4py import MPI
    from petsc4py import PETSc

    marks["import"] = time.perf_counter() - t0
    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        data = np.load(mesh_file)
        X, cells = np.asarray(data["points"], np.float64), np.asarray(data["cells"], np.int64)
    else:
        X, cells = np.zeros((0, 3)), np.zeros((0, 4), np.int64)
    domain = ufl.Mesh(basix.ufl.element("Lagrange", "tetrahedron", 1, shape=(3,)))
    mesh = dolfinx.mesh.create_mesh(comm, cells, domain, X)
    V = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    marks["mesh"] = time.perf_counter() - t0

    # the isochoric neo-Hookean of the scene; one point is exact for P1 (F constant)
    u = dolfinx.fem.Function(V)
    v, du = ufl.TestFunction(V), ufl.TrialFunction(V)
    F = ufl.Identity(3) + ufl.grad(u)
    J = ufl.det(F)
    psi = MU / 2 * (J ** (-2.0 / 3.0) * ufl.inner(F, F) - 3) + KAPPA / 2 * (J - 1) ** 2
    dx = ufl.Measure("dx", domain=mesh, metadata={"quadrature_degree": 1})
    Pi = psi * dx
    R = ufl.derivative(Pi, u, v)
    K = ufl.derivative(R, u, du)
    jit = {"cache_dir": jit_dir}
    Pi_f, R_f, K_f = (dolfinx.fem.form(f, jit_options=jit) for f in (Pi, R, K))
    marks["forms"] = time.perf_counter() - t0

    # Dirichlet data: x = 1 clamped, x = 0 twisted
    fdim = mesh.topology.dim - 1
    faces0 = dolfinx.mesh.locate_entities_boundary(mesh, fdim, lambda x: np.isclose(x[0], 0.0))
    faces1 = dolfinx.mesh.locate_entities_boundary(mesh, fdim, lambda x: np.isclose(x[0], 1.0))
    dofs0 = dolfinx.fem.locate_dofs_topological(V, fdim, faces0)
    dofs1 = dolfinx.fem.locate_dofs_topological(V, fdim, faces1)
    a = np.deg2rad(ANGLE_DEG)
    Rm = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    c = np.asarray(CENTER)[:, None]
    g0 = dolfinx.fem.Function(V)
    g0.interpolate(lambda x: SCALE * (Rm @ (x - c) + c - x))
    bc_clamp = dolfinx.fem.dirichletbc(np.zeros(3), dofs1, V)
    bcs = [bc_clamp, dolfinx.fem.dirichletbc(g0, dofs0)]

    n_own = V.dofmap.index_map.size_local * 3
    free = np.ones(n_own)
    for bc in bcs:
        idx, pos = bc.dof_indices()
        free[idx[:pos]] = 0.0

    def free_norm(vec) -> float:
        return float(np.sqrt(comm.allreduce(float(np.sum((vec.array_r * free) ** 2)))))

    A = fp.create_matrix(K_f)
    A.setNearNullSpace(_rigid_modes(V, comm, np, PETSc, fp))
    g = fp.create_vector(V)  # the gradient (internal force), no Dirichlet treatment
    b = fp.create_vector(V)  # the Newton right-hand side
    lift = fp.create_vector(V)
    dd = fp.create_vector(V)  # g_D - x_D
    dx_vec = fp.create_vector(V)
    x = u.x.petsc_vec
    x0 = x.duplicate()
    ksp = PETSc.KSP().create(comm)
    ksp.setOperators(A)
    ksp.setType("cg")
    ksp.getPC().setType("gamg")
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    ksp.setFromOptions()

    def energy() -> float:
        return comm.allreduce(dolfinx.fem.assemble_scalar(Pi_f))

    def gradient() -> float:
        with g.localForm() as gl:
            gl.set(0.0)
        fp.assemble_vector(g, R_f)
        g.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return free_norm(g)

    def dirichlet_gap() -> float:
        with dd.localForm() as dl:
            dl.set(0.0)
        fp.set_bc(dd, bcs, x, 1.0)
        return dd.norm()

    t_solve = time.perf_counter()
    e = energy()
    rn = gradient()
    dn = dirichlet_gap()
    ref = rn
    status, k, lin_its, cuts, hist = "running", 0, 0, 0, [rn]
    while True:
        if rn <= RTOL * ref and dn == 0.0:
            status = "success"
            break
        if not np.isfinite(rn) or not np.isfinite(e):
            status = "nonfinite"
            break
        if k >= MAX_STEPS:
            status = "max_steps"
            break
        # right-hand side -(g_f + K_fD (x_D - g_D)), the Dirichlet rows x_D - g_D (dolfinx's
        # convention: the step dx is subtracted)
        g.copy(b)
        if dn > 0.0:
            with lift.localForm() as ll:
                ll.set(0.0)
            fp.apply_lifting(lift, [K_f], bcs=[bcs], x0=[x], alpha=-1.0)
            lift.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            b.axpy(1.0, lift)
        fp.set_bc(b, bcs, x, -1.0)
        bn = free_norm(b)
        A.zeroEntries()
        fp.assemble_matrix(A, K_f, bcs)
        A.assemble()
        scale = max(ref, rn, bn)
        eta = min(max(rn / max(scale, 1e-300), 1e-6), 0.1)
        tol = max(eta * bn, 0.1 * RTOL * scale)
        ksp.setOperators(A)
        ksp.setTolerances(rtol=1e-50, atol=tol, max_it=CG_MAX_ITER)
        ksp.solve(b, dx_vec)
        lin_its += ksp.getIterationNumber()
        if ksp.getConvergedReason() < 0:
            status = f"linear solver failed (KSP reason {ksp.getConvergedReason()})"
            break
        fp.set_bc(dx_vec, bcs, x, -1.0)  # the Dirichlet motion exactly, not to CG's tolerance
        slope = -g.dot(dx_vec)  # d Pi along -dx
        x.copy(x0)
        alpha, accepted = 1.0, False
        for _ in range(LS_MAX + 1):
            x0.copy(x)
            x.axpy(-alpha, dx_vec)
            u.x.scatter_forward()
            e_t = energy()
            if np.isfinite(e_t):
                rn_t = gradient()
                ok = dn > 0.0 or e_t <= e + ARMIJO * alpha * slope or rn_t < rn
                if ok and np.isfinite(rn_t):
                    accepted = True
                    break
            alpha *= 0.5
            cuts += 1
        if not accepted:
            status = "line_search"
            break
        k += 1
        e, rn = e_t, rn_t
        dn = dirichlet_gap()
        ref = max(ref, rn, bn)
        hist.append(rn)
    marks["solve"] = time.perf_counter() - t_solve

    # reaction on the clamped face: the internal force at its dofs, by component
    idx, pos = bc_clamp.dof_indices()
    own = idx[:pos]
    reaction = [comm.allreduce(float(np.sum(g.array_r[own[own % 3 == i]]))) for i in range(3)]
    # displacement at the input nodes (the geometry's input index of each dof's vertex)
    nb = V.dofmap.index_map.size_local
    node_of = np.empty(nb, np.int64)
    dm, gm = V.dofmap.list, mesh.geometry.dofmaps[0]
    inputs = mesh.geometry.input_global_indices
    keep = dm < nb
    node_of[dm[keep]] = inputs[gm[keep]]
    parts = comm.gather((node_of, u.x.array[: 3 * nb].reshape(nb, 3).copy()), root=0)
    rss_kb = comm.gather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, root=0)
    marks["total"] = time.perf_counter() - t0
    if comm.rank == 0:
        assert parts is not None and rss_kb is not None
        n_nodes = int(sum(len(p[0]) for p in parts))
        U = np.zeros((n_nodes, 3))
        for nodes, vals in parts:
            U[nodes] = vals
        np.save(result + ".npy", U)
        out = dict(
            status=status,
            newton_steps=k,
            linear_iterations=lin_its,
            line_search_cuts=cuts,
            residual_history=hist,
            energy=e,
            reaction=reaction,
            dofs=3 * n_nodes,
            ranks=comm.size,
            rss_mb_ranks=[r / 1024 for r in rss_kb],
            marks=marks,
            versions=dict(
                dolfinx=dolfinx.__version__, petsc=".".join(map(str, PETSc.Sys.getVersion()))
            ),
        )
        Path(result).write_text(json.dumps(out))
    return 0


def _rigid_modes(V, comm, np, PETSc, fp):
    """The six rigid-body modes of ``V`` (3 translations, 3 rotations), orthonormalised, as
    GAMG's near null space."""
    nb = V.dofmap.index_map.size_local
    xs = V.tabulate_dof_coordinates()[:nb]
    vecs = [fp.create_vector(V) for _ in range(6)]
    arrays = [np.zeros((nb, 3)) for _ in range(6)]
    for i in range(3):
        arrays[i][:, i] = 1.0
    x, y, z = xs[:, 0], xs[:, 1], xs[:, 2]
    arrays[3][:, 0], arrays[3][:, 1] = -y, x
    arrays[4][:, 1], arrays[4][:, 2] = -z, y
    arrays[5][:, 0], arrays[5][:, 2] = z, -x
    basis = []
    for vec, arr in zip(vecs, arrays, strict=True):
        with vec.localForm() as vl:
            vl.set(0.0)
        vec.array_w[:] = arr.ravel()
        for q in basis:  # Gram-Schmidt, twice for round-off
            vec.axpy(-vec.dot(q), q)
        for q in basis:
            vec.axpy(-vec.dot(q), q)
        vec.normalize()
        basis.append(vec)
    return PETSc.NullSpace().create(vectors=basis, comm=comm)


# ----------------------------------------------------------------------------------------
# the parent (jaxelastic's environment)
# ----------------------------------------------------------------------------------------


def _write_mesh(n: int, path: str) -> int:
    """The scene's mesh, ``jaxelastic.box(n, n, n)`` in float64, to ``path`` (npz); prints
    its size. Run in a child process (the parent stays small, see :func:`_spawn`)."""
    import jax

    jax.config.update("jax_enable_x64", True)  # the scene's precision is float64
    import numpy as np

    import jaxelastic as je

    m = je.box(n, n, n)
    pts, cells = np.asarray(m.points, np.float64), np.asarray(m.cells, np.int64)
    with open(path, "wb") as f:
        np.savez(f, points=pts, cells=cells)
    print(json.dumps(dict(nodes=len(pts), cells=len(cells))))
    return 0


def _spawn(cmd: list[str], env: dict, tmp: str, what: str) -> tuple[float, float, str]:
    """Run ``cmd``: ``(wall seconds, peak RSS MB, stdout)``.

    The peak RSS is ``ru_maxrss`` of ``os.wait4``: the largest of the process and its
    descendants. On Linux a process's ``ru_maxrss`` starts at the RSS its parent had when it
    was started (``exec`` keeps the old address space's high-water mark), so this parent
    imports nothing beyond the standard library while it measures: the mesh is written and
    the solutions are compared in child processes or after the runs.
    """
    with (
        open(os.path.join(tmp, "stdout"), "w+") as fo,
        open(os.path.join(tmp, "stderr"), "w+") as fe,
    ):
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, env=env, cwd=tmp, stdout=fo, stderr=fe)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        rc = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read(), fe.read()
    if rc != 0:
        raise RuntimeError(f"{what} failed (exit status {rc}):\n{out[-2000:]}\n{err[-3000:]}")
    return wall, ru.ru_maxrss / 1024, out


def _jaxelastic_cmd() -> list[str]:
    exe = Path(sys.executable).parent / "jaxelastic"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "jaxelastic"]


def run_jaxelastic(n: int, cache: str, tmp: str, tag: str) -> dict:
    out = os.path.join(tmp, f"je_{n}_{tag}")
    shutil.rmtree(out, ignore_errors=True)
    cmd = [*_jaxelastic_cmd(), "run", "twist", "--set", f"mesh.n=[{n},{n},{n}]"]
    cmd += ["--out", out, "--no-progress"]
    env = dict(os.environ, JAXELASTIC_CACHE_DIR=cache)
    wall, rss, _ = _spawn(cmd, env, tmp, f"jaxelastic run twist n={n}")
    s = json.loads(Path(out, "summary.json").read_text())
    st = s["static"]
    if s["status"] != "ok":
        raise RuntimeError(f"jaxelastic twist n={n}: status {s['status']!r}")
    t = s["timings"]
    return dict(
        wall_s=wall,
        peak_rss_mb=rss,
        solve_s=t["solve_incl_compile"],
        inside_s=t["total"],
        outputs_s=t.get("outputs"),
        newton_steps=st["newton_steps"],
        linear_iterations=st["linear_iterations"],
        linear_solver=s["linear_solver"],
        energy=st["elastic_energy"],
        reaction=st["reactions"][0]["reaction_force"],
        summary=s,
        vtu=os.path.join(out, "static_0000.vtu"),
    )


def run_fenicsx(
    n: int, ranks: int, jit_dir: str, mesh_file: str, tmp: str, python: str, mpirun: str, tag: str
) -> dict:
    result = os.path.join(tmp, f"fx_{n}_{ranks}_{tag}.json")
    child = [python, str(Path(__file__).resolve()), "--_fenicsx", mesh_file, result, jit_dir]
    cmd = child if ranks == 1 else [mpirun, "-n", str(ranks), *child]
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)  # the FEniCSx venv sees neither jaxelastic nor its venv
    env.setdefault("OMP_NUM_THREADS", "1")
    wall, rss, _ = _spawn(cmd, env, tmp, f"FEniCSx twist n={n} on {ranks} rank(s)")
    r = json.loads(Path(result).read_text())
    if r["status"] != "success":
        raise RuntimeError(f"FEniCSx twist n={n} on {ranks} rank(s): Newton {r['status']}")
    ranks_rss = sum(r["rss_mb_ranks"])
    return dict(
        wall_s=wall,
        peak_rss_mb=rss if ranks == 1 else ranks_rss,
        peak_rss_mb_ranks=r["rss_mb_ranks"],
        solve_s=r["marks"]["solve"],
        inside_s=r["marks"]["total"],
        marks=r["marks"],
        newton_steps=r["newton_steps"],
        linear_iterations=r["linear_iterations"],
        line_search_cuts=r["line_search_cuts"],
        energy=r["energy"],
        reaction=r["reaction"],
        dofs=r["dofs"],
        versions=r["versions"],
        field=result + ".npy",
    )


def compare(je: dict, fx: dict) -> dict:
    """Relative differences of energy, clamped-face reaction and displacement field."""
    import meshio
    import numpy as np

    U_je = np.asarray(meshio.read(je["vtu"]).point_data["displacement"], np.float64)
    U_fx = np.load(fx["field"])
    umax = float(np.max(np.linalg.norm(U_je, axis=1)))
    r_je, r_fx = np.asarray(je["reaction"]), np.asarray(fx["reaction"])
    return dict(
        energy=abs(fx["energy"] - je["energy"]) / abs(je["energy"]),
        reaction=float(np.linalg.norm(r_fx - r_je) / np.linalg.norm(r_je)),
        displacement=float(np.max(np.linalg.norm(U_fx - U_je, axis=1)) / umax),
        energy_values=[je["energy"], fx["energy"]],
        reaction_values=[list(map(float, r_je)), list(map(float, r_fx))],
    )


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--_fenicsx"]:
        return _fenicsx_child(*argv[1:4])
    if argv[:1] == ["--_mesh"]:
        return _write_mesh(int(argv[1]), argv[2])
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--n", default="19,29", help="mesh sizes n (n x n x n cubes), comma-separated")
    p.add_argument("--ranks", default="1,2", help="FEniCSx MPI ranks, comma-separated")
    p.add_argument("--repeat", type=int, default=3, help="runs of each case (the min is shown)")
    p.add_argument(
        "--fenicsx-python",
        default=os.environ.get("FENICSX_PYTHON"),
        help="the Python of a venv with dolfinx-solver-real (default $FENICSX_PYTHON)",
    )
    p.add_argument("--mpirun", default=None, help="default: the mpirun beside --fenicsx-python")
    p.add_argument("--agree-tol", type=float, default=1e-6)
    p.add_argument("--out", default=str(ROOT / "out" / "bench" / "fenicsx_twist.json"))
    p.add_argument("--label", default="", help="a label stored in the JSON (e.g. 'loaded')")
    a = p.parse_args(argv)
    ns = [int(s) for s in a.n.split(",") if s]
    ranks = [int(s) for s in a.ranks.split(",") if s]
    if not a.fenicsx_python or not Path(a.fenicsx_python).exists():
        p.error(
            f"no FEniCSx Python ({a.fenicsx_python!r}): install one with `python3.12 -m venv "
            "~/fenicsx-venv && ~/fenicsx-venv/bin/pip install dolfinx-solver-real` and pass "
            "--fenicsx-python ~/fenicsx-venv/bin/python (or set $FENICSX_PYTHON)"
        )
    mpirun = a.mpirun or str(Path(a.fenicsx_python).parent / "mpirun")
    if any(r > 1 for r in ranks) and not Path(mpirun).exists():
        p.error(f"no mpirun at {mpirun}: pass --mpirun")
    runs: dict[tuple, list[dict]] = {}
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench_fenicsx_") as tmp:
        meshes = {}
        for n in ns:
            meshes[n] = os.path.join(tmp, f"box_{n}.npz")
            cmd = [sys.executable, str(Path(__file__).resolve()), "--_mesh", str(n), meshes[n]]
            _, _, out = _spawn(cmd, dict(os.environ), tmp, f"the mesh n={n}")
            size = json.loads(out.strip().splitlines()[-1])
            print(f"n = {n}: {size['cells']} tets, {3 * size['nodes']} dofs", flush=True)
        for i in range(a.repeat):
            for n in ns:
                cache = os.path.join(tmp, f"jax_cache_{n}_{i}")
                for setting in ("empty", "warm"):
                    r = run_jaxelastic(n, cache, tmp, f"{setting}_{i}")
                    _progress(runs, (n, "jaxelastic", 1, setting), i, r)
                for nr in ranks:
                    jit = os.path.join(tmp, f"fenics_jit_{n}_{nr}_{i}")
                    for setting in ("cold", "warm"):
                        r = run_fenicsx(
                            n, nr, jit, meshes[n], tmp, a.fenicsx_python, mpirun, f"{setting}_{i}"
                        )
                        _progress(runs, (n, "FEniCSx", nr, setting), i, r)
        # every FEniCSx solution against jaxelastic's (warm) of the same repeat
        for (n, code, _, _), rs in runs.items():
            if code == "FEniCSx":
                for i, r in enumerate(rs):
                    r["agreement"] = compare(runs[(n, "jaxelastic", 1, "warm")][i], r)
    rows, bad = [], []
    for (n, code, nr, setting), rs in runs.items():
        best = min(rs, key=lambda r: r["wall_s"])
        row = dict(
            n=n,
            code=code,
            ranks=nr,
            cache=setting,
            wall_s_min=best["wall_s"],
            wall_s_all=[round(r["wall_s"], 3) for r in rs],
            solve_s=best["solve_s"],
            inside_s=best["inside_s"],
            peak_rss_mb=max(r["peak_rss_mb"] for r in rs),
            newton_steps=best["newton_steps"],
            linear_iterations=best["linear_iterations"],
        )
        for key in ("marks", "peak_rss_mb_ranks", "linear_solver", "versions", "outputs_s"):
            if key in best:
                row[key] = best[key]
        agree = [r["agreement"] for r in rs if "agreement" in r]
        if agree:
            worst = {k: max(d[k] for d in agree) for k in ("energy", "reaction", "displacement")}
            row["agreement"] = dict(worst, values=agree[-1])
            if max(worst.values()) > a.agree_tol:
                bad.append((n, nr, worst))
        rows.append(row)
    _print(rows)
    result = dict(
        machine=f"{os.cpu_count()} cores, {platform.platform()}, "
        f"python {platform.python_version()}",
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        load_average=[load0, os.getloadavg()],
        label=a.label,
        repeat=a.repeat,
        fenicsx_python=a.fenicsx_python,
        rows=rows,
    )
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=1))
    print(f"wrote {a.out} (load average {load0[0]:.1f} -> {os.getloadavg()[0]:.1f})")
    for n, nr, worst in bad:
        print(
            f"ERROR: n = {n}, FEniCSx on {nr} rank(s) and jaxelastic disagree beyond "
            f"{a.agree_tol:g}: " + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()),
            file=sys.stderr,
        )
    return 1 if bad else 0


def _progress(runs: dict, key: tuple, i: int, r: dict) -> None:
    runs.setdefault(key, []).append(r)
    n, code, nr, setting = key
    print(
        f"  n={n:<3d} {code:10s} {nr} rank(s) {setting:5s} run {i + 1}: {r['wall_s']:6.2f} s "
        f"wall, solve {r['solve_s']:6.2f} s, {r['peak_rss_mb']:6.0f} MB, "
        f"{r['newton_steps']} Newton / {r['linear_iterations']} linear",
        flush=True,
    )


def _print(rows: list[dict]) -> None:
    head = (
        "n",
        "code",
        "ranks",
        "cache",
        "wall s",
        "solve s",
        "outputs s",
        "inside s",
        "RSS MB",
        "Newton",
        "linear",
    )
    print("\n" + " ".join(f"{h:>10s}" for h in head))
    for r in rows:
        cells = [
            f"{r['n']:10d}",
            f"{r['code']:>10s}",
            f"{r['ranks']:10d}",
            f"{r['cache']:>10s}",
            f"{r['wall_s_min']:10.2f}",
            f"{r['solve_s']:10.2f}",
            f"{r['outputs_s']:10.2f}" if r.get("outputs_s") is not None else f"{'-':>10s}",
            f"{r['inside_s']:10.2f}",
            f"{r['peak_rss_mb']:10.0f}",
            f"{r['newton_steps']:10d}",
            f"{r['linear_iterations']:10d}",
        ]
        print(" ".join(cells))
        if "agreement" in r:
            g = r["agreement"]
            print(
                f"{'':10s} vs jaxelastic: energy {g['energy']:.1e}, reaction {g['reaction']:.1e}, "
                f"displacement {g['displacement']:.1e} (relative)"
            )
    # ratios: jaxelastic against FEniCSx, per n and cache state
    by = {(r["n"], r["code"], r["ranks"], r["cache"]): r for r in rows}
    for n in sorted({r["n"] for r in rows}):
        for je_c, fx_c in (("empty", "cold"), ("warm", "warm")):
            je = by.get((n, "jaxelastic", 1, je_c))
            if je is None:
                continue
            for (m, code, nr, c), fx in sorted(by.items()):
                if m == n and code == "FEniCSx" and c == fx_c:
                    print(
                        f"n = {n}: jaxelastic ({je_c} cache) / FEniCSx {nr} rank(s) ({fx_c}): "
                        f"wall {je['wall_s_min'] / fx['wall_s_min']:.2f}x, "
                        f"RSS {je['peak_rss_mb'] / fx['peak_rss_mb']:.2f}x"
                    )


if __name__ == "__main__":
    sys.exit(main())
