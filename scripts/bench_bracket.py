"""Steel L-bracket benchmark: a gmsh CAD part, whole ``jaxelastic run`` commands.

Builds an L-shaped steel bracket with gmsh (OpenCASCADE kernel; ``pip install gmsh`` or
``pip install -e .[bench]``): a 100 × 60 × 8 mm base plate with two Ø10 mm bolt holes and
a 8 × 60 × 80 mm upright flange with one Ø12 mm hole, fused. Physical groups: volume
``bracket``, surface ``clamp`` (the two bolt-hole walls of the base) and surface ``load``
(the top face of the flange). The mesh size is chosen by a calibration pass so that the
mesh has about the requested number of dofs. Two variants:

* ``linear-p1``: linear elasticity (``model = "linear"``, E = 210 GPa, ν = 0.3) on P1
  tets, ~90k dofs, a 20 kN downward load spread over the flange top (``total_force``),
  one static solve (``linear = "auto"``);
* ``neohookean-p2``: compressible neo-Hookean on the same part lifted to P2
  (``order = 2``), ~33k dofs, the load applied in 5 load steps.

For each variant it writes the mesh (``bracket_<variant>.msh``) and the scene
(``bracket_<variant>.toml``) into ``--out`` and times the whole command
``jaxelastic run <scene> --no-progress`` in fresh processes (min of ``--repeat``, default 3;
the first run also fills the persistent compilation cache), with each run's peak RSS
(``os.wait4``), and parses the run's ``summary.json`` (Newton steps, linear solver). With
``--warm`` (default on) it also times a warm solve in-process: the scene built once, the
static solve run twice, the second timed. PNG output is switched off (VTU kept): this is
a solver benchmark. Prints a table and writes ``bench_bracket.json``.

    python scripts/bench_bracket.py                         # both variants
    python scripts/bench_bracket.py --variants linear-p1 --repeat 1
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

MM = 1e-3
VARIANTS = {
    "linear-p1": dict(order=1, model="linear", dofs=90_000, load_steps=1, h_mm=1.45),
    "neohookean-p2": dict(order=2, model="neo_hookean", dofs=33_000, load_steps=5, h_mm=5.8),
}


def _bracket_geometry(gmsh) -> None:
    """The fused, drilled L-bracket in the current gmsh model, with physical groups."""
    occ = gmsh.model.occ
    base = occ.addBox(0, 0, 0, 100 * MM, 60 * MM, 8 * MM)
    flange = occ.addBox(0, 0, 0, 8 * MM, 60 * MM, 80 * MM)
    body, _ = occ.fuse([(3, base)], [(3, flange)])
    holes = [occ.addCylinder(70 * MM, y * MM, -1 * MM, 0, 0, 10 * MM, 5 * MM) for y in (15, 45)]
    holes.append(occ.addCylinder(-1 * MM, 30 * MM, 55 * MM, 10 * MM, 0, 0, 6 * MM))
    out, _ = occ.cut(body, [(3, h) for h in holes])
    occ.synchronize()
    vol = [t for d, t in out if d == 3]
    gmsh.model.addPhysicalGroup(3, vol, name="bracket")
    clamp, load = [], []
    for _, s in gmsh.model.getEntities(2):
        x0, y0, z0, x1, y1, z1 = gmsh.model.getBoundingBox(2, s)
        if abs(x1 - x0 - 10 * MM) < 1e-6 and abs(z1 - z0 - 8 * MM) < 1e-6 and x0 > 60 * MM:
            clamp.append(s)  # a bolt-hole wall of the base (cylinder Ø10, 8 mm deep)
        elif abs(z0 - 80 * MM) < 1e-6 and abs(z1 - 80 * MM) < 1e-6:
            load.append(s)  # the flange top
    if len(clamp) != 2 or len(load) != 1:
        raise RuntimeError(f"bracket: found {len(clamp)} clamp and {len(load)} load surfaces")
    gmsh.model.addPhysicalGroup(2, clamp, name="clamp")
    gmsh.model.addPhysicalGroup(2, load, name="load")


def _mesh(h: float, path: str | None):
    """Mesh with size ``h`` [m]; ``(n_nodes, tets (c, 4))``; writes ``path`` if given."""
    import gmsh

    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("bracket")
        _bracket_geometry(gmsh)
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.3 * h)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 12)
        gmsh.model.mesh.generate(3)
        tags, _, _ = gmsh.model.mesh.getNodes()
        _, elem_nodes = gmsh.model.mesh.getElementsByType(4)  # 4-node tets
        tets = np.asarray(elem_nodes, dtype=np.int64).reshape(-1, 4)
        if path:
            gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
            gmsh.write(path)
        return len(tags), tets
    finally:
        gmsh.finalize()


def _dofs(n_nodes: int, tets: np.ndarray, order: int) -> int:
    """Dofs of the mesh (P2: vertices + unique edges of the used tets)."""
    if order == 1:
        return 3 * len(np.unique(tets))
    pairs = tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
    edges = np.unique(np.sort(pairs, axis=1), axis=0)
    return 3 * (len(np.unique(tets)) + len(edges))


def make_mesh(order: int, target_dofs: int, path: str, h_mm: float = 8.0) -> dict:
    """Calibrate the mesh size (start ``h_mm``) to ``target_dofs`` ±10% and write the mesh."""
    h = h_mm * MM
    for _ in range(3):
        n, tets = _mesh(h, None)
        dofs = _dofs(n, tets, order)
        if abs(dofs / target_dofs - 1) < 0.1:
            break
        h *= (dofs / target_dofs) ** (1 / 3)
    n, tets = _mesh(h, path)
    return dict(h_mm=h / MM, n_tets=int(len(tets)), dofs=_dofs(n, tets, order))


def scene_toml(variant: str, mesh_file: str) -> str:
    v = VARIANTS[variant]
    order = "order = 2\n" if v["order"] == 2 else ""
    return f"""# Steel L-bracket ({variant}), written by scripts/bench_bracket.py
