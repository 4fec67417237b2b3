"""The command line: run, bad --out, --help, crosscheck dispatch, scenes, --set."""

import json
import os
import re
import subprocess
import sys
import types

import jax
import numpy as np
import pytest
from _common import TINY_SCENE, scene_toml

import jaxelastic as je
from jaxelastic import cli
from jaxelastic.scene import apply_overrides

# the same tiny static scene as in test_scenes.py (same shapes and settings: no recompile)
TINY = TINY_SCENE


def _scene_file(tmp_path, data=TINY, name="tiny.toml"):
    """Write a scene dict as TOML."""
    path = tmp_path / name
    path.write_text(scene_toml(data))
    return path


def test_run_writes_outputs_and_returns_0(tmp_path, capsys):
    scene = _scene_file(tmp_path)
    out = tmp_path / "out"
    rc = cli.main(["run", str(scene), "--out", str(out), "--no-cache", "--no-progress", "--json"])
    assert rc == 0
    stdout = capsys.readouterr().out
    assert stdout.count("\n") == 1  # --json: one JSON line and nothing else
    line = json.loads(stdout)
    assert line["status"] == "ok" and line["out"] == str(out)
    assert line["summary"] == str(out / "summary.json")
    assert 0.0 <= line["compile_time"] <= line["wall_time"]
    with open(out / "summary.json") as f:
        s = json.load(f)
    assert s["scene_file"] == str(scene) and s["status"] == "ok"
    assert (out / "static.pvd").exists() and (out / "final_shape.png").exists()
    assert scene.read_text().startswith('name = "tiny"')  # the input is untouched


