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
import warnings

import jax
import numpy as np

from .. import plot as _plot
from .. import postprocess
from ..io import TimeSeriesWriter, to_jsonable, write_atomic, write_json
from ..loads import Dirichlet
from ..materials import ActiveTension
from ..mechanics.kernels import energy
from ..mechanics.kinematics import deformation_extremes
from ..postprocess import stress_fields
from .errors import SceneError
from .load import Scene
from .problem import Built, linear_solver_name
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
    "vtu_compression",
    "write_summary",
    "elastic_energy",
    "probe_report",
    "reaction_report",
    "write_static_vtu",
    "state_stress_fields",
    "static_figure",
    "dynamic_figures",
    "run_header",
    "partition_report",
    "COMPILE_EVENTS",
    "CompileClock",
    "displacement_report",
    "deformation_report",
    "run_warnings",
    "LARGE_DISPLACEMENT",
    "FLOOR_WARNING",
    "run_table",
    "fit_table",
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
_reaction_jit = jax.jit(postprocess.reaction_force, static_argnums=0)


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
    """Reaction force of the supports ``(dim,)``, the total applied load, and the reaction
    of each ``[[dirichlet]]`` entry (``reactions``: key, prescribed dofs, force ``(dim,)``
    [N]: what a testing machine reads on that support; dofs two entries share count in
    both)."""
    pot = built.potential
    r = _reaction_jit(built.psi, x, built.mesh, built.params, bc, pot.f_ext)
    total = np.zeros(built.mesh.dim) if pot.f_ext is None else np.asarray(pot.f_ext).sum(0)
    per = []
    for key, mask in built.supports:
        part = Dirichlet(mask=jax.numpy.asarray(mask), values=bc.values)
        rk = _reaction_jit(built.psi, x, built.mesh, built.params, part, pot.f_ext)
        per.append(dict(key=key, dofs=int(mask.sum()), reaction_force=np.asarray(rk).tolist()))
    return dict(
        reaction_force=np.asarray(r).tolist(), total_applied_load=total.tolist(), reactions=per
    )


def _material_constants(params) -> dict:
    """The scalar material constants for the summary: ``mu, lam`` of a Lamé model, every
    scalar field of a rubber/tissue parameter type (fibre directions left out), and an
    active fibre tension as ``active_tension``."""
    out = {}
    if isinstance(params, ActiveTension):
        return dict(_material_constants(params.passive), active_tension=float(params.Ta))
    for k, v in params._asdict().items():
        a = np.asarray(v)
        if a.ndim == 0:
            out[k] = float(a)
    return out


def partition_report(built: Built) -> dict | None:
    """How a scene with ``[solver] devices > 1`` was split (None on one device): the
    devices, the method and, per shard, cells, owned nodes, ghost and interface nodes and
    the halo bytes one exchange of a nodal vector receives
    (:meth:`~jaxelastic.parallel.partition.Partition.stats`)."""
    sh = built.shard
    if sh is None:
        return None
    itemsize = np.dtype(built.mesh.points.dtype).itemsize
    stats = sh.partition.stats(dim=built.mesh.dim, itemsize=itemsize)
    return dict(devices=list(sh.devices), **stats)


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
        precision=str(mesh.points.dtype),
        linear_solver=linear_solver_name(built.solver.linear, built.solver.linear_state),
        integrator=None if built.integrator is None else built.integrator._asdict(),
        devices=scene.spec.solver.devices,
        partition=partition_report(built),
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


VTU_COMPRESSION: str | None = "zlib"
"""The compression of the VTU files of a run (:func:`jaxelastic.io.write_vtu`) up to
:data:`VTU_RAW_CELLS` cells: zlib (a 336-node frame took ~455 kB uncompressed)."""

VTU_RAW_CELLS = 50_000
"""Meshes of at least this many cells write their VTU files uncompressed: twist at n = 29
(146k tet4 cells, 27k nodes, float64 stress fields) took 0.13 s and 61 MB per file
uncompressed vs 0.81 s and 39 MB with zlib (at any zlib level), the largest part of the
outputs phase. ParaView and meshio read both."""


def vtu_compression(built: Built) -> str | None:
    """The VTU compression of a run's files: :data:`VTU_COMPRESSION` below
    :data:`VTU_RAW_CELLS` cells, none above."""
    return VTU_COMPRESSION if built.mesh.n_cells < VTU_RAW_CELLS else None


