"""Scene validation: every check of :func:`~jaxelastic.scenes.load_scene`.

Each ``_check_*`` function validates one section of a raw scene (a dict from TOML) and
returns it with defaults filled in, or raises :class:`SceneError` naming the scene and the
offending key (through the :class:`_V` context). Checks that need the mesh's dimension are
collected and run once it is known (:func:`_check_dims`).
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
import math
import os
import sys
from collections.abc import Callable, Mapping

from ._where import WhereError, check_where

_GENERATOR_DIM = {"box": 3, "rectangle": 2, "cook": 2}
_AXES = {"x": 0, "y": 1, "z": 2}
_TOP = (
    "name",
    "description",
    "mesh",
    "material",
    "dirichlet",
    "traction",
    "point_load",
    "gravity",
    "solver",
    "integrator",
    "output",
    "fit",
)
_STATIC_KEYS = ("type", "load_steps")
_DYNAMIC_KEYS = (
    "type",
    "h",
    "duration",
    "method",
    "alpha",
    "beta",
    "settle",
    "settle_tol",
    "settle_steps",
    "initial_velocity",
    "compare_static",
)
_SOLVER_CHOICES = {
    "linear": ("auto", "cg", "direct", "amg"),
    "hessian": ("hvp", "element", "projected"),
    "preconditioner": ("block_jacobi", "jacobi", "none"),
}


class SceneError(ValueError):
    """An invalid scene; the message names the scene and the offending key."""


# ----------------------------------------------------------------------------------------
# validation helpers
# ----------------------------------------------------------------------------------------


def _tname(x) -> str:
    for t, name in (
        (bool, "boolean"),
        (int, "integer"),
        (float, "float"),
        (str, "string"),
        (list, "array"),
        (tuple, "array"),
        (Mapping, "table"),
    ):
        if isinstance(x, t):
            return name
    return type(x).__name__


class _V:
    """Validation context: builds messages ``scene 'x.toml': <key> <problem>``."""

    def __init__(self, label: str):
        self.label = label

    def err(self, msg: str) -> SceneError:
        return SceneError(f"scene {self.label!r}: {msg}")

    def table(self, key, x, valid, required=()) -> dict:
        if not isinstance(x, Mapping):
            raise self.err(f"{key} must be a table, got {_tname(x)} {x!r}")
        for k in x:
            if k not in valid:
                where = f"{key}.{k}" if key else repr(k)
                kind = "unknown key" if key else "unknown top-level key"
                raise self.err(f"{kind} {where} (valid: {', '.join(valid)})")
        for k in required:
            if k not in x:
                raise self.err(f"{key}.{k} is required")
        return dict(x)

    def number(self, key, x, *, gt=None, ge=None, lt=None, le=None) -> float:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise self.err(f"{key} must be a number, got {_tname(x)} {x!r}")
        if not math.isfinite(x):
            raise self.err(f"{key} must be finite, got {x!r}")
        for bound, ok, op in (
            (gt, lambda b: x > b, ">"),
            (ge, lambda b: x >= b, ">="),
            (lt, lambda b: x < b, "<"),
            (le, lambda b: x <= b, "<="),
        ):
            if bound is not None and not ok(bound):
                raise self.err(f"{key} must be {op} {bound:g}, got {x!r}")
        return x

    def integer(self, key, x, *, ge=None) -> int:
        if isinstance(x, bool) or not isinstance(x, int):
            raise self.err(f"{key} must be an integer, got {_tname(x)} {x!r}")
        if ge is not None and x < ge:
            raise self.err(f"{key} must be >= {ge}, got {x!r}")
        return x

    def boolean(self, key, x) -> bool:
        if not isinstance(x, bool):
            raise self.err(f"{key} must be true or false, got {_tname(x)} {x!r}")
        return x

    def string(self, key, x, choices=None) -> str:
        if not isinstance(x, str):
            raise self.err(f"{key} must be a string, got {_tname(x)} {x!r}")
        if choices is not None and x not in choices:
            raise self.err(f"{key} must be one of {', '.join(map(repr, choices))}, got {x!r}")
        return x

    def vector(self, key, x, checks: list, *, kind: str = "vec") -> list:
        if not isinstance(x, (list, tuple)) or not x:
            raise self.err(f"{key} must be a non-empty array of numbers, got {_tname(x)} {x!r}")
        out = [self.number(f"{key}[{i}]", v) for i, v in enumerate(x)]
        checks.append((kind, key, len(out)))
        return out

    def axis(self, key, x, checks: list) -> int | str:
        if isinstance(x, str):
            if x not in _AXES:
                raise self.err(f"{key} must be 0, 1, 2 or 'x', 'y', 'z', got {x!r}")
            checks.append(("axis", key, _AXES[x]))
            return x
        a = self.integer(key, x, ge=0)
        checks.append(("axis", key, a))
        return a


def _axis_index(a) -> int:
    return _AXES[a] if isinstance(a, str) else int(a)


@contextlib.contextmanager
def _on_path(directory: str):
    sys.path.insert(0, directory)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(directory)


def _import_callable(v: _V, key: str, spec: str, base_dir: str) -> Callable:
    """Resolve ``"module:function"`` (dotted attribute paths allowed after the colon)."""
    mod_name, _, attr = spec.partition(":")
    if not mod_name or not attr:
        raise v.err(f"{key}: {spec!r} is not of the form 'module:function'")
    try:
        with _on_path(base_dir):
            obj = importlib.import_module(mod_name)
    except Exception as e:  # noqa: BLE001 — any import failure is reported with the key
        raise v.err(f"{key}: cannot import module {mod_name!r} ({type(e).__name__}: {e})") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise v.err(f"{key}: module {mod_name!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise v.err(f"{key}: {spec!r} is not callable")
    return obj


def _n_positional(fn) -> int:
    """Number of positional parameters ``fn`` accepts (a large number for ``*args``)."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return 1
    n = 0
    for p in sig.parameters.values():
        if p.kind == p.VAR_POSITIONAL:
            return 99
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            n += 1
    return n


