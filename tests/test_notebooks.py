"""Execute every notebook in ``notebooks/``: their claims are ``assert``s, so each is a test.

The kernel is the interpreter running pytest: a throw-away kernel spec (argv
``sys.executable -m ipykernel_launcher``) in a temp dir put first on ``JUPYTER_PATH``, so a
fresh ``python3 -m venv .venv && pip install -e '.[all,dev]'`` works whatever kernels are
installed globally or per user. Each notebook runs in a temporary working directory, and
the executed copy is never written back over the source.

A notebook that reads ``JAXELASTIC_NOTEBOOK_FAST`` (``FAST = os.environ.get(FAST_ENV) == "1"``:
fewer time steps, a smaller grid, fewer fits; every claim still asserted) runs in that mode
under ``-m extended`` and at full size under ``-m slow``; the documentation build
(``mkdocs build`` in ``.ci/run``) executes every notebook at full size too. A notebook without
the switch runs at full size under ``-m extended``, except those in ``SLOW_ONLY``. The whole
file is in the second tier (``pytest -m extended``, run by ``.ci/run``).
"""

from __future__ import annotations

import json
import pathlib
import sys
import time

import nbformat
import pytest
from jupyter_client.kernelspec import KernelSpecManager
from nbclient import NotebookClient

pytestmark = pytest.mark.extended  # the second tier: pytest -m extended

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
KERNEL_NAME = "jaxelastic-test-python"
CELL_TIMEOUT = 600  # seconds, per cell
FAST_ENV = "JAXELASTIC_NOTEBOOK_FAST"
# run only under -m slow: notebook 04 drives the accuracy and stability report scripts,
# which tests/test_reports.py runs, and `mkdocs build` in .ci/run
# executes it at full size (67 s on the 2-core machine, 2026-12-02, commit 5628254)
SLOW_ONLY = {"04_error_vs_runtime_and_stability"}


def _params():
    """``(path, fast)`` per notebook: the fast variant (if it has one) under ``-m extended``,
    the full size under ``-m slow``."""
    params = []
    for path in NOTEBOOKS:
        if FAST_ENV in path.read_text(encoding="utf-8"):
            params.append(pytest.param(path, True, id=f"{path.stem}-fast"))
            params.append(pytest.param(path, False, id=path.stem, marks=pytest.mark.slow))
        elif path.stem in SLOW_ONLY:
            params.append(pytest.param(path, False, id=path.stem, marks=pytest.mark.slow))
        else:
            params.append(pytest.param(path, False, id=path.stem))
    return params


@pytest.fixture(scope="module")
def jupyter_path(tmp_path_factory) -> pathlib.Path:
    """A data dir holding a kernel spec that runs ipykernel with this very interpreter."""
    data = tmp_path_factory.mktemp("jupyter")
    spec_dir = data / "kernels" / KERNEL_NAME
    spec_dir.mkdir(parents=True)
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": f"Python {sys.version_info.major}.{sys.version_info.minor} (tests)",
        "language": "python",
        "metadata": {"debugger": False},
    }
    (spec_dir / "kernel.json").write_text(json.dumps(spec, indent=1))
    return data


def _stray_files() -> set[str]:
    """Files under ``notebooks/`` other than notebooks (outputs a notebook must not write)."""
    return {
        str(p.relative_to(ROOT))
        for p in NOTEBOOK_DIR.rglob("*")
        if p.suffix != ".ipynb" and ".ipynb_checkpoints" not in p.parts
    }


@pytest.mark.parametrize(("path", "fast"), _params())
def test_notebook_executes(path, fast, jupyter_path, tmp_path, monkeypatch):
    # Find our kernel spec first; keep the kernel's connection and IPython files out of
    # $HOME; let ipykernel pick its inline matplotlib backend even if the caller exported a
    # non-interactive one.
    monkeypatch.setenv("JUPYTER_PATH", str(jupyter_path))
    monkeypatch.setenv("JUPYTER_RUNTIME_DIR", str(tmp_path / "runtime"))
    monkeypatch.setenv("IPYTHONDIR", str(tmp_path / "ipython"))
    monkeypatch.setenv("PYDEVD_DISABLE_FILE_VALIDATION", "1")
    monkeypatch.delenv("MPLBACKEND", raising=False)
    if fast:
        monkeypatch.setenv(FAST_ENV, "1")
    else:
        monkeypatch.delenv(FAST_ENV, raising=False)
    workdir = tmp_path / "cwd"
    workdir.mkdir()

    source = path.read_bytes()
    nb = nbformat.reads(source.decode("utf-8"), as_version=4)
    before = _stray_files()

    assert KernelSpecManager().get_kernel_spec(KERNEL_NAME).argv[0] == sys.executable

    client = NotebookClient(  # owns (starts and shuts down) its kernel
        nb,
        timeout=CELL_TIMEOUT,
        kernel_name=KERNEL_NAME,
        resources={"metadata": {"path": str(workdir)}},
    )
    t0 = time.perf_counter()
    client.execute()  # raises CellExecutionError, with the failing cell, on any error
    elapsed = time.perf_counter() - t0

    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"
    ]
    assert not errors, errors
    assert path.read_bytes() == source, "the source notebook was modified"
    assert _stray_files() == before, "the notebook wrote files into notebooks/"
    print(f"{path.name}{' (fast)' if fast else ''}: executed in {elapsed:.1f} s")
