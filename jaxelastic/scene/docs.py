"""The scene-file reference (``docs/scenes.md``), generated from the JSON Schema.

:func:`reference_markdown` writes one section per table of a scene file with every key's
type, default, allowed values or range and description (from the pydantic models of
:mod:`jaxelastic.scene.schema`), plus an example scene (:data:`EXAMPLE`, checked by the
tests to be valid), the where-expression rules and what a run writes.
``python scripts/gen_scene_docs.py`` rewrites ``docs/scenes.md``.
"""

from __future__ import annotations

import json

from .schema import json_schema

__all__ = ["EXAMPLE", "reference_markdown"]

EXAMPLE = """\
name = "beam"
description = "a soft beam released under gravity"

[mesh]
generator = "box"             # or file = "part.msh" (relative to the scene file)
n = [20, 3, 3]
size = [2.0, 0.25, 0.25]

[material]
model = "neo_hookean"         # or "module:function" for your own psi(F, params)
E = 1e7
nu = 0.3
density = 1000.0

[[dirichlet]]
nodes = { plane = { axis = "x", value = 0.0 } }

[[traction]]
facets = { plane = { axis = "x", value = 2.0 } }
traction = [0, 0, -100.0]

[[point_load]]
nodes = { box = { lo = [2, 0, 0], hi = [2, 0.25, 0.25] } }
force = [0, 0, -1.0]

[gravity]
g = [0, 0, -9.81]

[solver]
linear = "auto"
rtol = 1e-8

[integrator]
type = "dynamic"
h = 0.02
duration = 10.0
alpha = 2.0
settle = true
compare_static = true

[output]
every = 5
probes = [[2.0, 0.125, 0.125]]
"""
"""A valid scene using most tables (the reference's example)."""

_INTRO = """\
# Scene file reference

<!-- Generated from jaxelastic.scene.schema by `python scripts/gen_scene_docs.py`;
     do not edit by hand (tests/test_scenes.py checks that it is up to date). -->

A scene is a TOML file: a mesh, a material, boundary conditions, loads, solver settings,
an integrator and outputs. `jaxelastic run SCENE --out DIR` solves it, `jaxelastic fit
SCENE --out DIR` fits E and nu as its `[fit]` table says, `jaxelastic scenes` lists the
shipped scenes. Unknown keys, wrong types and impossible values are refused with a message
naming the key as written here (`[material].nu`, `[dirichlet][0].nodes.plane.axis`), the
value and what is valid.

Editor support: `jaxelastic schema > scene.schema.json` writes the JSON Schema of a scene
file; with taplo / Even Better TOML, put `#:schema ./scene.schema.json` on the first line of
a scene file (or map `*.toml` scenes to it in `.taplo.toml`) for completion and checks.

Vectors (*array of float*) have one entry per mesh dimension. An axis is `0/1/2` or
`"x"/"y"/"z"`. A `"module:function"` is imported with the scene file's directory first on
`sys.path`; user materials receive `params = Lame(mu, lam)`. A static scene needs a
Dirichlet condition; elastic parameters are checked with `jaxelastic.materials.lame`.

## Example

```toml
{example}```
"""

_WHERE = """\
## Where-expressions

`where` (node selections) and `[fit].regions` are boolean expressions of the rest
positions (`X` `(n, dim)`, or its columns `x`, `y`, `z`), evaluated by a small interpreter,
**not** `eval`: numbers, arithmetic, comparisons (chained too), `&` `|` `^` `~` `and` `or`
`not`, integer indexing and slicing (`X[:, 0]`), `pi`, and the NumPy functions `abs sqrt
hypot minimum maximum sin cos arctan2 isclose logical_and logical_or logical_not` (also as
`np.abs` ...; keywords `atol`/`rtol` only). Anything else is refused, and so are constants
beyond the range of float64 (`1e999`), constant arithmetic that overflows (`9 ** 9 ** 9`)
and floating-point errors while evaluating (overflow, division by zero, `sqrt` of a
negative number).
"""