# ----------------------------------------------------------------------------------------
# sections
# ----------------------------------------------------------------------------------------


def _check_mesh(v: _V, x, base_dir: str, checks: list):
    key = "[mesh]"
    t = v.table(key, x, ("generator", "n", "size", "origin", "file", "order", "formulation"))
    if ("generator" in t) == ("file" in t):
        raise v.err(f"{key} needs exactly one of generator = ... or file = ...")
    fe = _check_mesh_element(v, key, t)
    if "file" in t:
        for k in ("n", "size", "origin"):
            if k in t:
                raise v.err(f"{key}.{k} is only valid with a generator (a file has its geometry)")
        path = os.path.join(base_dir, os.path.expanduser(v.string(f"{key}.file", t["file"])))
        path = os.path.normpath(path)
        if not os.path.isfile(path):
            raise v.err(f"{key}.file: no such mesh file {path!r}")
        return {"file": path, **fe}, None
    gen = v.string(f"{key}.generator", t["generator"], tuple(_GENERATOR_DIM))
    dim = _GENERATOR_DIM[gen]
    if gen == "cook":
        for k in ("size", "origin"):
            if k in t:
                raise v.err(f"{key}.{k} is not valid for generator 'cook' (fixed geometry)")
        n = t.get("n", 16)
        if isinstance(n, list) and len(n) == 1:
            n = n[0]
        return {"generator": gen, "n": v.integer(f"{key}.n", n, ge=1), **fe}, dim
    if "n" not in t:
        raise v.err(f"{key}.n is required for generator {gen!r}")
    n = t["n"]
    if not isinstance(n, list) or len(n) != dim:
        raise v.err(f"{key}.n must be an array of {dim} integers for {gen!r}, got {n!r}")
    out = {"generator": gen, "n": [v.integer(f"{key}.n[{i}]", a, ge=1) for i, a in enumerate(n)]}
    size = t.get("size", [1.0] * dim)
    out["size"] = v.vector(f"{key}.size", size, checks)
    for i, s in enumerate(out["size"]):
        v.number(f"{key}.size[{i}]", s, gt=0)
    out["origin"] = v.vector(f"{key}.origin", t.get("origin", [0.0] * dim), checks)
    return {**out, **fe}, dim


def _check_mesh_element(v: _V, key: str, t: dict) -> dict:
    """``order`` (1 | 2) and ``formulation`` ("standard" | "fbar" | "bbar") of [mesh]."""
    from .mesh import FORMULATIONS

    out = {
        "formulation": v.string(
            f"{key}.formulation", t.get("formulation", "standard"), FORMULATIONS
        )
    }
    if "order" in t:
        order = v.integer(f"{key}.order", t["order"], ge=1)
        if order not in (1, 2):
            raise v.err(f"{key}.order must be 1 or 2, got {order}")
        out["order"] = order
    elif "generator" in t:
        out["order"] = 1  # a file keeps its own order unless order = ... is given
    return out