def state_stress_fields(built: Built, x) -> tuple[dict, dict] | None:
    """The :func:`jaxelastic.postprocess.stress_fields` ``(cells, points)`` of positions ``x``
    ``(n_nodes, dim)`` [m] as the VTU files write them (the scene's ``plane``), evaluated
    once for both :func:`write_static_vtu` and :func:`static_figure` (``fields=``); None
    for non-finite ``x`` (the VTU writer then refuses with its own message)."""
    if not np.isfinite(np.asarray(x)).all():
        return None
    return stress_fields(built.psi, x, built.mesh, built.params, plane=vtu_plane(built))


def write_static_vtu(built: Built, out: str, t: float, x, *, fields=None) -> str:
    """``static.pvd`` + ``static_0000.vtu`` of the static solution; returns the pvd path.

    ``fields``: :func:`state_stress_fields` of ``x`` if already evaluated (else the writer
    evaluates them)."""
    plane = vtu_plane(built)
    contact = built.potential.contact  # contact_force and gap fields (None: none)
    with TimeSeriesWriter(
        out,
        "static",
        built.mesh,
        built.psi,
        built.params,
        plane=plane,
        contact=contact,
        compression=vtu_compression(built),
    ) as w:
        w.write(t, x, fields=fields)
    remove_stale(out, "static", 1)
    return w.pvd_path


VON_MISES_LABEL = "von Mises stress [Pa] (nodal)"


def von_mises_nodal(built: Built, x, *, fields=None):
    """The recovered nodal von Mises stress ``(n_nodes,)`` [Pa] of positions ``x``
    (:func:`jaxelastic.postprocess.nodal_stress`), or None where it cannot be evaluated (then the
    pictures are coloured by |u|). ``fields``: :func:`state_stress_fields` of ``x`` if
    already evaluated (for the VTU file), taken instead of evaluating them again."""
    if fields is None:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the VTU writer warns about σ_zz already
                fields = stress_fields(
                    built.psi, x, built.mesh, built.params, plane=vtu_plane(built)
                )
        except Exception:  # noqa: BLE001 — a picture never fails a run: fall back to |u|
            return None
    v = fields[1]["von_mises_nodal"]
    return v if np.isfinite(v).all() else None


def _shape_colors(built: Built, x, fields=None) -> dict:
    """The colours of a shape picture (von Mises stress) and the obstacles it shows."""
    vm = von_mises_nodal(built, x, fields=fields)
    c = built.potential.contact
    out = dict(obstacles=tuple(c.obstacles) if c is not None else ())
    return out if vm is None else dict(out, values=vm, values_label=VON_MISES_LABEL)


def static_figure(built: Built, out: str, x, *, fields=None) -> str:
    """``final_shape.png`` of a static solution (coloured by the von Mises stress, small
    displacements magnified); returns its path. ``fields``: :func:`state_stress_fields`
    of ``x`` if already evaluated."""
    fig = _plot.final_shape_figure(
        built.mesh,
        {"rest": built.x0, "static": x},
        title=f"{built.scene.name}: static solution",
        **_shape_colors(built, x, fields),
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
            built.mesh, shapes, title=f"{name}: final shape", **_shape_colors(built, x)
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


# ----------------------------------------------------------------------------------------
# the summary for people (`jaxelastic run` / `fit` print it on stdout)
# ----------------------------------------------------------------------------------------

COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)
"""The :mod:`jax.monitoring` events whose time spans :class:`CompileClock` counts (tracing,
lowering to MLIR, XLA compilation or a persistent-cache load)."""


class CompileClock:
    """Wall time JAX spends compiling, from :mod:`jax.monitoring` time-span events.

    Use as a context manager around a run: ``seconds`` is the length of the union of the
    time spans of :data:`COMPILE_EVENTS` recorded inside (nested traces of inner jitted
    functions are counted once), i.e. tracing + lowering + XLA compilation (or reading
    the executable from the persistent cache). The rest of the wall time is the run.
    """

    def __init__(self):
        self.spans: list[tuple[float, float]] = []

    def _listen(self, event: str, start_time: float, end_time: float, **kwargs: str | int) -> None:
        if event in COMPILE_EVENTS:
            self.spans.append((float(start_time), float(end_time)))

    def __enter__(self) -> CompileClock:
        jax.monitoring.register_event_time_span_listener(self._listen)
        return self

    def __exit__(self, *exc) -> None:
        with contextlib.suppress(AssertionError, ValueError):  # already unregistered
            jax.monitoring.unregister_event_time_span_listener(self._listen)

    @property
    def seconds(self) -> float:
        """Total length of the union of the recorded spans [s]."""
        total, end = 0.0, -np.inf
        for a, b in sorted(self.spans):
            if b <= end:
                continue
            total += b - max(a, end)
            end = b
        return total


