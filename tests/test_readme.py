"""The README's Python examples run as written (each block in a fresh interpreter)."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.S)


def test_readme_has_examples():
    assert len(BLOCKS) >= 2, "README lost its Python examples"


def _run(code: str, tmp_path):
    script = tmp_path / "example.py"
    script.write_text(code, encoding="utf-8")
    out = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=600, cwd=tmp_path
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_quickstart_example_runs(tmp_path):
    """The first block: a solve, its status line and a gradient through it."""
    stdout = _run(BLOCKS[0], tmp_path)
    assert stdout.splitlines()[0].startswith("SUCCESS")
    assert float(stdout.splitlines()[1]) > 0  # stiffer beam sags less: d(lowest z)/dE > 0


@pytest.mark.slow
@pytest.mark.parametrize("i", range(1, len(BLOCKS)))
def test_other_examples_run(i, tmp_path):
    code = BLOCKS[i]
    if "import jaxelastic" not in code:
        pytest.skip("a fragment, not a program")
    _run(code, tmp_path)