def _check_material(v: _V, x, base_dir: str):
    key = "[material]"
    t = v.table(key, x, ("model", "E", "nu", "mu", "lam", "plane", "density"), ("model",))
    model = v.string(f"{key}.model", t["model"])
    from .materials import BUILTIN

    if ":" in model:
        _import_callable(v, f"{key}.model", model, base_dir)
    elif model not in BUILTIN:
        raise v.err(
            f"{key}.model: unknown material {model!r} (built-in: {', '.join(BUILTIN)}; or "
            "'module:function' for your own psi(F, params))"
        )
    out = {"model": model}
    has_E, has_mu = ("E" in t or "nu" in t), ("mu" in t or "lam" in t)
    if has_E == has_mu:
        raise v.err(f"{key} needs either E and nu, or mu and lam (exactly one pair)")
    if has_E:
        for k in ("E", "nu"):
            if k not in t:
                raise v.err(f"{key}.{k} is required (give E and nu together)")
        out["E"] = v.number(f"{key}.E", t["E"], gt=0)
        out["nu"] = v.number(f"{key}.nu", t["nu"], gt=-1, lt=0.5)
    else:
        for k in ("mu", "lam"):
            if k not in t:
                raise v.err(f"{key}.{k} is required (give mu and lam together)")
        out["mu"] = v.number(f"{key}.mu", t["mu"], gt=0)
        out["lam"] = v.number(f"{key}.lam", t["lam"])
        if not out["lam"] > -out["mu"]:
            raise v.err(f"{key}.lam must be > -mu (a positive bulk modulus), got {t['lam']!r}")
    if "plane" in t:
        out["plane"] = v.string(f"{key}.plane", t["plane"], ("strain", "stress"))
        if has_mu:
            raise v.err(f"{key}.plane needs E and nu (mu and lam are used as given)")
    if "density" in t:
        out["density"] = v.number(f"{key}.density", t["density"], gt=0)
    return out


def _parse_where(v: _V, key: str, expr: str) -> None:
    try:
        check_where(expr)
    except WhereError as e:
        raise v.err(f"{key}: {e} in {expr!r}") from None


def _check_selector(v: _V, key: str, x, checks: list):
    t = v.table(key, x, ("plane", "box", "group", "where"))
    if len(t) != 1:
        raise v.err(f"{key} needs exactly one of plane, box, group, where; got {sorted(t)}")
    ((kind, val),) = t.items()
    k = f"{key}.{kind}"
    if kind == "plane":
        p = v.table(k, val, ("axis", "value", "tol"), ("axis", "value"))
        out = {"axis": v.axis(f"{k}.axis", p["axis"], checks)}
        out["value"] = v.number(f"{k}.value", p["value"])
        if "tol" in p:
            out["tol"] = v.number(f"{k}.tol", p["tol"], gt=0)
        return {"plane": out}
    if kind == "box":
        b = v.table(k, val, ("lo", "hi"), ("lo", "hi"))
        lo, hi = v.vector(f"{k}.lo", b["lo"], checks), v.vector(f"{k}.hi", b["hi"], checks)
        if len(lo) != len(hi) or any(a > c for a, c in zip(lo, hi, strict=True)):
            raise v.err(f"{k}: lo must not exceed hi componentwise, got lo={lo}, hi={hi}")
        return {"box": {"lo": lo, "hi": hi}}
    if kind == "group":
        return {"group": v.string(k, val)}
    _parse_where(v, k, v.string(k, val))
    return {"where": val}


def _check_displacement(v: _V, key: str, x, base_dir: str, checks: list):
    if isinstance(x, str):
        _import_callable(v, key, x, base_dir)
        return x
    if isinstance(x, Mapping):
        t = v.table(key, x, ("rotate",), ("rotate",))
        k = f"{key}.rotate"
        r = v.table(k, t["rotate"], ("axis", "angle_deg", "center", "scale"), ("angle_deg",))
        out = {"axis": v.axis(f"{k}.axis", r.get("axis", "z"), [])}  # checked as "rotate"
        out["angle_deg"] = v.number(f"{k}.angle_deg", r["angle_deg"])
        if "center" in r:
            out["center"] = v.vector(f"{k}.center", r["center"], checks)
        out["scale"] = v.number(f"{k}.scale", r.get("scale", 1.0))
        checks.append(("rotate", k, _axis_index(out["axis"])))
        return {"rotate": out}
    return v.vector(key, x, checks)