_OUTPUTS = """\
## Running a scene and reading its outputs

```
jaxelastic run [SCENE] --out DIR [--set integrator.duration=1.0 ...] [--no-progress] [--json]
python -m jaxelastic run twist --out results/twist      # a shipped scene by name
jaxelastic scenes                                        # list the shipped scenes
jaxelastic schema > scene.schema.json                    # the JSON Schema
```

stdout gets a summary table (mesh, material, solver, iterations, largest displacement,
reaction vs applied load, energy, compile and run time, files written); `--json` prints
one JSON line instead (`status`, `out`, `summary`, `wall_time`, `compile_time`).

In Python: `summary = jaxelastic.scene.run_scene("my.toml", "out")` (enable float64
first); `load_scene` and `build` give the validated scene and its arrays. `DIR` receives,
each file written atomically:

* `dynamic.pvd` + `dynamic_NNNN.vtu` (every `[output].every` steps) and/or `static.pvd` +
  `static_0000.vtu`: open the `.pvd` in ParaView and apply *Warp By Vector* with
  `displacement`; cell data `J`, `green_strain`, `stress_P`, `cauchy_stress`,
  `von_mises`, `energy_density`; point data `cauchy_stress_nodal`, `von_mises_nodal`
  (recovered nodal stresses) and `velocity` in dynamics;
* `final_shape.png` (rest, final and static shapes, coloured by the von Mises stress,
  small displacements magnified with the factor in the title), and in dynamics
  `tip_displacement.png` (first probe, or the node farthest from the supports) and
  `energy.png`;
* `summary.json`: `scene` (with defaults), `mesh`, `material`, `solver`, `timings` (build,
  first step including compilation, median step, static solve, outputs, total),
  `dynamic.per_step` (time, Newton and CG iterations, residual, kinetic/elastic/
  load-potential/total energy), `static` (iterations, residual history, reaction force vs
  applied load), `probes`, `comparison` (static vs dynamic: max nodal distance, relative
  to the tip deflection), `status` (`ok`, `failed`, `interrupted`) and `interrupted`;
  `dynamic.kinetic_over_elastic` is `null` when the elastic energy is zero to round-off
  (a free body in rigid motion), and then `settle` needs the kinetic energy at round-off
  too.

`jaxelastic fit` writes `summary.json` (cases, target, initial guess, fitted values and
their errors when the truth is known, histories), `fit.png` and `observed.npz`.

Exit status: 0 success, 1 a solve failed (`summary.json` is still written), 2 an invalid
scene or `--out`, 130 interrupted. Before anything is built, the memory a scene needs is
estimated from its mesh size (element Hessians, the sparse pattern and factor, ...) and a
scene that will not fit the memory available is refused with the estimate; set
`[solver] max_memory_gb` (`--set solver.max_memory_gb=64`) to use another budget. Ctrl-C
(SIGINT) or SIGTERM stops a run at the next time step or load increment (a fit's optimiser
at once; a second signal stops at once too): the last completed state is written, the
`.pvd` lists only the files written, `summary.json` has `"interrupted": true` and what was
`completed`, and temporaries are removed.
"""


def _ref(p: dict) -> str | None:
    r = p.get("$ref")
    return r.rsplit("/", 1)[-1] if r else None


def _type(p: dict) -> str:
    """A short type name of a JSON Schema node."""
    if _ref(p):
        return "table"
    for key in ("oneOf", "anyOf"):
        if key in p:
            return " or ".join(dict.fromkeys(_type(a) for a in p[key]))
    if "const" in p or "enum" in p:
        vals = p.get("enum", [p.get("const")])
        return "integer" if all(isinstance(v, int) for v in vals) else "string"
    t: str = p.get("type", "any")
    if t == "array":
        return f"array of {_type(p['items'])}" if "items" in p else "array"
    if t == "object":
        return "table"
    return {"number": "float"}.get(t, t)