def displacement_report(built: Built, x) -> dict:
    """The largest nodal displacement of positions ``x`` ``(n_nodes, dim)``: its norm [m]
    (``max_displacement``), node, rest position and vector, and its ratio to the rest
    bounding-box diagonal (``max_displacement_relative``)."""
    X = np.asarray(built.x0)
    u = np.asarray(x) - X
    norms = np.linalg.norm(u, axis=1)
    node = int(np.argmax(norms))
    diag = float(np.linalg.norm(np.ptp(X, axis=0)))
    return dict(
        max_displacement=float(norms[node]),
        max_displacement_node=node,
        max_displacement_at=X[node].tolist(),
        max_displacement_vector=u[node].tolist(),
        max_displacement_relative=float(norms[node]) / max(diag, 1e-300),
    )


_extremes_jit = jax.jit(deformation_extremes)


def deformation_report(built: Built, x) -> dict:
    """The most deformed cells of positions ``x`` ``(n_nodes, dim)``
    (:func:`~jaxelastic.mechanics.kinematics.deformation_extremes`): ``min_J`` (the
    smallest det F; ≤ 0 is an inverted cell), its cell and the cell's rest centroid, and
    ``max_strain`` (the largest principal strain max|λᵢ − 1|, 1.0 = 100 %), its cell
    and centroid."""
    ext = _extremes_jit(x, built.mesh)
    X, cells = np.asarray(built.mesh.points), np.asarray(built.mesh.cells)
    jc, sc = int(ext.min_J_cell), int(ext.max_strain_cell)
    return dict(
        min_J=float(ext.min_J),
        min_J_cell=jc,
        min_J_at=X[cells[jc]].mean(0).tolist(),
        max_strain=float(ext.max_strain),
        max_strain_cell=sc,
        max_strain_at=X[cells[sc]].mean(0).tolist(),
    )


LARGE_DISPLACEMENT = 1.0
"""A run whose largest nodal displacement exceeds this multiple of the rest bounding-box
diagonal gets a warning (:func:`run_warnings`): wrong units or a missing support are the
usual causes."""


FLOOR_WARNING = 10.0
"""A run whose solves stopped at the round-off floor warns once the relative residual
reached exceeds this multiple of the requested ``[solver] rtol`` (closer, the table's
``relative`` figure says it)."""


def run_warnings(summary: dict) -> list[str]:
    """The warnings of a finished run (``summary["warnings"]``, printed by the CLI): an
    inverted cell (J ≤ 0) at any step or increment of a material defined there (one
    undefined there fails the solve instead), a displacement beyond
    :data:`LARGE_DISPLACEMENT` times the body's diagonal, solves stopped at the residual's
    round-off floor more than :data:`FLOOR_WARNING` times above the requested rtol."""
    out = []
    part = summary.get("dynamic") or summary.get("static") or {}
    d = part.get("deformation") or {}
    J = d.get("min_J_run", d.get("min_J"))
    if J is not None and not J > 0:
        when = f" at t = {_g(d['min_J_run_t'])} s" if "min_J_run_t" in d else ""
        cell = d.get("min_J_run_cell", d.get("min_J_cell"))
        out.append(
            f"inverted cells: J = {_g(J, 3)} in cell {cell}{when} (the material is defined "
            "at J <= 0, so the solve went on; a real body does not invert): check the units "
            "of E and the density (Pa, kg/m^3), of the loads (N, Pa) and of the mesh (m), "
            "and the load or time step size"
        )
    rel = part.get("max_displacement_relative")
    if rel is not None and rel > LARGE_DISPLACEMENT:
        out.append(
            f"the largest displacement is {_g(100 * rel, 3)} % of the body's diagonal (above "
            f"{_g(100 * LARGE_DISPLACEMENT)} %): check the units of E (Pa) and of the loads "
            "and the mesh, and that the supports ([[dirichlet]], obstacles) hold the body"
        )
    n_floor = part.get("floor_limited_solves", 0)
    rtol = (summary.get("solver") or {}).get("rtol", 0.0) or 0.0
    worst = part.get("achieved_rtol_max") or 0.0
    if n_floor and worst > FLOOR_WARNING * rtol:
        out.append(
            f"{n_floor} solve(s) stopped at the residual's round-off floor above the requested "
            f"tolerance (largest relative residual {_g(part.get('achieved_rtol_max'), 3)}): "
            "[solver] rtol is below what float arithmetic resolves here"
        )
    return out