def _check_dirichlet(v: _V, x, base_dir: str, checks: list):
    if isinstance(x, Mapping):
        raise v.err("[dirichlet] must be an array of tables: write [[dirichlet]]")
    if not isinstance(x, list):
        raise v.err(f"[dirichlet] must be an array of tables, got {_tname(x)}")
    out = []
    for i, entry in enumerate(x):
        key = f"[dirichlet][{i}]"
        t = v.table(key, entry, ("nodes", "components", "displacement", "ramp_time"), ("nodes",))
        d = {"nodes": _check_selector(v, f"{key}.nodes", t["nodes"], checks)}
        if "components" in t:
            c = t["components"]
            if not isinstance(c, list) or not c:
                raise v.err(f"{key}.components must be a non-empty array, got {c!r}")
            comps = [v.axis(f"{key}.components[{j}]", a, checks) for j, a in enumerate(c)]
            if len({_axis_index(a) for a in comps}) != len(comps):
                raise v.err(f"{key}.components repeats a component: {c!r}")
            d["components"] = comps
        if "displacement" in t:
            d["displacement"] = _check_displacement(
                v, f"{key}.displacement", t["displacement"], base_dir, checks
            )
        if "ramp_time" in t:
            d["ramp_time"] = v.number(f"{key}.ramp_time", t["ramp_time"], gt=0)
        out.append(d)
    return out


def _check_loads(v: _V, section: str, x, checks: list):
    if isinstance(x, Mapping):
        raise v.err(f"[{section}] must be an array of tables: write [[{section}]]")
    if not isinstance(x, list):
        raise v.err(f"[{section}] must be an array of tables, got {_tname(x)}")
    where, value = ("facets", "traction") if section == "traction" else ("nodes", "force")
    out = []
    for i, entry in enumerate(x):
        key = f"[{section}][{i}]"
        t = v.table(key, entry, (where, value, "total_force"), (where,))
        if (value in t) == ("total_force" in t):
            raise v.err(f"{key} needs exactly one of {value} = [..] or total_force = [..]")
        d = {where: _check_selector(v, f"{key}.{where}", t[where], checks)}
        k = value if value in t else "total_force"
        d[k] = v.vector(f"{key}.{k}", t[k], checks)
        out.append(d)
    return out


def _check_solver(v: _V, x):
    from .solvers.newton import NewtonSettings

    key = "[solver]"
    fields = NewtonSettings._fields + ("linear",)
    t = v.table(key, x, fields)
    defaults = dict(NewtonSettings._field_defaults, linear="auto")
    out = {}
    for k, val in t.items():
        d, kk = defaults.get(k), f"{key}.{k}"
        if isinstance(d, bool):
            out[k] = v.boolean(kk, val)
        elif isinstance(d, int):
            out[k] = v.integer(kk, val, ge=0 if k == "atol" else 1)
        elif isinstance(d, float):
            out[k] = v.number(kk, val, ge=0)
        elif isinstance(d, str):
            out[k] = v.string(kk, val, _SOLVER_CHOICES.get(k))
        else:
            out[k] = val
    if out.get("armijo") is not None and not out["armijo"] < 1:
        raise v.err(f"{key}.armijo must be < 1, got {out['armijo']!r}")
    return out


def _check_integrator(v: _V, x, base_dir: str, checks: list):
    key = "[integrator]"
    if not isinstance(x, Mapping):
        raise v.err(f"{key} must be a table, got {_tname(x)}")
    kind = v.string(f"{key}.type", x.get("type", "static"), ("static", "dynamic"))
    if kind == "static":
        for k in x:
            if k not in _STATIC_KEYS:
                raise v.err(
                    f"unknown key {key}.{k} for type = 'static' (valid: {', '.join(_STATIC_KEYS)})"
                )
        return {
            "type": "static",
            "load_steps": v.integer(f"{key}.load_steps", x.get("load_steps", 1), ge=1),
        }
    t = v.table(key, x, _DYNAMIC_KEYS, ("h", "duration"))
    out = {"type": "dynamic"}
    out["h"] = v.number(f"{key}.h", t["h"], gt=0)
    out["duration"] = v.number(f"{key}.duration", t["duration"], gt=0)
    if out["duration"] < out["h"] * (1 - 1e-12):
        raise v.err(f"{key}.duration must be >= h = {out['h']!r}, got {out['duration']!r}")
    out["method"] = v.string(
        f"{key}.method", t.get("method", "backward_euler"), ("backward_euler", "bdf2")
    )
    out["alpha"] = v.number(f"{key}.alpha", t.get("alpha", 0.0), ge=0)
    out["beta"] = v.number(f"{key}.beta", t.get("beta", 0.0), ge=0)
    out["settle"] = v.boolean(f"{key}.settle", t.get("settle", False))
    out["settle_tol"] = v.number(f"{key}.settle_tol", t.get("settle_tol", 1e-8), gt=0)
    out["settle_steps"] = v.integer(f"{key}.settle_steps", t.get("settle_steps", 5), ge=1)
    out["compare_static"] = v.boolean(f"{key}.compare_static", t.get("compare_static", False))
    if "initial_velocity" in t:
        iv = t["initial_velocity"]
        if isinstance(iv, str):
            _import_callable(v, f"{key}.initial_velocity", iv, base_dir)
            out["initial_velocity"] = iv
        else:
            out["initial_velocity"] = v.vector(f"{key}.initial_velocity", iv, checks)
    return out


