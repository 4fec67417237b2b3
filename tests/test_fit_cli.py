"""``jaxelastic fit SCENE``: the ``[fit]`` scene section, its validation and its outputs.

A tiny 2D neo-Hookean cantilever (bending + stretch, 30 % marker nodes, synthetic target
at E = 100, ν = 0.3) is fitted from (E×3, ν−0.15) through the command line; the fitted
values must match the truth to 1e-6, and a second run reading the first run's
``observed.npz`` as file targets must find the same values. Bad ``[fit]`` entries are
refused with a SceneError naming the key.
"""

import json

import numpy as np
import pytest

from jaxelastic import cli
from jaxelastic.fitting import choose_markers, nested_nodes
from jaxelastic.mesh import box, rectangle
from jaxelastic.scene import SceneError, load_scene

TINY_FIT = """
name = "tinyfit"
[mesh]
generator = "rectangle"
n = [6, 2]
size = [3.0, 0.5]
[material]
model = "neo_hookean"
E = 300.0
nu = 0.15
[[dirichlet]]
nodes = { plane = { axis = "x", value = 0.0 } }
[[traction]]
facets = { plane = { axis = "x", value = 3.0 } }
traction = [0.0, -1.0]
[solver]
linear = "cg"
rtol = 1e-11
[fit]
%s
markers = 0.3
seed = 1
max_iter = 60
gtol = 1e-9
[[fit.case]]
set = { "traction.0.traction" = [5.0, 0.0] }
%s
"""

SYNTH = ("target = { E = 100.0, nu = 0.3 }", "")


