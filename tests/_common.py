"""Shared test data (imported by several test modules; not a test module itself)."""

from jaxelastic import materials as M

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