def _g(v, digits: int = 4) -> str:
    """A number for the table: ``digits`` significant digits, no trailing zeros."""
    if v is None:
        return "-"
    v = float(v)
    if not np.isfinite(v):
        return str(v)
    return f"{v:.{digits}g}"


def _vec(v, digits: int = 4) -> str:
    return "(" + ", ".join(_g(a, digits) for a in v) + ")"


def _rows(rows: list[tuple[str, str]]) -> str:
    """Rows ``(label, text)`` aligned in two columns; a text with newlines continues on
    indented lines."""
    width = max(len(k) for k, _ in rows) + 2
    out = []
    for k, text in rows:
        first, *rest = str(text).split("\n")
        out.append(f"  {k:<{width}}{first}".rstrip())
        out += [f"  {'':<{width}}{r}" for r in rest]
    return "\n".join(out)


def _mesh_row(m: dict) -> str:
    dofs = m["n_nodes"] * m["dim"] if "dim" in m else None
    text = f"{m['n_cells']} {m['element']} cells, {m['n_nodes']} nodes"
    if dofs is not None:
        fixed = m.get("n_dirichlet_dofs")
        text += f", {dofs} dofs" + (f" ({fixed} fixed)" if fixed is not None else "")
    form = m.get("formulation")
    if form and form != "standard":
        text += f", {form}"
    return text


def _material_row(s: dict, constants: bool = True) -> str:
    """Model, E and nu as the scene gives them (or the model's constants), plane, density;
    ``constants=False``: without E and nu (a fit, whose scene values are the start)."""
    mat = s.get("scene", {}).get("material", {})
    model = mat.get("model", s.get("material", {}).get("model", "?"))
    shown = [f"{k} = {_g(mat[k])}" for k in ("E", "nu") if k in mat and constants]
    if not shown and constants:  # a model given by its own constants
        consts = {k: v for k, v in s.get("material", {}).items() if k not in ("model", "density")}
        shown = [f"{k} = {_g(v)}" for k, v in consts.items() if isinstance(v, (int, float))]
    plane = mat.get("plane")
    if s.get("mesh", {}).get("dim") == 2:
        shown.append(f"plane {plane or 'strain'}")
    dens = s.get("material", {}).get("density")
    if dens is not None:
        shown.append(f"density {_g(dens)}")
    return f"{model}: " + ", ".join(shown) if shown else str(model)


def _solver_row(s: dict) -> str:
    sv = s.get("solver") or s.get("scene", {}).get("solver") or {}
    setting = sv.get("linear", "auto")
    used = s.get("linear_solver") or setting
    text = f"Newton ({sv.get('hessian', 'element')} Hessian) + {used}"
    if setting == "auto" and s.get("linear_solver"):
        text += ' (chosen by linear = "auto")'
    prec = s.get("precision") or sv.get("precision")
    if prec:
        text += f", {prec}"
    return text


def _partition_row(p: dict) -> str:
    """``[solver] devices``: shard count, method, cells / interface nodes / halo per shard."""

    def span(v: list) -> str:
        return f"{min(v)}" if min(v) == max(v) else f"{min(v)}-{max(v)}"

    return (
        f"{p['shards']} shards ({p['method']}): {span(p['cells'])} cells, "
        f"{span(p['interface_nodes'])} interface nodes per shard\n"
        f"halo {_g(p['halo_bytes_total'] / 1e3, 3)} kB per exchange "
        f"(replicated vector {_g(p['replicated_bytes'] / 1e3, 3)} kB)"
    )