def _range(p: dict) -> list[str]:
    out = []
    for key, op in (
        ("exclusiveMinimum", ">"),
        ("minimum", ">="),
        ("exclusiveMaximum", "<"),
        ("maximum", "<="),
    ):
        if key in p:
            out.append(f"{op} {p[key]:g}")
    return out


def _allowed(p: dict) -> str:
    """Allowed values or range of a JSON Schema node."""
    if "enum" in p:
        return ", ".join(json.dumps(v) for v in p["enum"])
    if "const" in p:
        return json.dumps(p["const"])
    parts = _range(p)
    if "items" in p and _allowed(p["items"]):
        parts.append(f"each {_allowed(p['items'])}")
    if p.get("minItems"):
        parts.append("non-empty")
    if "pattern" in p:
        parts.append('"module:function"')
    for key in ("oneOf", "anyOf"):
        parts += [a for a in (_allowed(x) for x in p.get(key, ())) if a]
    return "; ".join(parts)


def _default(p: dict, required: bool) -> str:
    if required:
        return "required"
    if "default" not in p:
        return "—"
    d = p["default"]
    if isinstance(d, dict):
        return "(table defaults)" if d else "`{}`"
    if d in ([], ""):
        return "`[]`" if d == [] else '`""`'
    return f"`{json.dumps(d)}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _table(defn: dict) -> list[str]:
    rows = ["| key | type | default | allowed | description |", "|---|---|---|---|---|"]
    req = set(defn.get("required", ()))
    for k, p in defn.get("properties", {}).items():
        cells = (
            f"`{k}`",
            _type(p),
            _default(p, k in req),
            _allowed(p),
            p.get("description", ""),
        )
        rows.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return rows


def _children(defn: dict):
    """``(key, def name, is_array)`` of the tables nested in a table."""
    for k, p in defn.get("properties", {}).items():
        for alt in p.get("oneOf", p.get("anyOf", [p])):
            name = _ref(alt) or _ref(alt.get("items", {}))
            if name:
                yield k, name, "items" in alt


def _heading(parent: str, key: str, is_array: bool, variant: str | None) -> str:
    if parent == "":
        name = f"[[{key}]]" if is_array else f"[{key}]"
    elif is_array and parent.startswith("[") and not parent.startswith("[["):
        name = f"[[{parent[1:-1]}.{key}]]"
    else:
        name = f"{parent}.{key}"
    return f"{name} ({variant})" if variant else name


def _walk(schema: dict):
    """Breadth-first ``(heading path, def name, variant)`` of every table, first use first,
    and every path each table is used at."""
    defs = schema["$defs"]
    order, paths = [], {}
    queue = [("", schema)]
    while queue:
        parent, defn = queue.pop(0)
        for key, name, is_array in _children(defn):
            here = _heading(parent, key, is_array, None)
            paths.setdefault(name, []).append(here)
            if len(paths[name]) > 1:
                continue
            props = defs[name].get("properties", {})
            variant = None
            if "const" in props.get("type", {}):
                variant = f'type = "{props["type"]["const"]}"'
            order.append((here, name, variant))
            queue.append((here, defs[name]))
    return order, paths


def _sections(schema: dict) -> list[str]:
    """The top level, then each table at the first key that uses it."""
    defs = schema["$defs"]
    lines = ["## Top level", "", *_table(schema), ""]
    order, paths = _walk(schema)
    for here, name, variant in order:
        d = defs[name]
        head = f"{here} ({variant})" if variant else here
        lines += [f"## `{head}`", "", d.get("description", "").replace("``", "`"), ""]
        others = [p for p in paths[name][1:] if p != here]
        if others:
            lines += ["Also used as " + ", ".join(f"`{p}`" for p in others) + ".", ""]
        lines += [*_table(d), ""]
    return lines


def reference_markdown() -> str:
    """The scene-file reference as Markdown (the content of ``docs/scenes.md``)."""
    schema = json_schema()
    parts = [_INTRO.replace("{example}", EXAMPLE), "\n".join(_sections(schema)), _WHERE, _OUTPUTS]
    return "\n".join(p.rstrip("\n") + "\n" for p in parts)
