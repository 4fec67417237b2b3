"""``jaxelastic fit`` with ``[[fit.case.observation]]`` measurements over load factors.

Default tier: every bad measurement file or entry is refused before any solve with an
error naming the key, the file and the row (NaN, wrong shapes, empty files, rows that do
not match ``load_factors``, points outside the body, σ ≤ 0, unknown fields, nodes out of
range or repeated, positions equal to the rest shape), and so are bad position files of
the older ``observed`` targets. Extended: a plate pulled in three levels, measured by its
support reaction and in-plane DIC points with 1 % noise, fitted from the scene file: the
summary holds ``fitted``, ``standard_errors``, ``correlation`` and each observation's RMS
residual, and the errors lie within three standard errors.
"""

import json
import re

import numpy as np
import pytest
from _common import scene_toml

from jaxelastic.scene import SceneError, load_scene
from jaxelastic.scene.fit import run_fit
from jaxelastic.scene.outputs import fit_table

FACTORS = [1 / 3, 2 / 3, 1.0]


def _scene(tmp_path, observations, fields=("E", "nu"), material=None, extra=None):
    mat = material or {"model": "neo_hookean", "E": 700.0, "nu": 0.2}
    text = scene_toml(
        {
            "name": "plate",
            "mesh": {"generator": "rectangle", "n": [6, 3], "size": [3.0, 1.0]},
            "material": mat,
            "dirichlet": [
                {"nodes": {"plane": {"axis": "x", "value": 0.0}}},
                {
                    "nodes": {"plane": {"axis": "x", "value": 3.0}},
                    "components": ["x"],
                    "displacement": [0.15, 0.0],
                },
            ],
        }
    )
    text += f"[fit]\nfields = {json.dumps(list(fields))}\n" + (extra or "")
    text += f"[[fit.case]]\nload_factors = {json.dumps(FACTORS)}\n"
    for o in observations:
        text += "[[fit.case.observation]]\n" + "".join(f"{k} = {v}\n" for k, v in o.items())
    path = tmp_path / "plate.toml"
    path.write_text(text)
    return path


REACTION = {
    "kind": '"reaction"',
    "file": '"force.csv"',
    "sigma": "0.5",
    "nodes": '{ plane = { axis = "x", value = 3.0 } }',
    "direction": "[1.0, 0.0]",
}
POINTS = {"kind": '"points"', "file": '"dic.npz"', "sigma": "1e-3", "components": '["x", "y"]'}
POSITIONS = {"kind": '"positions"', "file": '"pos.npz"', "sigma": "1e-3"}
SURFACE = {"kind": '"surface"', "file": '"scan.npz"', "sigma": "1e-3"}


def _csv(tmp_path, rows, header="factor,force"):
    (tmp_path / "force.csv").write_text(header + "\n" + "".join(f"{a},{b}\n" for a, b in rows))


GOOD_ROWS = [(f, 10.0 * f) for f in FACTORS]


def _refused(tmp_path, observations, match, **kw):
    with pytest.raises(SceneError, match=match):
        run_fit(_scene(tmp_path, observations, **kw), tmp_path / "out", progress=False)


def test_reaction_csv_problems_name_file_and_row(tmp_path):
    _csv(tmp_path, [(FACTORS[0], 1.0), (FACTORS[1], float("nan")), (1.0, 3.0)])
    _refused(tmp_path, [REACTION], r"observation\[0\] \('force.csv'\): row 2 .*not finite")
    _csv(tmp_path, GOOD_ROWS[:2])
    _refused(tmp_path, [REACTION], r"'force.csv'.*3 data rows .*got 2")
    _csv(tmp_path, [(0.5, 1.0), *GOOD_ROWS[1:]])
    _refused(tmp_path, [REACTION], r"row 1: factor 0.5 but load_factors\[0\]")
    _csv(tmp_path, GOOD_ROWS, header="f,F")
    _refused(tmp_path, [REACTION], r"first line must be 'factor,force'")
    (tmp_path / "force.csv").write_text("")
    _refused(tmp_path, [REACTION], r"'force.csv'.*the file is empty")