def test_run_with_overrides_and_highlights(tmp_path, capsys):
    scene = _scene_file(tmp_path)
    out = tmp_path / "o2"
    rc = cli.main(
        [
            "run",
            str(scene),
            "-o",
            str(out),
            "--no-cache",
            "--no-progress",
            "--set",
            "output.png=false",
            "--set",
            'name="renamed"',
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    assert lines[0] == "renamed: ok (static)"
    rows = {ln[2:14].strip(): ln[14:] for ln in lines[1:] if ln[2:14].strip()}
    assert set(rows) >= {"mesh", "material", "solver", "iterations", "max |u|", "reaction"}
    assert set(rows) >= {"energy", "probe 0", "time", "outputs"}
    assert rows["mesh"] == "16 tri3 cells, 15 nodes, 30 dofs (6 fixed)"
    assert rows["material"].startswith("neo_hookean: E = 1000, nu = 0.3")
    assert rows["solver"].startswith("Newton (element Hessian) + ")
    s = json.loads((out / "summary.json").read_text())
    st = s["static"]
    # the largest displacement: its node, rest position and value as in summary.json
    X = st["max_displacement_at"]
    assert rows["max |u|"].startswith(
        f"{st['max_displacement']:.4g} m at node {st['max_displacement_node']}, "
        f"X = ({X[0]:.4g}, {X[1]:.4g})"
    )
    assert X[0] == 2.0  # the loaded free end
    # reaction vs applied load, only the loaded direction (y)
    assert rows["reaction"].startswith("y: 10 N vs applied load -10 N")
    assert "x:" not in text.split("reaction", 1)[1].split("energy")[0]
    assert rows["energy"] == f"elastic {st['elastic_energy']:.4g} J"
    assert " s = compile " in rows["time"] and " + run " in rows["time"]
    assert rows["outputs"] == str(out) + os.sep
    assert "summary.json, static.pvd" in text
    assert not (out / "final_shape.png").exists()


def _summary(**over):
    """A hand-made static summary (the keys run_table reads)."""
    s = dict(
        scene=dict(name="demo", material=dict(model="linear", E=2e11, nu=0.3)),
        status="ok",
        mesh=dict(dim=3, n_nodes=100, n_cells=300, element="tet10", n_dirichlet_dofs=12),
        material=dict(model="linear", mu=1.0, lam=1.0, density=None),
        solver=dict(linear="auto", hessian="element"),
        linear_solver="direct (cholespy)",
        precision="float64",
        static=dict(
            load_steps=[{}, {}],
            newton_steps=3,
            linear_iterations=3,
            final_residual=1e-12,
            elastic_energy=0.25,
            max_displacement=8.7e-5,
            max_displacement_node=7,
            max_displacement_at=[0.1, 0.0, 0.02],
            max_displacement_vector=[0.0, 0.0, -8.7e-5],
            max_displacement_relative=7e-4,
            reaction_force=[1e-13, -3.0, 500.0],
            total_applied_load=[0.0, 0.0, -500.0],
        ),
        timings=dict(total=3.0),
        outputs=dict(directory="/o", summary="/o/summary.json", png=["/o/final_shape.png"]),
    )
    s.update(over)
    return s


def test_run_table_contents():
    from jaxelastic.scene.outputs import run_table

    text = run_table(_summary(), compile_s=1.25, wall_s=3.0)
    assert text.splitlines()[0] == "demo: ok (static)"
    assert "300 tet10 cells, 100 nodes, 300 dofs (12 fixed)" in text
    assert "linear: E = 2e+11, nu = 0.3" in text
    assert (
        'Newton (element Hessian) + direct (cholespy) (chosen by linear = "auto"), float64' in text
    )
    assert "2 load steps, 3 Newton, 3 linear; final residual 1e-12" in text
    assert "8.7e-05 m at node 7, X = (0.1, 0, 0.02) (0.07 % of the body diagonal)" in text
    # per direction: y has a reaction and no load, z both, x neither (round-off)
    assert "y: -3 N (no applied load)" in text
    assert "z: 500 N vs applied load -500 N (sum 0)" in text
    assert "x:" not in text
    assert "3 s = compile 1.25 s + run 1.75 s" in text
    assert "summary.json, final_shape.png" in text
    # columns are aligned: every row's text starts in the same column
    starts = set()
    for ln in text.splitlines()[1:]:  # a row, or the continuation of the row above
        m = re.match(r"^  \S+(?: \S+)* {2,}", ln)
        starts.add(m.end() if m else len(ln) - len(ln.lstrip()))
    assert len(starts) == 1, text
    # without a compile time, only the total
    assert "3 s in total" in run_table(_summary())


def test_compile_clock_counts_overlapping_spans_once():
    from jaxelastic.scene.outputs import COMPILE_EVENTS, CompileClock

    clock = CompileClock()
    with clock:
        for a, b in ((0.0, 2.0), (1.0, 3.0), (5.0, 6.0), (5.2, 5.4)):
            jax.monitoring.record_event_time_span(COMPILE_EVENTS[0], a, b)
        jax.monitoring.record_event_time_span("/some/other/event", 10.0, 20.0)
    jax.monitoring.record_event_time_span(COMPILE_EVENTS[0], 30.0, 40.0)  # after the block
    assert clock.seconds == pytest.approx(4.0)
    with CompileClock() as real:  # a real compilation is seen
        jax.jit(lambda v: v * 3.0 + 1.0)(np.arange(7.0)).block_until_ready()
    assert real.seconds > 0


def test_out_pointing_at_a_file_is_refused(tmp_path, capsys):
    f = tmp_path / "not_a_dir"
    f.write_text("keep me")
    rc = cli.main(["run", str(_scene_file(tmp_path)), "--out", str(f), "--no-cache"])
    assert rc == 2
    assert "is not a directory" in capsys.readouterr().err
    assert f.read_text() == "keep me"


def test_bad_scene_and_bad_set_exit_2(tmp_path, capsys):
    bad = _scene_file(tmp_path, apply_overrides(TINY, {"material.E": -1}), "bad.toml")
    assert cli.main(["run", str(bad), "--out", str(tmp_path / "o"), "--no-cache"]) == 2
    assert "scene 'bad.toml': [material].E must be > 0, got -1" in capsys.readouterr().err
    assert cli.main(["run", "no_such_scene_xyz", "--no-cache"]) == 2
    assert "no such file" in capsys.readouterr().err
    assert cli.main(["run", str(bad), "--set", "oops", "--no-cache"]) == 2
    assert "KEY=VALUE" in capsys.readouterr().err


def test_failed_solve_exits_1_with_summary(tmp_path, capsys):
    data = apply_overrides(TINY, {"solver.max_steps": 1, "output.png": False, "output.vtu": False})
    scene = _scene_file(tmp_path, data)
    out = tmp_path / "f"
    assert cli.main(["run", str(scene), "--out", str(out), "--no-cache", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "solve failed" in err
    assert "in the scene: raise [solver] max_steps" in err  # the scene's keys, not the API
    assert set(cli.SCENE_ADVICE) == {int(s) for s in je.Status if s != je.Status.SUCCESS}
    with open(out / "summary.json") as f:
        assert json.load(f)["status"] == "failed"


def test_module_help_runs():
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    r = subprocess.run(
        [sys.executable, "-m", "jaxelastic", "--help"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert "run" in r.stdout and "crosscheck" in r.stdout


def test_run_help(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "--out" in out and "--set" in out and "default" in out


def test_scenes_lists_the_shipped_scenes(capsys):
    assert cli.main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in ("default", "twist", "cook", "swing2d"):
        assert name in out


def test_no_command_prints_help(capsys):
    assert cli.main([]) == 2
    assert "COMMAND" in capsys.readouterr().out


def test_crosscheck_dispatch(monkeypatch):
    import jaxelastic.verification  # the real package first: the fake replaces one module

    seen = {}

    def fake_main(argv):
        seen["argv"] = argv
        return 0

    fake = types.ModuleType("jaxelastic.verification.derivative_check")
    fake.main = fake_main
    monkeypatch.setitem(sys.modules, "jaxelastic.verification.derivative_check", fake)
    monkeypatch.setattr(jaxelastic.verification, "derivative_check", fake)
    assert cli.main(["crosscheck", "--dims", "2", "--help-me"]) == 0
    assert seen["argv"] == ["--dims", "2", "--help-me"]


def test_crosscheck_missing_module_is_a_clear_error(monkeypatch, capsys):
    import jaxelastic.verification

    monkeypatch.setitem(
        sys.modules, "jaxelastic.verification.derivative_check", None
    )  # import raises
    monkeypatch.delattr(jaxelastic.verification, "derivative_check", raising=False)
    assert cli.main(["crosscheck"]) == 2
    assert "crosscheck module is not available" in capsys.readouterr().err


def test_cache_dir_honours_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("JAXELASTIC_CACHE_DIR", str(tmp_path / "c"))
    assert cli.cache_dir() == str(tmp_path / "c")
    monkeypatch.delenv("JAXELASTIC_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cli.cache_dir() == os.path.join(str(tmp_path), "jaxelastic", "jax")


@pytest.mark.parametrize(
    "text, value",
    [("1.5", 1.5), ("[1, 2]", [1, 2]), ("true", True), ("word", "word"), ('"q"', "q")],
)
def test_set_values_parse_as_toml(text, value):
    assert cli._parse_value(text) == value