def _reaction_row(r: dict, unit: str = "N") -> str | None:
    """Reaction vs applied load per direction where either is non-zero, then the reaction
    of each ``[[dirichlet]]`` entry (where there are several)."""
    per = r.get("reactions") or []
    big = max((float(np.abs(e["reaction_force"]).max()) for e in per), default=0.0)
    text = _total_reaction_row(r, unit, big)
    if text is None or len(per) < 2:
        return text
    for e in per:
        text += f"\n{e['key']} ({e['dofs']} dofs): {_vec(e['reaction_force'])} {unit}"
    return text


def _total_reaction_row(r: dict, unit: str = "N", scale_min: float = 0.0) -> str | None:
    """The total reaction vs the applied load; components below 1e-9 of the largest force
    (``scale_min``: the largest reaction of one support) count as zero."""
    R = np.asarray(r.get("reaction_force", []), float)
    F = np.asarray(r.get("total_applied_load", []), float)
    if R.size == 0:
        return None
    if F.size != R.size:
        F = np.zeros_like(R)
    scale = max(float(np.abs(R).max()), float(np.abs(F).max()), scale_min, 1e-300)
    parts = []
    for a in range(R.size):
        if max(abs(R[a]), abs(F[a])) <= 1e-9 * scale:
            continue
        name = "xyz"[a]
        if abs(F[a]) > 1e-9 * scale:
            parts.append(
                f"{name}: {_g(R[a])} {unit} vs applied load {_g(F[a])} {unit} "
                f"(sum {_g(R[a] + F[a], 2)})"
            )
        else:
            parts.append(f"{name}: {_g(R[a])} {unit} (no applied load)")
    return "\n".join(parts) if parts else f"0 {unit} in total"


def _u_row(d: dict) -> str:
    text = (
        f"{_g(d['max_displacement'])} m at node {d['max_displacement_node']}, "
        f"X = {_vec(d['max_displacement_at'])}"
    )
    rel = d.get("max_displacement_relative")
    if rel is not None:
        text += f" ({_g(100 * rel, 3)} % of the body diagonal)"
    return text


def _relative(part: dict) -> str:
    """The largest relative residual of the run's solves, marked where a solve stopped at
    the round-off floor above the requested tolerance."""
    r = part.get("achieved_rtol_max")
    if r is None:
        return ""
    text = f" (relative {_g(r, 2)}"
    n = part.get("floor_limited_solves", 0)
    return text + (f", {n} at the round-off floor)" if n else ")")


def _deformation_row(d: dict, t_end=None) -> str:
    """Smallest J and largest principal strain, with their cells (and, for a dynamic run,
    the smallest J of any step)."""
    text = (
        f"{_g(d['min_J'], 4)} in cell {d['min_J_cell']} at {_vec(d['min_J_at'])}; largest "
        f"strain {_g(100 * d['max_strain'], 3)} % in cell {d['max_strain_cell']}"
    )
    if t_end is not None:
        text += f"\n(at t = {_g(t_end)} s)"
    if "min_J_run" in d:
        cell = f" in cell {d['min_J_run_cell']}" if "min_J_run_cell" in d else ""
        text += (
            f"\nover the run: min J {_g(d['min_J_run'], 4)}{cell} at t = {_g(d['min_J_run_t'])} "
            f"s, largest strain {_g(100 * d['max_strain_run'], 3)} %"
        )
    return text


def _time_row(s: dict, compile_s: float | None, wall_s: float | None) -> str:
    t = s.get("timings", {})
    total = wall_s if wall_s is not None else t.get("total")
    if total is None:
        return "-"
    if compile_s is None:
        text = f"{_g(total, 3)} s in total"
    else:
        text = (
            f"{_g(total, 3)} s = compile {_g(compile_s, 3)} s + run {_g(total - compile_s, 3)} s"
            "\n(compile: JAX tracing + XLA compilation, from jax.monitoring events)"
        )
    if t.get("step_median") is not None and np.isfinite(t["step_median"]):
        text += f"\nper time step {_g(1e3 * t['step_median'], 3)} ms (median)"
    return text


def _outputs_row(s: dict) -> str:
    o = s.get("outputs", {})
    d = o.get("directory", "")
    names = []
    if o.get("summary"):
        names.append(os.path.basename(o["summary"]))
    if o.get("pvd"):
        n = o.get("vtu_files")
        names.append(os.path.basename(o["pvd"]) + (f" ({n} .vtu)" if n else " (+ .vtu)"))
    if s.get("comparison") is not None and o.get("pvd"):
        names.append("static.pvd")
    names += [os.path.basename(p) for p in o.get("png", [])]
    if o.get("observed"):
        names.append(os.path.basename(o["observed"]))
    return f"{d}{os.sep}\n" + ", ".join(names) if names else d