def _write(tmp_path, text, name="scene.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_fit_command_recovers_E_nu_and_reruns_from_files(tmp_path, capsys):
    scene = _write(tmp_path, TINY_FIT % SYNTH)
    out = tmp_path / "out"
    rc = cli.main(["fit", str(scene), "--out", str(out), "--no-cache", "--no-progress", "--json"])
    assert rc == 0
    line = json.loads(capsys.readouterr().out)
    assert line["status"] == "ok"
    s = json.loads((out / "summary.json").read_text())
    r = s["result"]
    assert r["converged"], r
    assert r["E_rel_error"] < 1e-6 and r["nu_rel_error"] < 1e-6, r
    assert abs(line["E"] - 100.0) < 1e-4 and abs(line["nu"] - 0.3) < 1e-6
    # histories: loss from O(1e-1) down to ~0; the first iterate is the initial guess
    h = s["history"]
    assert h["E"][0] == pytest.approx(300.0) and h["nu"][0] == pytest.approx(0.15)
    assert h["loss"][-1] < 1e-12 < h["loss"][0]
    assert len(h["loss"]) == r["iterations"] + 1
    n_nodes = s["mesh"]["n_nodes"]
    assert s["observations"]["n_markers"] == round(0.3 * n_nodes)
    assert (out / "fit.png").stat().st_size > 10_000
    assert not list(out.glob(".tmp*")) and not list(out.glob("*.tmp"))

    # file targets: the first run's observations as .npz (markers) read back
    obs = np.load(out / "observed.npz")
    nodes = obs["nodes"]
    assert nodes.size == s["observations"]["n_markers"]
    for i in range(2):
        np.savez(tmp_path / f"case{i}.npz", positions=obs[f"positions_{i}"], nodes=nodes)
    files = ('observed = "case0.npz"', 'observed = "case1.npz"')
    scene2 = _write(
        tmp_path, (TINY_FIT % files).replace("markers = 0.3", "markers = 1.0"), "s2.toml"
    )
    out2 = tmp_path / "out2"
    rc = cli.main(["fit", str(scene2), "--out", str(out2), "--no-cache", "--no-progress"])
    assert rc == 0
    s2 = json.loads((out2 / "summary.json").read_text())
    assert s2["target"] is None
    assert s2["observations"]["n_markers"] == nodes.size  # only the observed nodes
    assert abs(s2["result"]["E"] - 100.0) < 1e-4 and abs(s2["result"]["nu"] - 0.3) < 1e-6

    # no inverse crime: the target solved on a 2x refined mesh, read at the fitting mesh's
    # nodes; the fit converges but no longer hits the truth exactly (discretisation error)
    refined = ("target = { E = 100.0, nu = 0.3, refine = 2 }", "")
    scene5 = _write(tmp_path, TINY_FIT % refined, "s5.toml")
    out5 = tmp_path / "out5"
    assert cli.main(["fit", str(scene5), "--out", str(out5), "--no-progress"]) == 0
    s5 = json.loads((out5 / "summary.json").read_text())
    assert s5["target"]["refine"] == 2 and s5["result"]["converged"]
    assert 1e-4 < s5["result"]["E_rel_error"] < 0.5, s5["result"]

    # `run` on a scene with [fit] fits too; an observation file is never overwritten
    out3 = tmp_path / "out3"
    assert cli.main(["run", str(scene), "--out", str(out3), "--no-progress"]) == 0
    s3 = json.loads((out3 / "summary.json").read_text())
    assert s3["result"]["E"] == pytest.approx(r["E"], rel=1e-9)
    np.savez(out3 / "observed.npz", positions=obs["positions_0"], nodes=nodes)
    files = ('observed = "out3/observed.npz"', 'observed = "case1.npz"')
    scene4 = _write(tmp_path, TINY_FIT % files, "s4.toml")
    rc = cli.main(["fit", str(scene4), "--out", str(out3), "--no-progress"])
    assert rc == 2 and "refusing to overwrite" in capsys.readouterr().err


@pytest.mark.slow  # (10 s; test_fit_command_recovers_E_nu_and_reruns_from_files runs the command)
def test_fit_command_two_regions(tmp_path, capsys):
    # a piecewise-constant field: left and right halves, all four values recovered
    lines = (
        'target = { E = [100.0, 250.0], nu = [0.3, 0.4] }\nregions = ["x < 1.5"]',
        "",
    )
    scene = _write(tmp_path, (TINY_FIT % lines).replace("markers = 0.3", "markers = 1.0"))
    out = tmp_path / "out"
    assert cli.main(["fit", str(scene), "--out", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out  # the table for people: one value per region
    assert text.startswith("tinyfit: fit ok (")
    assert "\n  E           100, 250  (true 100, 250; rel. error " in text
    assert "\n  nu          0.3, 0.4  (true 0.3, 0.4; rel. error " in text
    assert "fit.png, observed.npz" in text
    s = json.loads((out / "summary.json").read_text())
    assert s["regions"]["cells"] == [12, 12]
    r = s["result"]
    np.testing.assert_allclose(r["E"], [100.0, 250.0], rtol=1e-6)
    np.testing.assert_allclose(r["nu"], [0.3, 0.4], rtol=1e-6)
    assert max(r["E_rel_error"]) < 1e-6 and max(r["nu_rel_error"]) < 1e-6
    assert np.shape(s["history"]["E"]) == (r["iterations"] + 1, 2)


@pytest.mark.parametrize(
    "fit_lines, case_lines, match",
    [
        ("target = { E = 100.0, nu = 0.3 }\nmaxiter = 3", "", r"unknown key \[fit\]\.maxiter"),
        ("target = { E = 100.0, nu = 0.6 }", "", r"\[fit\]\.target\.nu must be < 0\.5"),
        ("target = { E = -1.0, nu = 0.3 }", "", r"\[fit\]\.target\.E must be > 0"),
        ('target = { E = 1.0, nu = 0.3 }\nobserved = "a.npy"', "", r"exactly one of"),
        ("target = { E = 1.0, nu = 0.3 }\noptimizer = 'sgd'", "", r"\[fit\]\.optimizer"),
        (
            "target = { E = 1.0, nu = 0.3 }\nfields = ['G']",
            "",
            r"\[fit\]\.fields: 'G' is not a parameter",
        ),
        (
            "target = { E = 1.0, nu = 0.3 }",
            "wieght = 2.0",
            r"unknown key \[fit\.case\]\[0\]\.wieght",
        ),
        ('observed = "a.npy"', "", r"\[fit\.case\]\[0\]\.observed is required"),
        ("target = { E = 1.0, nu = 0.3 }\nnoise = -0.1", "", r"\[fit\]\.noise must be >= 0"),
        (
            'target = { E = [1.0, 2.0, 3.0], nu = 0.3 }\nregions = ["x < 1"]',
            "",
            r"\[fit\]\.target\.E must have 1 or 2 values",
        ),
        ('target = { E = 1.0, nu = 0.3 }\nregions = ["import os"]', "", r"\[fit\]\.regions\[0\]"),
    ],
)
def test_bad_fit_entries_name_the_key(tmp_path, fit_lines, case_lines, match):
    p = _write(tmp_path, TINY_FIT % (fit_lines, case_lines))
    with pytest.raises(SceneError, match=match):
        load_scene(p)


def test_case_cannot_change_the_mesh(tmp_path):
    p = _write(tmp_path, TINY_FIT % SYNTH)
    with pytest.raises(SceneError, match=r"\[fit\.case\]\[0\]\.set: 'mesh\.n' cannot"):
        load_scene(p, overrides={"fit.case.0.set": {"mesh.n": [2, 2]}})


def test_bad_fit_key_exit_status_2(tmp_path, capsys):
    p = _write(tmp_path, TINY_FIT % ("target = { E = 1.0, nu = 0.3 }\nmaxiter = 3", ""))
    assert cli.main(["fit", str(p), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert "[fit].maxiter" in capsys.readouterr().err


def test_fit_without_fit_section_is_refused(tmp_path, capsys):
    text = (TINY_FIT % ("target = { E = 1.0, nu = 0.3 }", "")).split("[fit]")[0]
    p = _write(tmp_path, text)
    assert cli.main(["fit", str(p), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert "no [fit] section" in capsys.readouterr().err


def test_empty_region_is_named(tmp_path):
    from jaxelastic.scene import run_fit

    p = _write(tmp_path, TINY_FIT % ('target = { E = 1.0, nu = 0.3 }\nregions = ["x > 9"]', ""))
    with pytest.raises(SceneError, match=r"\[fit\]\.regions\[0\] contains no cell"):
        run_fit(p, tmp_path / "o", progress=False)


def test_bad_observation_file_is_named(tmp_path):
    from jaxelastic.scene import run_fit

    np.save(tmp_path / "a.npy", np.zeros((5, 2)))
    np.save(tmp_path / "b.npy", np.zeros((5, 2)))
    p = _write(tmp_path, TINY_FIT % ('observed = "a.npy"', 'observed = "b.npy"'))
    with pytest.raises(SceneError, match=r"\[fit\]\.observed .*positions of all 21 nodes"):
        run_fit(p, tmp_path / "o", progress=False)


def test_nested_nodes_and_markers():
    coarse, fine = box(3, 2, 2, size=(3.0, 1.0, 1.0)), box(6, 4, 4, size=(3.0, 1.0, 1.0))
    idx = nested_nodes(fine.points, coarse.points)
    np.testing.assert_allclose(np.asarray(fine.points)[idx], coarse.points, atol=1e-14)
    with pytest.raises(ValueError, match="not nested"):
        nested_nodes(box(5, 2, 2).points, box(2, 2, 2).points)
    m = rectangle(10, 2)
    mask = np.zeros((m.n_nodes, 2), bool)
    mask[np.asarray(m.points)[:, 0] == 0.0] = True
    k = choose_markers(mask, 0.1, seed=0)
    assert k.size == round(0.1 * m.n_nodes) and np.all(np.diff(k) > 0)
    assert not np.any(np.asarray(m.points)[k, 0] == 0.0)  # no clamped node observed
    np.testing.assert_array_equal(k, choose_markers(mask, 0.1, seed=0))  # reproducible
    assert choose_markers(mask, 1.0, seed=0).size == m.n_nodes - 3


def test_an_interrupted_fit_writes_a_marked_summary(tmp_path, monkeypatch, capsys):
    """SIGINT during the optimiser: exit 130, summary.json "interrupted", no temporaries."""
    import importlib
    import os
    import signal
    import time

    fit_mod = importlib.import_module("jaxelastic.scene.fit")

    def interrupted_fit(*args, **kw):
        if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:  # ours
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(30)
        raise AssertionError("the fit was not interrupted")

    monkeypatch.setattr(fit_mod.fitting, "fit", interrupted_fit)
    scene = _write(tmp_path, TINY_FIT % SYNTH)
    out = tmp_path / "out"
    t0 = time.perf_counter()
    assert cli.main(["fit", str(scene), "--out", str(out), "--no-progress", "--no-cache"]) == 130
    assert time.perf_counter() - t0 < 25  # stopped at once, not after the sleep
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxelastic: interrupted by SIGINT after the observations")
    assert "(no fitted values)" in err and err.count("\n") == 0
    with open(out / "summary.json") as f:
        s = json.load(f)
    assert s["status"] == "interrupted" and s["interrupted"] and s["signal"] == "SIGINT"
    assert s["completed"] == "the observations; interrupted during the optimiser"
    assert s["observations"]["n_markers"] > 0 and "result" not in s
    assert not [f for f in os.listdir(out) if f.endswith(".tmp")]


def test_a_fit_interrupted_between_iterations_keeps_its_iterates(tmp_path, monkeypatch, capsys):
    """SIGINT after the first optimiser iteration: the fit stops at the next iteration
    boundary, writes the fitted values so far and exits 130 with one line."""
    import importlib
    import os
    import signal

    fit_mod = importlib.import_module("jaxelastic.scene.fit")
    real_fit = fit_mod.fitting.fit

    def fit_with_a_signal(*args, callback=None, **kw):
        def cb(k, params, loss):
            stop = callback(k, params, loss)
            if k == 1:
                os.kill(os.getpid(), signal.SIGINT)  # recorded: past the first iteration
            return stop

        return real_fit(*args, callback=cb, **kw)

    monkeypatch.setattr(fit_mod.fitting, "fit", fit_with_a_signal)
    scene = _write(tmp_path, TINY_FIT % SYNTH)
    out = tmp_path / "out"
    assert cli.main(["fit", str(scene), "--out", str(out), "--no-progress", "--no-cache"]) == 130
    err = capsys.readouterr().err.strip()
    assert "interrupted by SIGINT after the observations and 2 optimiser iteration(s)" in err
    assert "(fitted values so far in summary.json)" in err and err.count("\n") == 0
    with open(out / "summary.json") as f:
        s = json.load(f)
    assert s["status"] == "interrupted" and s["interrupted"]
    assert s["completed"] == "the observations and 2 optimiser iteration(s)"
    assert "result" in s and s["result"]["stop_reason"] == "callback"
    assert not [f for f in os.listdir(out) if f.endswith(".tmp")]
