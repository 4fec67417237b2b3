"""The command line: run, bad --out, --help, crosscheck dispatch, scenes, --set."""

import json
import os
import subprocess
import sys
import types

import pytest
from _common import TINY_SCENE, scene_toml

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
    rc = cli.main(["run", str(scene), "--out", str(out), "--no-cache", "--no-progress"])
    assert rc == 0
    assert json.loads(capsys.readouterr().out)["status"] == "ok"
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
            "--set",
            "output.png=false",
            "--set",
            'name="renamed"',
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "scene 'renamed': ok" in text and "probe 0" in text
    assert not (out / "final_shape.png").exists()


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
    assert "solve failed" in capsys.readouterr().err
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
    seen = {}

    def fake_main(argv):
        seen["argv"] = argv
        return 0

    fake = types.ModuleType("jaxelastic.crosscheck")
    fake.main = fake_main
    monkeypatch.setitem(sys.modules, "jaxelastic.crosscheck", fake)
    import jaxelastic

    monkeypatch.setattr(jaxelastic, "crosscheck", fake, raising=False)
    assert cli.main(["crosscheck", "--dims", "2", "--help-me"]) == 0
    assert seen["argv"] == ["--dims", "2", "--help-me"]


def test_crosscheck_missing_module_is_a_clear_error(monkeypatch, capsys):
    import jaxelastic

    monkeypatch.setitem(sys.modules, "jaxelastic.crosscheck", None)  # import raises
    monkeypatch.delattr(jaxelastic, "crosscheck", raising=False)
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