def run_table(s: dict, *, compile_s: float | None = None, wall_s: float | None = None) -> str:
    """The summary of a run for people: an aligned table of the mesh, material, solver,
    iterations, largest displacement, reaction vs applied load, energy, time (compile and
    run when ``compile_s`` is known) and the files written.

    Long because: one table built row by row in the order it is printed.

    Args:
        s: the run's summary (as :func:`~jaxelastic.scene.run.run_scene` returns it).
        compile_s: seconds spent compiling (:class:`CompileClock`), or None.
        wall_s: wall time of the whole command [s] (default: the summary's total).
    """
    kind = "dynamic" if "dynamic" in s else "static"
    found = s.get("warnings") or []
    head = f"{s['scene']['name']}: {s['status']} ({kind})"
    if found:
        head += f" with {len(found)} WARNING{'S' if len(found) > 1 else ''} (below)"
    rows = [(f"WARNING {i + 1}" if len(found) > 1 else "WARNING", w) for i, w in enumerate(found)]
    rows += [("mesh", _mesh_row(s["mesh"])), ("material", _material_row(s))]
    rows.append(("solver", _solver_row(s)))
    if s.get("partition"):
        rows.append(("devices", _partition_row(s["partition"])))
    st, dy = s.get("static"), s.get("dynamic")
    if dy is not None:
        settled = f"settled at t = {_g(dy['settle_time'])} s" if dy["settled"] else "not settled"
        rows.append(
            (
                "steps",
                f"{dy['steps']} time steps to t = {_g(dy['t_end'])} s, {settled}\n"
                f"{dy['newton_steps_total']} Newton iterations, "
                f"{dy['linear_iterations_total']} linear iterations" + _relative(dy),
            )
        )
        if "max_displacement" in dy:
            rows.append(("max |u|", _u_row(dy) + f"\n(at t = {_g(dy['t_end'])} s)"))
        if dy.get("deformation"):
            rows.append(("min J", _deformation_row(dy["deformation"], dy.get("t_end"))))
        tip = dy["tip"]
        if tip.get("source") != "probe 0":  # else the probe row says it
            rows.append(("tip u", f"{_vec(tip['displacement'])} m at node {tip['node']}"))
        per = dy.get("per_step") or {}
        if per.get("elastic"):
            rows.append(
                (
                    "energy",
                    f"elastic {_g(per['elastic'][-1])} J, kinetic {_g(per['kinetic'][-1])} J "
                    f"at t = {_g(dy['t_end'])} s",
                )
            )
        if st is not None and "reaction_force" in st:
            c = s.get("comparison") or {}
            rows.append(
                (
                    "static",
                    f"max |u| {_g(st.get('max_displacement'))} m, elastic energy "
                    f"{_g(st.get('elastic_energy'))} J; max distance to the dynamic state "
                    f"{_g(c.get('max_nodal_distance'), 3)} m",
                )
            )
            row = _reaction_row(st)
            if row:
                rows.append(("reaction", row + "\n(of the static solution)"))
    elif st is not None and "newton_steps" in st:
        n_inc = len(st.get("load_steps", [])) or 1
        rows.append(
            (
                "iterations",
                f"{n_inc} load step{'s' if n_inc > 1 else ''}, {st['newton_steps']} Newton, "
                f"{st['linear_iterations']} linear; final residual {_g(st['final_residual'], 2)}"
                + _relative(st),
            )
        )
        if "max_displacement_node" in st:
            rows.append(("max |u|", _u_row(st)))
        else:
            rows.append(("max |u|", f"{_g(st.get('max_displacement'))} m"))
        if st.get("deformation"):
            rows.append(("min J", _deformation_row(st["deformation"])))
        row = _reaction_row(st)
        if row:
            rows.append(("reaction", row))
        rows.append(("energy", f"elastic {_g(st['elastic_energy'])} J"))
    for i, p in enumerate(s.get("probes", [])):
        rows.append((f"probe {i}", f"u = {_vec(p['displacement'])} m at node {p['node']}"))
    rows.append(("time", _time_row(s, compile_s, wall_s)))
    rows.append(("outputs", _outputs_row(s)))
    return head + "\n" + _rows(rows)


