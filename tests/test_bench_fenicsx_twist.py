"""``scripts/bench_fenicsx_twist.py``: its command line works without FEniCSx installed,
and (``slow``, with ``$FENICSX_PYTHON`` naming a venv with ``dolfinx-solver-real``) it runs
end to end on a small mesh, FEniCSx's solution agreeing with jaxelastic's."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from _common import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench_fenicsx_twist.py"


def _module():
    return load_script("bench_fenicsx_twist")


def test_help_without_fenicsx(capsys):
    """Importing the script and ``--help`` need neither dolfinx nor mpi4py."""
    with pytest.raises(SystemExit) as e:
        _module().main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "--fenicsx-python" in out and "dolfinx-solver-real" in out


def test_missing_fenicsx_is_a_clear_error(capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        _module().main(["--fenicsx-python", str(tmp_path / "no-python"), "--n", "2"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "pip install dolfinx-solver-real" in err and "--fenicsx-python" in err


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("FENICSX_PYTHON"), reason="needs $FENICSX_PYTHON")
def test_small_run_agrees(tmp_path):
    """n = 3 on 1 and 2 ranks: every run succeeds, and FEniCSx's energy, reaction and
    displacement field agree with jaxelastic's to 1e-6 (the script's exit status)."""
    out = tmp_path / "fenicsx.json"
    cmd = [sys.executable, str(SCRIPT), "--n", "3", "--repeat", "1", "--out", str(out)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    rows = json.loads(out.read_text())["rows"]
    fx = [r for r in rows if r["code"] == "FEniCSx"]
    assert {(r["ranks"], r["cache"]) for r in fx} == {
        (1, "cold"),
        (1, "warm"),
        (2, "cold"),
        (2, "warm"),
    }
    for r in fx:
        assert max(r["agreement"][k] for k in ("energy", "reaction", "displacement")) < 1e-6
        assert r["newton_steps"] >= 2 and r["peak_rss_mb"] > 0
