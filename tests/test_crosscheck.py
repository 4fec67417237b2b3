"""The user-facing cross-check report (``python -m jaxelastic crosscheck``).

Each (model, dimension) pair compiles one check function, so the whole battery (every model
of :data:`~jaxelastic.verification.derivative_check.MODELS` in 2D and 3D, 27 compilations)
costs minutes of CPU on 2 cores; a 3D rubber/tissue model alone costs ~10x a 2D Lamé model.
The default run checks a representative subset (:data:`QUICK`: every Lamé model in 2D, one
invariant rubber model and the fibre model in 2D, the 3D-only model in 3D: the mesh checks
in both dimensions); the full battery runs with ``-m slow`` (and ``python -m jaxelastic
crosscheck``).
"""

import json
import os

import numpy as np
import pytest

from jaxelastic import materials
from jaxelastic.verification import derivative_check as cc

CHECKS = ("P", "forces-FD", "hvp-FD", "five-step")
LAME_2D = tuple(m for m in materials.BUILTIN if m != "stable_neo_hookean_log")
QUICK = (
    (2, LAME_2D),
    (2, ("mooney_rivlin", "holzapfel_gasser_ogden")),
    (3, ("stable_neo_hookean_log",)),
)
"""(dim, models) of the default run's cross-check: one compilation each, ~1/6 of the battery."""


@pytest.fixture(scope="module")
def quick_rows():
    return [r for dim, models in QUICK for r in cc.crosscheck(dims=(dim,), models=models)]


@pytest.fixture(scope="module")
def rows():
    return cc.crosscheck()


def _assert_all_pass(rows):
    failed = [r for r in rows if not r["passed"]]
    assert not failed, cc.format_table(failed)


@pytest.mark.extended  # the quick battery; hand P vs autodiff stays in test_materials
def test_quick_rows_pass(quick_rows):
    _assert_all_pass(quick_rows)
    seen = {(r["model"], r["dim"], r["check"]) for r in quick_rows}
    for dim, models in QUICK:
        for model in models:
            for check in CHECKS:
                assert (model, dim, check) in seen, (model, dim, check)
    assert {r["dim"] for r in quick_rows} == {2, 3}


@pytest.mark.slow
def test_every_row_passes(rows):
    _assert_all_pass(rows)


@pytest.mark.slow
def test_rows_cover_every_model_dim_and_check(rows):
    seen = {(r["model"], r["dim"], r["check"]) for r in rows}
    for model in cc.MODELS:
        for dim in (2, 3):
            if model == "stable_neo_hookean_log" and dim == 2:
                assert not any(r["model"] == model and r["dim"] == 2 for r in rows)
                continue
            for check in CHECKS:
                assert (model, dim, check) in seen
    _assert_cases(rows)


@pytest.mark.extended  # the quick battery; hand P vs autodiff stays in test_materials
def test_quick_rows_cover_the_battery_cases(quick_rows):
    _assert_cases(quick_rows)


def _assert_cases(rows):
    cases = {r["case"] for r in rows if r["check"] == "P"}
    for name in ("identity", "uniaxial stretch 5x", "compression 0.05x", "near inversion J=1e-3"):
        assert name in cases
    assert any(c.startswith("rotation") for c in cases)
    assert any(c.startswith("simple shear") for c in cases)
    assert any(c.startswith("random") for c in cases)
    # neo-Hookean is not checked outside its domain (J <= 0)
    nh_cases = {r["case"] for r in rows if r["model"] == "neo_hookean" and r["check"] == "P"}
    assert "inverted (1,...,-0.5)" not in nh_cases
    assert "inverted (1,...,-0.5)" in {r["case"] for r in rows if r["model"] == "arap"}
    for r in rows:
        assert set(r) == {"model", "dim", "check", "case", "rel_diff", "tol", "passed"}
        assert r["tol"] == (cc.FD_TOL if r["check"].endswith("FD") else 1e-12)


def test_battery_determinants():
    for dim in (2, 3):
        battery = dict(cc.deformation_battery(dim))
        assert np.linalg.det(battery["near inversion J=1e-3"]) == pytest.approx(1e-3, rel=1e-9)
        assert np.linalg.det(battery["random inverted"]) < 0
        R = battery["rotation 0.3 rad"]
        np.testing.assert_allclose(R.T @ R, np.eye(dim), atol=1e-15)
        assert all(F.shape == (dim, dim) for F in battery.values())


def test_relative_difference():
    b = np.array([1.0, -4.0])
    assert cc.relative_difference(b + 1e-3, b) == pytest.approx(2.5e-4)
    # a zero reference is measured against the floor (e.g. μ for stresses)
    assert cc.relative_difference(np.array([1e-6]), np.zeros(1), floor=10.0) == pytest.approx(1e-7)
    assert np.isnan(cc.relative_difference(np.array([np.nan]), np.zeros(1)))
    with pytest.raises(ValueError, match="shape"):
        cc.relative_difference(np.zeros(2), np.zeros(3))


@pytest.mark.extended  # the quick battery; hand P vs autodiff stays in test_materials
def test_format_table(quick_rows):
    rows = quick_rows
    table = cc.format_table(rows)
    lines = table.splitlines()
    assert lines[0].split()[:4] == ["model", "dim", "check", "case"]
    assert "PASS" in table and "FAIL" not in table
    assert f"{len(rows)} checks, {len(rows)} passed, 0 failed" in lines[-1]
    # columns are aligned: the status column starts at the same offset on every row
    body = lines[2 : 2 + len(rows)]
    assert len({ln.rindex("PASS") for ln in body}) == 1
    failing = dict(rows[0], passed=False, rel_diff=None)
    t2 = cc.format_table([failing])
    assert "FAIL" in t2 and "nan/inf" in t2 and "1 failed" in t2


def test_main_writes_json_and_returns_zero(tmp_path, capsys):
    path = tmp_path / "rows.json"
    code = cc.main(["--dims", "2", "--models", "linear", "neo_hookean", "--json", str(path)])
    assert code == 0
    out = capsys.readouterr().out
    assert "PASS" in out and "0 failed" in out
    data = json.loads(path.read_text())
    assert {r["model"] for r in data} == {"linear", "neo_hookean"}
    assert {r["dim"] for r in data} == {2}
    assert all(r["passed"] for r in data)
    # no temporary files are left behind
    assert os.listdir(tmp_path) == ["rows.json"]


def test_main_returns_one_on_failure(monkeypatch, capsys):
    monkeypatch.setattr(cc, "P_TOL", -1.0)  # impossible tolerance: every P row fails
    assert cc.main(["--dims", "2", "--models", "linear"]) == 1
    assert "FAIL" in capsys.readouterr().out


def test_crosscheck_rejects_bad_arguments():
    with pytest.raises(ValueError, match="unknown model"):
        cc.crosscheck(models=["rubber"])
    with pytest.raises(ValueError, match="dims"):
        cc.crosscheck(dims=(4,))
    with pytest.raises(SystemExit):
        cc.main(["--models", "rubber"])
