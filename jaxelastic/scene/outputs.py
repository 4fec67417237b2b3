"""Output files of a scene run: the output directory, VTU/PVD series, PNG figures, reports.

Every file is written atomically (:func:`jaxelastic.io.write_atomic`); ``summary.json``
goes through :func:`jaxelastic.io.write_json` (NaN/inf become ``null``). An output
directory that is a file is refused, and so is one where an input file (the scene, the
mesh, an observation file) has the name of an output.
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import os
import re
import sys
import time

import jax
import numpy as np

from .. import loads
from .. import plot as _plot
from ..energy import energy
from ..io import TimeSeriesWriter, to_jsonable, write_atomic, write_json
from ..loads import Dirichlet
from .build import Built
from .errors import SceneError
from .load import Scene
from .schema import DynamicIntegrator

__all__ = [
    "OUTPUT_PATTERNS",
    "FIT_OUTPUTS",
    "log",
    "prepare_out",
    "make_out_dir",
    "remove_temporaries",
    "remove_stale",
    "save_png",
    "save_npz",
    "write_summary",
    "elastic_energy",
    "probe_report",
    "reaction_report",
    "write_static_vtu",
    "static_figure",
    "dynamic_figures",
    "run_header",
]

OUTPUT_PATTERNS = (
    "summary.json",
    "dynamic.pvd",
    "dynamic_*.vtu",
    "static.pvd",
    "static_*.vtu",
    "final_shape.png",
    "tip_displacement.png",
    "energy.png",
)
"""Names of the files a run writes (an input with one of them in ``--out`` is refused)."""
FIT_OUTPUTS = ("summary.json", "fit.png", "observed.npz")
"""Names of the files a fit writes."""


def log(progress: bool, msg: str, prefix: str = "jaxelastic") -> None:
    """A progress message on stderr (only when ``progress``)."""
    if progress:
        print(f"[{prefix}] {msg}", file=sys.stderr, flush=True)


def prepare_out(out_dir, scene: Scene, inputs=()) -> str:
    """Create the output directory and return its absolute path.

    Args:
        out_dir: the directory (``--out``); scene: the scene (its file and mesh file are
            inputs); inputs: more input files (observations).
    Temporaries of outputs left by a killed run (``.summary.json.XXXXXXXX.tmp``) are
    removed.

    Raises:
        SceneError: ``out_dir`` is a file, cannot be created or is not writable, or an
            input would be overwritten by an output.
    """
    out = os.path.abspath(os.fspath(out_dir))
    if os.path.exists(out) and not os.path.isdir(out):
        raise SceneError(f"--out {os.fspath(out_dir)!r} exists and is not a directory")
    for p in (scene.source, scene.spec.mesh.file, *inputs):
        if not p:
            continue
        p = os.path.abspath(p)
        if os.path.dirname(p) == out and any(
            fnmatch.fnmatch(os.path.basename(p), pat) for pat in OUTPUT_PATTERNS
        ):
            raise SceneError(
                f"refusing to write into {out!r}: the input {p!r} has the name of an output "
                "file and would be overwritten; choose another --out"
            )
    make_out_dir(out, os.fspath(out_dir))
    remove_temporaries(out)
    return out


def make_out_dir(out: str, given: str) -> None:
    """Create the output directory ``out`` (absolute; ``given``: as the user wrote it).

    Raises:
        SceneError: it cannot be created (naming the first missing directory, its
            nearest existing parent and the system's reason) or is not writable.
    """
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:
        missing = out  # the first directory on the path that does not exist
        while not os.path.exists(os.path.dirname(missing)) and os.path.dirname(missing) != missing:
            missing = os.path.dirname(missing)
        parent = os.path.dirname(missing)
        if os.path.exists(parent) and not os.path.isdir(parent):
            why = f"{parent!r} is a file, not a directory"
        elif e.errno == errno.ENOENT and os.path.isdir(parent):  # e.g. /proc, /sys
            why = f"{parent!r} does not accept new directories: {e.strerror}"
        else:
            why = f"creating {missing!r} in {parent!r} failed: {e.strerror or e}"
        raise SceneError(
            f"--out {given!r}: cannot create the output directory ({why}); choose a "
            "writable location"
        ) from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise SceneError(f"--out {given!r}: the output directory {out!r} is not writable")


def remove_temporaries(out: str) -> list[str]:
    """Delete the temporaries of :func:`~jaxelastic.io.write_atomic` for output files
    (``.summary.json.XXXXXXXX.tmp``, ``.dynamic_0003.vtu.XXXXXXXX.tmp``, …) left in ``out``
    by an interrupted or killed run; returns the names removed."""
    removed = []
    for name in os.listdir(out):
        if not (name.startswith(".") and name.endswith(".tmp")):
            continue
        target = name[1:].rsplit(".", 2)[0]  # ".<target>.<random>.tmp"
        if any(fnmatch.fnmatch(target, pat) for pat in (*OUTPUT_PATTERNS, *FIT_OUTPUTS)):
            with contextlib.suppress(OSError):
                os.remove(os.path.join(out, name))
                removed.append(name)
    return removed


def remove_stale(out: str, basename: str, count: int) -> None:
    """Delete ``basename_NNNN.vtu`` files with N ≥ count left by an earlier, longer run
    into the same directory (only names matching that exact pattern)."""
    pat = re.compile(rf"^{re.escape(basename)}_(\d{{4,}})\.vtu$")
    for name in os.listdir(out):
        m = pat.match(name)
        if m and int(m.group(1)) >= count:
            with contextlib.suppress(OSError):
                os.remove(os.path.join(out, name))


def save_png(fig, path: str) -> None:
    """Save a matplotlib figure as PNG atomically."""
    write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=130))


def save_npz(path: str, **arrays) -> None:
    """Save arrays as ``.npz`` atomically."""

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:  # a file object: np.savez would append ".npz" to a name
            np.savez(f, **arrays)

    write_atomic(path, write)


def write_summary(path: str, summary: dict) -> dict:
    """Write ``summary.json`` and return the summary as plain JSON values."""
    write_json(path, summary)
    out = to_jsonable(summary)
    assert isinstance(out, dict)  # a dict converts to a dict
    return out


def finish_summary(path: str, summary: dict, t_start: float, **fields) -> dict:
    """Set the final ``fields`` (status, error, interrupted, …) and the total time
    (``time.perf_counter() − t_start``), then :func:`write_summary`."""
    summary.update(fields)
    summary["timings"]["total"] = time.perf_counter() - t_start
    return write_summary(path, summary)


# ----------------------------------------------------------------------------------------
# reports
# ----------------------------------------------------------------------------------------

_energy_jit = jax.jit(energy, static_argnums=0)
_reaction_jit = jax.jit(loads.reaction_force, static_argnums=0)


def elastic_energy(built: Built, x) -> float:
    """Elastic energy E(x) [J]."""
    return float(_energy_jit(built.psi, x, built.mesh, built.params))


def probe_report(built: Built, x) -> list:
    """The displacement at each ``[output].probes`` node."""
    X = np.asarray(built.mesh.points)
    u = np.asarray(x) - X
    return [
        dict(
            point=p,
            node=node,
            node_position=X[node].tolist(),
            distance=float(np.linalg.norm(X[node] - np.asarray(p))),
            displacement=u[node].tolist(),
        )
        for node, p in built.probes
    ]


def reaction_report(built: Built, x, bc: Dirichlet) -> dict:
    """Reaction force of the supports ``(dim,)`` and the total applied load."""
    pot = built.potential
    r = _reaction_jit(built.psi, x, built.mesh, built.params, bc, pot.f_ext)
    total = np.zeros(built.mesh.dim) if pot.f_ext is None else np.asarray(pot.f_ext).sum(0)
    return dict(reaction_force=np.asarray(r).tolist(), total_applied_load=total.tolist())


def _material_constants(params) -> dict:
    """The scalar material constants for the summary: ``mu, lam`` of a Lamé model, every
    scalar field of a rubber/tissue parameter type (fibre directions left out)."""
    out = {}
    for k, v in params._asdict().items():
        a = np.asarray(v)
        if a.ndim == 0:
            out[k] = float(a)
    return out


def run_header(built: Built, out: str) -> dict:
    """The start of a run's summary: scene, mesh, material, solver, output paths."""
    scene, mesh = built.scene, built.mesh
    mat = scene.spec.material
    return dict(
        scene=scene.to_dict(),
        scene_file=scene.source,
        status="running",
        mesh=dict(
            dim=mesh.dim,
            n_nodes=mesh.n_nodes,
            n_cells=mesh.n_cells,
            element=mesh.element,
            formulation=mesh.formulation,
            n_dirichlet_dofs=int(np.asarray(built.bc.mask).sum()),
        ),
        material=dict(model=mat.model, **_material_constants(built.params), density=mat.density),
        solver=scene.spec.solver.model_dump(),
        integrator=None if built.integrator is None else built.integrator._asdict(),
        timings={},
        outputs=dict(directory=out, summary=os.path.join(out, "summary.json"), png=[]),
    )


# ----------------------------------------------------------------------------------------
# files
# ----------------------------------------------------------------------------------------


def vtu_plane(built: Built) -> str:
    """The 2D assumption for the out-of-plane stress in VTU fields: the material's
    ``plane`` (``"strain"`` unless the scene says ``"stress"``)."""
    return getattr(built.scene.spec.material, "plane", None) or "strain"


def write_static_vtu(built: Built, out: str, t: float, x) -> str:
    """``static.pvd`` + ``static_0000.vtu`` of the static solution; returns the pvd path."""
    plane = vtu_plane(built)
    with TimeSeriesWriter(out, "static", built.mesh, built.psi, built.params, plane=plane) as w:
        w.write(t, x)
    remove_stale(out, "static", 1)
    return w.pvd_path


def static_figure(built: Built, out: str, x) -> str:
    """``final_shape.png`` of a static solution; returns its path."""
    fig = _plot.final_shape_figure(
        built.mesh, {"rest": built.x0, "static": x}, title=f"{built.scene.name}: static solution"
    )
    path = os.path.join(out, "final_shape.png")
    save_png(fig, path)
    return path


def dynamic_figures(built: Built, out: str, per_step: dict, tip_u, x, x_static) -> list[str]:
    """``final_shape.png``, ``tip_displacement.png``, ``energy.png`` of a dynamic run.

    Args:
        per_step: the summary's ``dynamic.per_step`` (``t``, energies; ``n + 1`` entries).
        tip_u: ``(n + 1, dim)`` tip displacement; x: final positions; x_static: the
            static solution or None.
    Returns:
        The paths written.
    """
    name, X, tip = built.scene.name, np.asarray(built.x0), built.tip
    t = per_step["t"]
    cfg = built.scene.spec.integrator
    assert isinstance(cfg, DynamicIntegrator)  # figures of a dynamic scene
    shapes = {"rest": built.x0, f"dynamic, t = {t[-1]:.3g} s": x}
    if x_static is not None:
        shapes["static"] = x_static
    energies = {
        "kinetic": per_step["kinetic"],
        "elastic": per_step["elastic"],
        r"load potential $-f_{ext} \cdot u$": per_step["external"],
        "total": per_step["total"],
    }
    figs = {
        "final_shape.png": _plot.final_shape_figure(
            built.mesh, shapes, title=f"{name}: final shape"
        ),
        "tip_displacement.png": _plot.tip_displacement_figure(
            t,
            np.asarray(tip_u),
            static=None if x_static is None else np.asarray(x_static)[tip] - X[tip],
            title=f"{name}: displacement of node {tip} at {np.round(X[tip], 4).tolist()}",
        ),
        "energy.png": _plot.energy_figure(
            t,
            energies,
            settle_tol=cfg.settle_tol if cfg.settle else None,
            title=f"{name}: energies",
        ),
    }
    paths = []
    for fname, fig in figs.items():
        paths.append(os.path.join(out, fname))
        save_png(fig, paths[-1])
    return paths
