"""Shared test data (imported by several test modules; not a test module itself)."""

import importlib.util
import json
import sys
from pathlib import Path

from jaxelastic import materials as M

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"

# every built-in model in every dimension its definition allows
MODEL_DIMS = [
    (name, d)
    for name in M.BUILTIN
    for d in (2, 3)
    if not (name == "stable_neo_hookean_log" and d == 2)
]
IDS = [f"{n}-{d}D" for n, d in MODEL_DIMS]

# a tiny 2D static scene (reused by several tests, so its solver compiles once)
TINY_SCENE = {
    "name": "tiny",
    "mesh": {"generator": "rectangle", "n": [4, 2], "size": [2.0, 1.0]},
    "material": {"model": "neo_hookean", "E": 1000.0, "nu": 0.3},
    "dirichlet": [{"nodes": {"plane": {"axis": "x", "value": 0.0}}}],
    "traction": [{"facets": {"plane": {"axis": "x", "value": 2.0}}, "total_force": [0.0, -10.0]}],
    "integrator": {"type": "static"},
    "output": {"probes": [[2.0, 0.5]]},
}


def scene_toml(data: dict) -> str:
    """A scene dict as TOML text (the subset scenes need: scalars, vectors, inline tables,
    tables and arrays of tables)."""

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(a) for a in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {val(a)}" for k, a in v.items()) + " }"
        return repr(v)

    lines = [f"{k} = {val(v)}" for k, v in data.items() if not isinstance(v, (dict, list))]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += [f"[{k}]"] + [f"{a} = {val(b)}" for a, b in v.items()]
        elif isinstance(v, list):
            for entry in v:
                lines += [f"[[{k}]]"] + [f"{a} = {val(b)}" for a, b in entry.items()]
    return "\n".join(lines) + "\n"


def load_script(name: str):
    """Import ``scripts/<name>.py`` as the module ``name`` (once per process), as running
    it from scripts/ would: registered in ``sys.modules`` before it runs, so the reports
    import their sibling ``_report_common`` by that name."""
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]