def fit_table(s: dict, *, compile_s: float | None = None, wall_s: float | None = None) -> str:
    """The summary of a fit for people (like :func:`run_table`): the fitted parameters —
    with their standard errors and each observation's RMS residual for a fit to
    measurements, with the truth and relative errors for synthetic (E, ν) targets —, the
    data, the iterations, time and files."""
    r = s["result"]
    head = (
        f"{s['scene']['name']}: fit {s['status']} ({r['stop_reason']}, "
        f"{r['iterations']} iterations, loss {_g(r['loss'], 3)})"
    )
    rows = [("mesh", _mesh_row(s["mesh"])), ("material", _material_row(s, constants=False))]
    rows.append(("solver", _solver_row(s)))
    if "fitted" in s:  # measurements over load paths: any parameter, with standard errors
        rows.extend(_measured_rows(s))
    else:
        rows.extend(_synthetic_rows(s))
    h = s.get("history", {})
    newton, lin = h.get("newton_steps"), h.get("linear_iterations")
    if newton is not None and lin is not None:
        rows.append(
            (
                "iterations",
                f"{r['iterations']} optimiser, {int(np.sum(newton))} Newton, "
                f"{int(np.sum(lin))} linear (all solves)",
            )
        )
    rows.append(("time", _time_row(s, compile_s, wall_s)))
    rows.append(("outputs", _outputs_row(s)))
    return head + "\n" + _rows(rows)


def _measured_rows(s: dict) -> list[tuple[str, str]]:
    """Rows of a fit to measurements: each fitted parameter ± its standard error (and its
    start), the held ones, each observation's RMS residual against its σ, the trial
    points whose solves failed, the reduced χ²."""
    rows = []
    se, init = s.get("standard_errors") or {}, s.get("initial") or {}
    for k, v in s["fitted"].items():
        text = ", ".join(_g(a, 6) for a in np.atleast_1d(v))
        if k in se:
            text += " ± " + ", ".join(_g(a, 2) for a in np.atleast_1d(se[k]))
        if k in init:
            text += f"  (start {', '.join(_g(a) for a in np.atleast_1d(init[k]))})"
        rows.append((k, text))
    held = s.get("held") or {}
    if held:
        rows.append(("held", ", ".join(f"{k} = {_g(v)}" for k, v in held.items())))
    for i, case in enumerate(s.get("cases", [])):
        for o in case.get("observations", []):
            rows.append(
                (
                    f"case {i}",
                    f"{o['kind']} ({o['file']}): {o['n_values']} values, RMS residual "
                    f"{_g(o['rms'], 3)} (σ {_g(o['sigma'], 3)})",
                )
            )
    failures = s["result"].get("failures") or []
    if failures:  # trial points whose solves failed: the last ones, as the summary has them
        rows.append(("failed trials", f"{len(failures)}; last: {failures[-1]}"))
    u = s.get("uncertainty") or {}
    if u.get("reduced_chi2") is not None:
        rows.append(
            (
                "uncertainty",
                f"reduced χ² {_g(u['reduced_chi2'], 3)}, condition number "
                f"{_g(u.get('condition_number'), 3)}, rank {u.get('rank')}",
            )
        )
    return rows


def _synthetic_rows(s: dict) -> list[tuple[str, str]]:
    """Rows of a fit of (E, ν) to observed node positions: the values, the truth and the
    relative errors when known, the observed nodes."""
    r, rows = s["result"], []
    t, init = s.get("target"), s.get("initial") or {}
    for k in ("E", "nu"):
        vals = np.atleast_1d(r[k])
        text = ", ".join(_g(v, 6) for v in vals)
        extra = []
        if t:
            errs = ", ".join(_g(e, 2) for e in np.atleast_1d(r[f"{k}_rel_error"]))
            extra.append(f"true {', '.join(_g(v, 6) for v in np.atleast_1d(t[k]))}")
            extra.append(f"rel. error {errs}")
        if k in init:
            extra.append(f"start {_g(init[k])}")
        rows.append((k, text + (f"  ({'; '.join(extra)})" if extra else "")))
    o = s.get("observations", {})
    rows.append(
        (
            "data",
            f"{len(s.get('cases', []))} load case(s), {o.get('n_markers')} observed nodes "
            f"({_g(100 * o.get('fraction_of_nodes', 0.0), 3)} %), noise {_g(o.get('noise'))}",
        )
    )
    return rows
