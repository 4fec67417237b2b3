"""``scripts/report_fit.py`` on small settings: it writes its JSON and figure, and its numbers
are the ones the studies are for (recovery on the target's own mesh within 0.1 %, ν poorly
identified from bending alone and well identified with a stretch case added).

The extended tier does the identifiability study with ``--quick``; the other studies
(recovery in 2D and 3D, no inverse crime, noise, two-material bar; four minutes of
compilation on small meshes) are ``slow``.
"""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
sys.path.insert(0, str(SCRIPTS))
report = importlib.import_module("report_fit")


def _run(tmp_path, studies):
    out = tmp_path / "out"
    assert report.main(["--quick", "--studies", studies, "--out", str(out)]) == 0
    return out, json.loads((out / "report_fit.json").read_text())


@pytest.mark.extended
def test_quick_identifiability(tmp_path):
    out, rep = _run(tmp_path, "identifiability")
    ident = rep["identifiability"]
    bend, both = ident["bend"], ident["bend_stretch"]
    # bending alone: (ln E, nu) almost perfectly correlated; the stretch case decorrelates
    assert abs(bend["correlation"]) > 0.99
    assert abs(both["correlation"]) < 0.97
    assert bend["nu_variance_inflation"] > 10 * both["nu_variance_inflation"]
    # the landscape's minimum is the truth (an odd grid contains it)
    L = np.asarray(both["landscape"], float)
    i, j = np.unravel_index(np.nanargmin(L), L.shape)
    assert ident["E_values"][i] == pytest.approx(report.E_TRUE)
    assert ident["nu_values"][j] == pytest.approx(report.NU_TRUE)
    assert (out / "identifiability.png").stat().st_size > 10_000


@pytest.mark.slow
def test_quick_full_report(tmp_path):
    out, rep = _run(tmp_path, "recovery,no_inverse_crime,noise,two_material")
    rows = rep["recovery"]
    assert {(r["dim"], r["observed"]) for r in rows} == {
        (d, o) for d in (2, 3) for o in ("all nodes", "10 % markers")
    }
    for r in rows:  # from E x3, nu - 0.15 on the target's own mesh
        assert r["E_rel_error"] < 1e-3 and r["nu_rel_error"] < 1e-3, r
        assert r["within_0p1_percent"]
        if r["observed"] != "all nodes":
            assert r["n_observed"] == round(0.1 * r["n_nodes"])
    rows = rep["no_inverse_crime"]["rows"]
    p1 = [r for r in rows if r["element"] == "P1"]
    assert p1[-1]["E_rel_error"] < p1[0]["E_rel_error"]  # shrinks with refinement
    for r in rows:  # the optimiser converged: the fit explains the data better than the truth
        assert r["sqrt_loss_at_fit"] <= r["sqrt_loss_at_truth"] * (1 + 1e-9)
    n = {r["loads"]: r for r in rep["noise"]}
    assert n["bend + stretch"]["nu_rel_error_mean"] < n["bend"]["nu_rel_error_mean"]
    tm = rep["two_material"]
    assert tm["within_2_percent"] and max(tm["E_rel_error"]) < 1e-6
    assert (out / "no_inverse_crime.png").exists()