def _check_output(v: _V, x, checks: list):
    key = "[output]"
    t = v.table(key, x, ("every", "vtu", "png", "probes"))
    out = {
        "every": v.integer(f"{key}.every", t.get("every", 1), ge=1),
        "vtu": v.boolean(f"{key}.vtu", t.get("vtu", True)),
        "png": v.boolean(f"{key}.png", t.get("png", True)),
    }
    probes = t.get("probes", [])
    if not isinstance(probes, list):
        raise v.err(f"{key}.probes must be an array of points, got {_tname(probes)}")
    out["probes"] = [v.vector(f"{key}.probes[{i}]", p, checks) for i, p in enumerate(probes)]
    return out


def _check_dims(v: _V, checks, dim: int) -> None:
    """Check vector lengths and axis indices against the mesh dimension."""
    for kind, key, n in checks:
        if kind == "vec" and n != dim:
            raise v.err(f"{key} must have {dim} components (the mesh is {dim}D), got {n}")
        if kind == "axis" and n >= dim:
            raise v.err(f"{key} must be an axis of a {dim}D mesh (0..{dim - 1}), got {n}")
        if kind == "rotate" and dim == 2 and n != 2:
            raise v.err(f"{key}.axis must be 'z' (2) in 2D, got {n}")
        if kind == "rotate" and n > 2:
            raise v.err(f"{key}.axis must be 0, 1, 2 or 'x', 'y', 'z', got {n}")


def _validate(v: _V, raw, base_dir: str):
    t = v.table("", raw, _TOP, ())
    for k in ("mesh", "material"):
        if k not in t:
            raise v.err(f"[{k}] is required")
    checks: list = []
    data = {
        "name": v.string("name", t.get("name", "scene")),
        "description": v.string("description", t.get("description", "")),
    }
    data["mesh"], dim = _check_mesh(v, t["mesh"], base_dir, checks)
    data["material"] = _check_material(v, t["material"], base_dir)
    data["dirichlet"] = _check_dirichlet(v, t.get("dirichlet", []), base_dir, checks)
    data["traction"] = _check_loads(v, "traction", t.get("traction", []), checks)
    data["point_load"] = _check_loads(v, "point_load", t.get("point_load", []), checks)
    if "gravity" in t:
        g = v.table("[gravity]", t["gravity"], ("g",), ("g",))
        data["gravity"] = {"g": v.vector("[gravity].g", g["g"], checks)}
    data["solver"] = _check_solver(v, t.get("solver", {}))
    data["integrator"] = _check_integrator(v, t.get("integrator", {}), base_dir, checks)
    data["output"] = _check_output(v, t.get("output", {}), checks)
    if "fit" in t:  # material identification: validated and run by jaxelastic._scene_fit
        from ._scene_fit import check_fit

        data["fit"] = check_fit(v, t["fit"], data)

    mat, integ = data["material"], data["integrator"]
    dynamic = integ["type"] == "dynamic"
    if "density" not in mat:
        if dynamic:
            raise v.err("[material].density is required for a dynamic scene")
        if "gravity" in data:
            raise v.err("[material].density is required with [gravity]")
    if not dynamic:
        if not data["dirichlet"]:
            raise v.err(
                "[dirichlet]: a static scene needs at least one Dirichlet condition "
                "(else rigid motions are free)"
            )
        for i, d in enumerate(data["dirichlet"]):
            if "ramp_time" in d:
                raise v.err(f"[dirichlet][{i}].ramp_time is only valid in a dynamic scene")
            u = d.get("displacement")
            if isinstance(u, str):
                fn = _import_callable(v, f"[dirichlet][{i}].displacement", u, base_dir)
                if _n_positional(fn) < 1:
                    raise v.err(f"[dirichlet][{i}].displacement: {u!r} must accept u(X)")
    if dim is not None:
        if dim == 3 and "plane" in mat:
            raise v.err("[material].plane applies to 2D meshes only")
        _check_dims(v, checks, dim)
    return data, dim, tuple(checks)