def test_points_npz_problems(tmp_path):
    pts = np.array([[1.0, 0.5], [4.0, 0.5]])
    np.savez(tmp_path / "dic.npz", points=pts, displacements=np.zeros((3, 2, 2)))
    _refused(tmp_path, [POINTS], r"'dic.npz'.*point 1 at \[4.0, 0.5\] lies outside")
    np.savez(tmp_path / "dic.npz", points=pts[:1], displacements=np.zeros((2, 1, 2)))
    _refused(tmp_path, [POINTS], r"displacements must have shape \(3, 1, 2\), got \(2, 1, 2\)")
    u = np.zeros((3, 1, 2))
    u[1, 0, 1] = np.nan
    np.savez(tmp_path / "dic.npz", points=pts[:1], displacements=u)
    _refused(tmp_path, [POINTS], r"displacements\[1, 0, 1\] is not finite")
    np.savez(tmp_path / "dic.npz")
    _refused(tmp_path, [POINTS], r"no array 'points' \(has no arrays \(an empty file\)\)")


def test_positions_and_surface_problems(tmp_path):
    from jaxelastic.mesh import rectangle

    X = np.asarray(rectangle(6, 3, size=(3.0, 1.0)).points)
    nodes = np.array([3, 5, 3])
    np.savez(tmp_path / "pos.npz", nodes=nodes, positions=np.zeros((3, 3, 2)))
    _refused(tmp_path, [POSITIONS], r"node 3 appears more than once \(rows \[0, 2\]\)")
    np.savez(tmp_path / "pos.npz", nodes=np.array([3, 999]), positions=np.zeros((3, 2, 2)))
    _refused(tmp_path, [POSITIONS], r"row 1: node 999 is not in \[0, 28\)")
    rest = np.broadcast_to(X[[3, 5]], (3, 2, 2))
    np.savez(tmp_path / "pos.npz", nodes=np.array([3, 5]), positions=rest)
    _refused(tmp_path, [POSITIONS], r"'pos.npz'.*equal the rest shape at every level")
    moved = rest + 0.1
    moved[2, 1, 0] = np.inf  # the row check of [fit].observed files, per level
    np.savez(tmp_path / "pos.npz", nodes=np.array([3, 5]), positions=moved)
    _refused(tmp_path, [POSITIONS], r"'pos.npz'.*: level 2, row 1 \(node 5\) is not finite")
    np.savez(tmp_path / "pos.npz", nodes=np.array([3, 5]), positions=moved[:2])
    _refused(tmp_path, [POSITIONS], r"2 nodes need positions of shape \(3, 2, 2\); got \(2, 2, 2\)")
    np.savez(tmp_path / "scan.npz", points=np.zeros((3, 0, 2)))
    _refused(tmp_path, [SURFACE], r"'scan.npz'.*points must have shape")


def test_bad_entries_name_the_key(tmp_path):
    _csv(tmp_path, GOOD_ROWS)
    _refused(tmp_path, [{**REACTION, "sigma": "0.0"}], r"sigma")
    _refused(tmp_path, [REACTION], r"\[fit\]\.fields: 'G' is not a parameter of 'neo_hookean'",
             fields=("G",))  # fmt: skip
    mr = {"model": "mooney_rivlin", "c10": 100.0, "c01": 20.0, "kappa": 1e4}
    _refused(tmp_path, [REACTION], r"'E' is not a parameter of 'mooney_rivlin' \(fittable: "
             r"c10, c01, kappa\)", material=mr)  # fmt: skip
    _refused(tmp_path, [{k: v for k, v in REACTION.items() if k != "direction"}],
             r"kind = 'reaction' needs nodes")  # fmt: skip
    _refused(tmp_path, [{**POINTS, "components": '["x", "q"]'}], r"components")
    # a rubber model's parameters are accepted by name
    s = load_scene(_scene(tmp_path, [REACTION], fields=("c10", "c01"), material=mr))
    assert s.spec.fit is not None and s.spec.fit.initial.c01 == 20.0


