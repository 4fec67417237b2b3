"""The library imports and solves without its host-only dependencies (a lean GPU image).

A subprocess installs a ``sys.meta_path`` finder that refuses every host-only package
(pyamg, pypardiso, mkl, cholespy, scikit-sparse, matplotlib, tqdm, gmsh, and the
partitioner and XDMF reader of the extras, pymetis and h5py) before anything
is imported, then imports jaxelastic, solves with the device CG and with ``linear="auto"``
(which must fall back to the device multigrid with one warning) and checks that none of
the refused packages was even attempted at import time.
"""

import json
import subprocess
import sys
import textwrap

import pytest

HOST_ONLY = (
    "pyamg",
    "pypardiso",
    "mkl",
    "cholespy",
    "sksparse",
    "matplotlib",
    "tqdm",
    "gmsh",
    "pymetis",
    "h5py",
)

_BLOCKER = """
import importlib.abc, sys
HOST_ONLY = set({host_only!r})
ATTEMPTS = []
class _Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HOST_ONLY:
            ATTEMPTS.append(name)
            raise ImportError(f"{{name}} is hidden by the lean-import test")
        return None
sys.meta_path.insert(0, _Refuse())
"""

_SCRIPT = """
import warnings
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import jaxelastic as je
from jaxelastic import loads, materials as M

at_import = list(ATTEMPTS)
mesh = je.rectangle(8, 2, (4.0, 1.0))
bc = loads.fix(mesh, loads.nodes_on_plane(mesh, 0, 0.0))
f = jnp.zeros_like(mesh.points).at[loads.nodes_on_plane(mesh, 0, 4.0), 1].set(-0.01)
pot = je.Potential(mesh=mesh, params=M.Lame.from_E_nu(100.0, 0.3, dim=2), f_ext=f,
                   psi=M.neo_hookean)
tight = je.Newton(rtol=1e-12)
x_cg = je.solve(pot, bc, solver=tight.replace(linear=je.CG())).x
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("default")
    bound = je.solvers.linear.resolve("auto", mesh, bc)
    r1 = je.solve(pot, bc, solver=tight)  # "auto"
    r2 = je.solve(pot, bc, solver=tight)
fallback = [str(w.message) for w in caught if "linear='auto'" in str(w.message)]
print(json.dumps(dict(
    at_import=at_import,
    loaded=sorted(m for m in sys.modules if m.split(".")[0] in HOST_ONLY),
    auto=type(bound).__name__,
    warnings=fallback,
    status=[int(r1.status), int(r2.status)],
    diff=float(jnp.max(jnp.abs(r1.x - x_cg))),
    moved=float(jnp.max(jnp.abs(x_cg - mesh.points))),
)))
"""


def _run_hidden(script: str) -> dict:
    code = _BLOCKER.format(host_only=HOST_ONLY) + "import json\n" + textwrap.dedent(script)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def lean():
    return _run_hidden(_SCRIPT)


def test_import_touches_no_host_only_package(lean):
    """``import jaxelastic`` does not even try to import a host-only package."""
    assert lean["at_import"] == [], lean["at_import"]
    assert lean["loaded"] == [], lean["loaded"]


def test_cg_and_auto_solve_without_host_packages(lean):
    """With the host packages hidden, CG solves, and "auto" resolves to the device
    multigrid with exactly one warning naming the missing package, and gives CG's x*."""
    assert lean["auto"] == "Multilevel"
    assert lean["status"] == [0, 0]
    assert lean["moved"] > 1e-3  # the load did something
    assert lean["diff"] <= 1e-9, lean["diff"]
    assert len(lean["warnings"]) == 1, lean["warnings"]
    assert "pypardiso" in lean["warnings"][0] and "multilevel" in lean["warnings"][0]


def test_a_scene_run_loads_only_what_it_needs_and_preloads_matplotlib():
    """Running a scene imports neither the fitting modules nor the scene-reference
    generator (``jaxelastic.scene`` is lazy), and :func:`jaxelastic.plot.preload`
    imports matplotlib's figure and Agg modules in its background thread."""
    code = textwrap.dedent(
        """
        import json, sys
        import jaxelastic.scene.run
        from jaxelastic import plot
        before = sorted(m for m in sys.modules if m.startswith(("jaxelastic.fitting",
                        "jaxelastic.scene.docs", "jaxelastic.scene.fit", "matplotlib")))
        plot.preload().join(120)
        import jaxelastic.scene as S
        print(json.dumps(dict(before=before, after=[m in sys.modules for m in plot.PRELOADED],
                              run_fit=S.run_fit.__module__)))
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["before"] == [], out["before"]
    assert out["after"] == [True, True]
    assert out["run_fit"] == "jaxelastic.scene.fit"
