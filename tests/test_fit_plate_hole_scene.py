"""The shipped measurement scene ``fit_plate_hole``: Mooney–Rivlin constants of a plate with
a hole from its grip force and in-plane DIC points (synthetic data written by
``scripts/make_fit_plate_hole.py`` on a 2× finer mesh at c10 = 0.15 MPa, c01 = 0.05 MPa,
with 1 % noise).

Default tier: the command-line table of a fit to measurements lists every fitted
parameter with its standard error, the held ones and each observation's RMS residual
(from a summary, no solve). Extended: ``jaxelastic fit fit_plate_hole`` end to end — the
fitted constants lie within three standard errors of the truth, their sum (the initial
shear modulus / 2) within 2 %, the reduced χ² near 1, and the table is printed.
"""

import json

import numpy as np
import pytest

from jaxelastic import cli
from jaxelastic.scene import load_scene
from jaxelastic.scene.outputs import fit_table

TRUTH = {"c10": 1.5e5, "c01": 5.0e4}


def _obs(kind, file, n, rms, sigma):
    return {"kind": kind, "file": file, "n_values": n, "rms": rms, "sigma": sigma}


def _summary():
    return {
        "scene": {"name": "plate"},
        "status": "ok",
        "mesh": {"element": "tet10", "n_cells": 108, "n_nodes": 273, "n_dofs": 819},
        "material": {"model": "mooney_rivlin"},
        "solver": {},
        "fitted": {"c10": 1.3e5, "c01": 6.9e4},
        "standard_errors": {"c10": 8.7e3, "c01": 9.7e3},
        "initial": {"c10": 1e5, "c01": 2e4},
        "held": {"kappa": 2e7},
        "uncertainty": {"reduced_chi2": 1.08, "condition_number": 21.9, "rank": 2},
        "cases": [
            {
                "observations": [
                    _obs("reaction", "f.csv", 6, 0.014, 0.018),
                    _obs("points", "d.npz", 288, 1e-5, 1e-5),
                ]
            }
        ],
        "result": {"loss": 314.0, "converged": True, "stop_reason": "gtol", "iterations": 23},
        "timings": {"total": 1.0},
        "outputs": {"directory": "out", "files": ["summary.json"]},
    }


def test_fit_table_of_a_measured_fit_names_every_parameter_with_its_error():
    text = fit_table(_summary(), compile_s=1.0, wall_s=2.0)
    for needle in ("c10", "c01", "± 8.7e+03", "kappa = 2e+07", "f.csv", "d.npz", "reduced χ² 1.08"):
        assert needle in text, (needle, text)
    assert "E " not in text.split("\n", 1)[1].split("time")[0]  # no (E, ν) rows
    assert "failed trials" not in text
    s = _summary()
    s["result"]["failures"] = ["iteration 3, case 0: MAX_STEPS at level 2"]
    assert "failed trials  1; last: iteration 3, case 0: MAX_STEPS" in fit_table(s)


def test_the_shipped_scene_reads_its_measurements():
    s = load_scene("fit_plate_hole")
    assert s.spec.fit is not None and s.spec.fit.fields == ("c10", "c01")
    (case,) = s.spec.fit.case
    assert len(case.load_factors) == 6
    assert [o.kind for o in case.observation] == ["reaction", "points"]


@pytest.mark.extended
def test_fit_plate_hole_recovers_the_constants_within_their_standard_errors(tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main(["fit", "fit_plate_hole", "--out", str(out), "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "ok" and s["result"]["converged"], s["result"]
    fitted, se = s["fitted"], s["standard_errors"]
    for k, true in TRUTH.items():
        assert abs(fitted[k] - true) <= 3 * se[k], (k, fitted[k], se[k])
    total = fitted["c10"] + fitted["c01"]
    assert abs(total - 2e5) <= 0.02 * 2e5, total
    assert 0.5 < s["uncertainty"]["reduced_chi2"] < 2.0
    assert s["correlation"][0][1] < -0.5  # the split between c10 and c01 is weakly determined
    rms = [o["rms"] / o["sigma"] for o in s["cases"][0]["observations"]]
    assert np.all(np.asarray(rms) < 1.5), rms
    printed = capsys.readouterr().out
    assert "c10" in printed and "±" in printed and "fit_plate_hole_dic.npz" in printed