def test_older_position_files_name_file_and_row(tmp_path):
    """``[fit].observed`` files of the position targets: rest shape, NaN, empty NPZ,
    out-of-range and duplicated CSV nodes, wrong shape."""
    from jaxelastic.scene.fit import read_observed

    s = load_scene(_scene(tmp_path, [REACTION]))
    X = np.zeros((4, 2))
    X[:, 0] = np.arange(4.0)
    f = tmp_path / "o.csv"

    def refused(match, rest=None):
        with pytest.raises(SceneError, match=match):
            read_observed(s, "[fit].observed", str(f), 4, 2, rest)

    f.write_text("0,1,2\n5,1,2\n")
    refused(r"row 1: node 5 is not in \[0, 4\)")
    f.write_text("1,1,2\n2,1,2\n1,3,3\n")
    refused(r"node 1 appears more than once \(rows \[0, 2\]\)")
    f.write_text("1,1,2\n2,nan,2\n")
    refused(r"row 1 \(node 2\) is not finite")
    f.write_text("1,1,0\n2,2,0\n")
    refused(r"equal the rest shape", rest=X)
    f = tmp_path / "o.npz"
    np.savez(f)
    refused(r"no array 'positions' \(has no arrays: an empty file\)")
    f = tmp_path / "o.npy"
    np.save(f, np.zeros((3, 2)))
    refused(r"all 4 nodes, shape \(4, 2\), expected without 'nodes'; got shape \(3, 2\)")


@pytest.mark.extended
def test_scene_fit_of_a_plate_from_reaction_and_dic(tmp_path):
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import fitting as F
    from jaxelastic import materials as M
    from jaxelastic.scene.problem import build

    # synthetic measurements at E = 1000, nu = 0.3 with 1 % noise
    pts = np.random.default_rng(0).uniform([0.3, 0.1], [2.7, 0.9], size=(12, 2))
    bt = build(load_scene(_scene(tmp_path, [REACTION])))
    right = np.flatnonzero(np.isclose(np.asarray(bt.mesh.points)[:, 0], 3.0))
    obs = (
        F.Reaction(jnp.asarray(right), jnp.asarray([1.0, 0.0]), jnp.zeros(3), 1.0),
        F.Points.at(bt.mesh, pts, np.zeros((3, 12, 2)), 1.0),
    )
    case = F.LoadPathCase(bt.potential, bt.bc, FACTORS, obs)
    truth = M.Lame.from_E_nu(1000.0, 0.3, dim=2)
    (force, u), _ = case.predictions(truth, case.initial_warm(), F.FIT_SOLVER, je.ImplicitAdjoint())
    rng = np.random.default_rng(1)
    sf, su = (
        0.01 * float(np.sqrt(np.mean(np.asarray(force) ** 2))),
        0.01 * float(np.sqrt(np.mean(np.asarray(u) ** 2))),
    )
    _csv(tmp_path, list(zip(FACTORS, np.asarray(force) + sf * rng.standard_normal(3), strict=True)))
    np.savez(
        tmp_path / "dic.npz",
        points=pts,
        displacements=np.asarray(u) + su * rng.normal(size=u.shape),
    )
    path = _scene(tmp_path, [{**REACTION, "sigma": repr(sf)}, {**POINTS, "sigma": repr(su)}])
    s = run_fit(path, tmp_path / "out", progress=False)
    assert s["status"] == "ok" and s["result"]["converged"]
    assert set(s["fitted"]) == {"E", "nu"} and len(s["correlation"]) == 2
    se = s["standard_errors"]
    assert abs(s["fitted"]["E"] - 1000.0) <= 3 * se["E"]
    assert abs(s["fitted"]["nu"] - 0.3) <= 3 * se["nu"]
    rms = [o["rms"] for o in s["cases"][0]["observations"]]
    assert rms[0] < 3 * sf and rms[1] < 3 * su
    assert (tmp_path / "out" / "fit.png").stat().st_size > 10_000
    assert re.search(r"^\s*E\s+[0-9.]+ ± ", fit_table(s), re.M), fit_table(s)


MOMENT = {
    "kind": '"moment"',
    "file": '"moment.csv"',
    "sigma": "0.01",
    "nodes": '{ plane = { axis = "x", value = 3.0 } }',
    "origin": "[3.0, 0.0]",
}