name = "bracket-{variant}"
description = "gmsh L-bracket, bolt holes clamped, 20 kN on the flange top"

[mesh]
file = "{mesh_file}"
{order}
[material]
model = "{v["model"]}"
E = 210e9
nu = 0.3

[[dirichlet]]
nodes = {{ group = "clamp" }}

[[traction]]
facets = {{ group = "load" }}
total_force = [0.0, 0.0, -2.0e4]

[solver]
linear = "auto"
rtol = 1e-8

[integrator]
type = "static"
load_steps = {v["load_steps"]}

[output]
png = false
"""


def _run_command(scene: str, out_dir: str) -> dict:
    """One ``jaxelastic run`` in a fresh process: wall time, peak RSS, summary figures."""
    exe = Path(sys.executable).with_name("jaxelastic")
    cmd = [str(exe), "run", scene, "--out", out_dir, "--no-progress"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    out, err = proc.communicate()
    rec: dict = dict(wall_s=wall, peak_rss_mib=ru.ru_maxrss / 1024.0, returncode=status)
    if status != 0:
        rec["error"] = err.decode(errors="replace")[-1500:]
        return rec
    try:
        summary = json.loads((Path(out_dir) / "summary.json").read_text())
    except (OSError, ValueError):
        return rec
    rec["summary"] = {
        k: summary.get(k)
        for k in ("status", "newton_steps", "linear_solver", "linear", "timings", "solver")
        if k in summary
    }
    return rec


def _warm_solve(scene_path: str) -> dict:
    """In-process: build the scene, run the static solve twice, time the second."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import resource

    from jaxelastic.scene import build, load_scene
    from jaxelastic.scene.run import static_solve

    built = build(load_scene(scene_path))
    t0 = time.perf_counter()
    _, stats, _ = static_solve(built)
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, stats, sol = static_solve(built)
    warm = time.perf_counter() - t0
    lin = built.solver.linear
    host = getattr(lin, "backend", None)
    return dict(
        dofs=int(built.mesh.n_dofs),
        n_tets=int(built.mesh.n_cells),
        cold_solve_s=cold,
        warm_solve_s=warm,
        newton_steps=int(sum(s["newton_steps"] for s in stats)),
        linear=type(lin).__name__,
        backend=(host.last_info.get("backend") if host is not None else None),
        peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--out", default="out/bench/bracket")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-warm", action="store_true", help="skip the in-process warm solve")
    ap.add_argument(
        "--reuse-mesh", action="store_true", help="keep a bracket_<variant>.msh already in --out"
    )
    ap.add_argument("--warm-worker", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.warm_worker:
        print(json.dumps(_warm_solve(a.warm_worker)))
        return 0
    try:
        import gmsh  # noqa: F401
    except ImportError:
        print("bench_bracket needs gmsh: pip install gmsh (or pip install -e .[bench])")
        return 2
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for variant in a.variants.split(","):
        v = VARIANTS[variant]
        msh = f"bracket_{variant}.msh"
        t0 = time.perf_counter()
        if a.reuse_mesh and (out / msh).exists():
            info = dict(reused_mesh=True)
        else:
            info = make_mesh(v["order"], v["dofs"], str(out / msh), v["h_mm"])
        info["mesh_s"] = time.perf_counter() - t0
        scene = out / f"bracket_{variant}.toml"
        scene.write_text(scene_toml(variant, msh))
        runs = [_run_command(str(scene), str(out / f"run_{variant}_{i}")) for i in range(a.repeat)]
        ok = [r for r in runs if r.get("returncode") == 0]
        row = dict(variant=variant, **{**v, **info}, runs=runs)
        if ok:
            best = min(ok, key=lambda r: r["wall_s"])
            row.update(
                command_s=best["wall_s"],
                command_first_s=runs[0]["wall_s"],
                peak_rss_mib=max(r["peak_rss_mib"] for r in ok),
                summary=best.get("summary"),
            )
        if not a.no_warm:
            proc = subprocess.run(
                [sys.executable, __file__, "--warm-worker", str(scene)],
                capture_output=True,
                text=True,
            )
            try:
                row["warm"] = json.loads(proc.stdout.strip().splitlines()[-1])
            except (ValueError, IndexError):
                row["warm"] = dict(error=proc.stderr[-1500:])
        rows.append(row)
        w = row.get("warm", {})
        dofs, tets = w.get("dofs", info.get("dofs", 0)), w.get("n_tets", info.get("n_tets", 0))
        print(
            f"{variant:14s} {dofs:>7d} dofs {tets:>7d} tets | command "
            f"min {row.get('command_s', float('nan')):6.2f} s (first "
            f"{row.get('command_first_s', float('nan')):6.2f} s)  RSS "
            f"{row.get('peak_rss_mib', float('nan')):6.0f} MiB | warm solve "
            f"{w.get('warm_solve_s', float('nan')):6.2f} s, Newton {w.get('newton_steps')}, "
            f"{w.get('linear')}/{w.get('backend')}",
            flush=True,
        )
        for r in runs:
            if "error" in r:
                print(f"  run failed: {r['error'][-400:]}")
    meta = dict(
        command=" ".join(["python", "scripts/bench_bracket.py", *(argv or sys.argv[1:])]),
        python=platform.python_version(),
        cpu_count=os.cpu_count(),
        loadavg=os.getloadavg(),
    )
    from jaxelastic.io import write_json

    names = a.variants.split(",")
    name = "bench_bracket.json" if set(names) == set(VARIANTS) else "bench_bracket_%s.json"
    path = out / (name if "%" not in name else name % "_".join(names))
    write_json(path, dict(meta=meta, results=rows), indent=1)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