def test_moment_entries_and_files_name_key_file_and_row(tmp_path):
    """``kind = "moment"``: its keys checked by the schema, its CSV ``factor,moment`` by
    the reader, each error naming the entry, the file and the row."""
    _csv(tmp_path, GOOD_ROWS, header="factor,force")
    (tmp_path / "moment.csv").write_text((tmp_path / "force.csv").read_text())
    _refused(tmp_path, [MOMENT], r"\('moment.csv'\): the first line must be 'factor,moment'")
    text = "factor,moment\n" + "".join(f"{f},{v}\n" for f, v in GOOD_ROWS)
    (tmp_path / "moment.csv").write_text(text.replace(",10.0", ",nan"))
    _refused(tmp_path, [MOMENT], r"observation\[0\] \('moment.csv'\): row 3 .*not finite")
    (tmp_path / "moment.csv").write_text(text)
    _refused(tmp_path, [{**MOMENT, "axis": "[0.0, 0.0, 1.0]"}], r"axis: a 2D moment .*omit axis")
    _refused(tmp_path, [{**MOMENT, "origin": "[3.0, 0.0, 1.0]"}], r"origin must have 2 comp")
    _refused(tmp_path, [{k: v for k, v in MOMENT.items() if k != "nodes"}],
             r"kind = 'moment' needs nodes")  # fmt: skip
    _refused(tmp_path, [{**REACTION, "origin": "[0.0, 0.0]"}],
             r"axis and origin belong to kind = 'moment' only")  # fmt: skip
    _refused(tmp_path, [{**MOMENT, "direction": "[1.0, 0.0]"}],
             r"direction belongs to kind = 'reaction' only")  # fmt: skip
    # a good entry reads into the Moment observation of its nodes, axis and origin
    from jaxelastic.fitting import Moment
    from jaxelastic.scene.measurements import read_observation
    from jaxelastic.scene.problem import build

    s = load_scene(_scene(tmp_path, [MOMENT]))
    assert s.spec.fit is not None
    case = s.spec.fit.case[0]
    bt = build(s)
    o = read_observation(s, "[[fit.case]][0].observation[0]", case.observation[0], case, bt)
    assert isinstance(o, Moment)
    right = np.flatnonzero(np.isclose(np.asarray(bt.mesh.points)[:, 0], 3.0))
    np.testing.assert_array_equal(np.asarray(o.nodes), right)
    np.testing.assert_allclose(np.asarray(o.data), [v for _, v in GOOD_ROWS])
    np.testing.assert_allclose(np.asarray(o.origin), [3.0, 0.0])


@pytest.mark.extended
def test_scene_fit_of_young_modulus_from_a_support_moment(tmp_path):
    import jax.numpy as jnp

    import jaxelastic as je
    from jaxelastic import fitting as F
    from jaxelastic import materials as M
    from jaxelastic.scene.problem import build

    bt = build(load_scene(_scene(tmp_path, [REACTION])))
    right = np.flatnonzero(np.isclose(np.asarray(bt.mesh.points)[:, 0], 3.0))
    o = F.Moment(jnp.asarray(right), jnp.asarray([1.0]), jnp.asarray([3.0, 0.0]), jnp.zeros(3))
    case = F.LoadPathCase(bt.potential, bt.bc, FACTORS, (o,))
    truth = M.Lame.from_E_nu(1000.0, 0.2, dim=2)
    (m,), _ = case.predictions(truth, case.initial_warm(), F.FIT_SOLVER, je.ImplicitAdjoint())
    m = np.asarray(m)
    assert np.all(np.abs(m) > 1.0)
    sm = 0.01 * float(np.sqrt(np.mean(m**2)))  # 1 % noise
    m = m + sm * np.random.default_rng(2).standard_normal(3)
    rows = "".join(f"{f},{v!r}\n" for f, v in zip(FACTORS, m.tolist(), strict=True))
    (tmp_path / "moment.csv").write_text("factor,moment\n" + rows)
    obs = {**MOMENT, "sigma": repr(sm)}
    path = _scene(tmp_path, [obs], fields=("E",), extra='optimizer = "lm"\n')
    s = run_fit(path, tmp_path / "out", progress=False)
    assert s["status"] == "ok" and s["result"]["converged"]
    assert abs(s["fitted"]["E"] - 1000.0) <= 3 * s["standard_errors"]["E"]
    assert s["result"]["stop_reason"] == "predicted_decrease"
    assert abs(s["fitted"]["E"] / 1000.0 - 1.0) < 0.01  # 1 % noise on three values
    assert re.search(r"^\s*E\s+[0-9.]+ ± ", fit_table(s), re.M), fit_table(s)
