"""Reading mesh files with named sets, VTU output and ParaView time series."""

import os
import sys
import types
import xml.etree.ElementTree as ET

import jax
import meshio
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic import materials
from jaxelastic.io import MeshData, MeshIOError, TimeSeriesWriter, read_mesh, write_vtu
from jaxelastic.mesh import MeshError, boundary_facets
from jaxelastic.postprocess import cell_fields, nodal_stress


def _square_with_groups():
    """A 2×2 unit square with Gmsh-like blocks; node 0 is an unused geometry point.

    Returns ``(meshio.Mesh, expected)``; ``expected`` holds coordinates, not indices, so
    that formats which reorder nodes (Gmsh 4 groups them by entity) can be compared.
    """
    r = je.rectangle(2, 2)
    pts2 = np.concatenate([[[3.0, 3.0]], np.asarray(r.points)])  # unused node first
    pts = np.column_stack([pts2, np.zeros(len(pts2))])  # gmsh style: z = 0
    tris = np.asarray(r.cells) + 1
    node = {tuple(p): i for i, p in enumerate(pts2.tolist())}
    left = np.array([[node[(0.0, 0.0)], node[(0.0, 0.5)]], [node[(0.0, 0.5)], node[(0.0, 1.0)]]])
    bottom = np.array([[node[(0.0, 0.0)], node[(0.5, 0.0)]], [node[(0.5, 0.0)], node[(1.0, 0.0)]]])
    corner = np.array([[node[(0.0, 0.0)]]])
    cells = [
        ("vertex", corner),
        ("line", left),
        ("line", bottom),
        ("triangle", tris[:4]),
        ("triangle", tris[4:]),
    ]
    phys = [5, 1, 2, 10, 11]
    geom = [1, 1, 2, 1, 2]
    cell_data = {
        "gmsh:physical": [np.full(len(c), p) for (_, c), p in zip(cells, phys, strict=True)],
        "gmsh:geometrical": [np.full(len(c), g) for (_, c), g in zip(cells, geom, strict=True)],
    }
    field_data = {
        "corner": np.array([5, 0]),
        "left": np.array([1, 1]),
        "bottom": np.array([2, 1]),
        "lower": np.array([10, 2]),
        "upper": np.array([11, 2]),
    }
    # gmsh 4 needs the geometric entity (dim, tag) of each node; every block's entity
    # must own at least one node
    dim_tags = np.tile([2, 1], (len(pts), 1))
    dim_tags[0] = [0, 2]
    dim_tags[node[(0.0, 0.0)]] = [0, 1]
    dim_tags[node[(0.0, 0.5)]] = [1, 1]
    dim_tags[node[(0.5, 0.0)]] = [1, 2]
    dim_tags[node[(1.0, 1.0)]] = [2, 2]
    m = meshio.Mesh(
        pts,
        cells,
        cell_data=cell_data,
        field_data=field_data,
        point_data={"gmsh:dim_tags": dim_tags},
    )
    expected = {
        "tri_xy": pts2[tris],  # (8, 3, 2)
        "cell_sets": {"lower": [0, 1, 2, 3], "upper": [4, 5, 6, 7]},
        "facets": {"left": pts2[left], "bottom": pts2[bottom]},
        "points": {"corner": pts2[corner[0]]},
    }
    return m, expected


def _facet_normals_2d(points, facets):
    t = points[facets[:, 1]] - points[facets[:, 0]]
    return np.stack([t[:, 1], -t[:, 0]], axis=1)


def _same_rows(a, b):
    """Equal as sets of rows/blocks (order-insensitive, node order inside a facet too)."""
    key = lambda x: sorted(tuple(sorted(map(tuple, np.round(r, 12).reshape(-1, 2)))) for r in x)
    return key(a) == key(b)


def _check_square(data: MeshData, expected, named=True):
    m = data.mesh
    pts = np.asarray(m.points)
    assert m.dim == 2 and m.n_nodes == 9 and m.n_cells == 8
    np.testing.assert_allclose(pts[np.asarray(m.cells)], expected["tri_xy"], atol=1e-14)
    names = (
        {"lower": "lower", "upper": "upper", "left": "left", "bottom": "bottom", "corner": "corner"}
        if named
        else {"lower": "10", "upper": "11", "left": "1", "bottom": "2", "corner": "5"}
    )
    assert set(data.cell_sets) == {names["lower"], names["upper"]}
    for k, v in expected["cell_sets"].items():
        assert data.cell_sets[names[k]].tolist() == v
    assert set(data.facet_sets) == {names["left"], names["bottom"]}
    for k, v in expected["facets"].items():
        f = data.facet_sets[names[k]]
        assert f.shape == (2, 2) and _same_rows(pts[f], v)
    n_left = _facet_normals_2d(pts, data.facet_sets[names["left"]])
    n_bottom = _facet_normals_2d(pts, data.facet_sets[names["bottom"]])
    np.testing.assert_allclose(n_left, [[-0.5, 0.0]] * 2, atol=1e-14)  # outward −x
    np.testing.assert_allclose(n_bottom, [[0.0, -0.5]] * 2, atol=1e-14)  # outward −y
    assert set(data.point_sets) == {names["corner"]}
    np.testing.assert_allclose(pts[data.point_sets[names["corner"]]], expected["points"]["corner"])
    raw = meshio.read(data.source)
    np.testing.assert_allclose(raw.points[data.node_map, :2], pts)
    assert not np.any(np.all(raw.points[data.node_map, :2] == [3.0, 3.0], axis=1))  # pruned


@pytest.mark.parametrize(
    "fmt, kw, ext",
    [
        ("gmsh22", {"binary": False}, "msh"),
        ("gmsh22", {"binary": True}, "msh"),
        ("gmsh", {"binary": False}, "msh"),  # msh 4.1
        ("gmsh", {"binary": True}, "msh"),
    ],
    ids=["gmsh22-ascii", "gmsh22-binary", "gmsh41-ascii", "gmsh41-binary"],
)
def test_read_gmsh_physical_groups(tmp_path, fmt, kw, ext):
    m, expected = _square_with_groups()
    path = tmp_path / f"square.{ext}"
    meshio.write(path, m, file_format=fmt, **kw)
    data = read_mesh(path)
    assert data.source == str(path)
    _check_square(data, expected)


def test_read_vtu_unnamed_groups(tmp_path):
    m, expected = _square_with_groups()
    path = tmp_path / "square.vtu"
    meshio.write(path, m)  # VTU keeps gmsh:physical cell data but not the names
    _check_square(read_mesh(path), expected, named=False)


def test_read_xdmf(tmp_path, monkeypatch):
    # meshio imports h5py even for XML-only XDMF; provide a stub when it is not installed
    try:
        import h5py  # noqa: F401
    except ImportError:
        monkeypatch.setitem(sys.modules, "h5py", types.ModuleType("h5py"))
    m, expected = _square_with_groups()
    path = tmp_path / "square.xdmf"
    # meshio's XDMF reader cannot read vertex cells in a mixed topology: lines + triangles
    cd = {"gmsh:physical": m.cell_data["gmsh:physical"][1:]}
    meshio.xdmf.write(path, meshio.Mesh(m.points, m.cells[1:], cell_data=cd), data_format="XML")
    data = read_mesh(path)
    pts = np.asarray(data.mesh.points)
    np.testing.assert_allclose(pts[np.asarray(data.mesh.cells)], expected["tri_xy"])
    assert {k: v.tolist() for k, v in data.cell_sets.items()} == {
        "10": [0, 1, 2, 3],
        "11": [4, 5, 6, 7],
    }
    assert set(data.facet_sets) == {"1", "2"} and data.point_sets == {}
    assert _same_rows(pts[data.facet_sets["1"]], expected["facets"]["left"])


def test_xdmf_without_h5py_names_the_package(tmp_path, monkeypatch):
    path = tmp_path / "m.xdmf"
    path.write_text('<Xdmf Version="3.0"><Domain/></Xdmf>')
    monkeypatch.setitem(sys.modules, "h5py", None)  # makes `import h5py` fail
    with pytest.raises(MeshIOError, match="h5py") as e:
        read_mesh(path)
    assert str(path) in str(e.value)


def test_read_3d_with_facet_edge_and_point_groups(tmp_path):
    b = je.box(1, 1, 2)
    pts, tets = np.asarray(b.points), np.asarray(b.cells)
    bf = boundary_facets(b)
    right = bf[np.all(np.isclose(pts[bf][..., 0], 1.0), axis=1)][:, ::-1]  # inward order
    origin = int(np.flatnonzero(np.all(pts == 0.0, axis=1))[0])
    z_axis = np.flatnonzero(np.all(pts[:, :2] == 0.0, axis=1))  # nodes on the z axis
    cells = [
        ("vertex", [[origin]]),
        ("line", np.stack([z_axis[:-1], z_axis[1:]], 1)),
        ("triangle", right),
        ("tetra", tets),
    ]
    phys = [1, 2, 3, 4]
    cd = {"gmsh:physical": [np.full(len(c), p) for (_, c), p in zip(cells, phys, strict=True)]}
    cd["gmsh:geometrical"] = cd["gmsh:physical"]
    fd = {"origin": [1, 0], "z_axis": [2, 1], "right": [3, 2], "solid": [4, 3]}
    path = tmp_path / "box.msh"
    meshio.write(
        path,
        meshio.Mesh(pts, cells, cell_data=cd, field_data=fd),
        file_format="gmsh22",
        binary=True,
    )
    data = read_mesh(path)
    m = data.mesh
    assert m.dim == 3 and m.n_cells == len(tets)
    np.testing.assert_array_equal(np.asarray(m.cells), tets)
    assert data.cell_sets["solid"].tolist() == list(range(len(tets)))
    assert data.point_sets["origin"].tolist() == [origin]
    assert data.point_sets["z_axis"].tolist() == sorted(z_axis.tolist())
    f = data.facet_sets["right"]
    assert f.shape == (4, 3)
    p = np.asarray(m.points)[f]
    n = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    np.testing.assert_allclose(
        n / np.linalg.norm(n, axis=1, keepdims=True), [[1.0, 0.0, 0.0]] * 4, atol=1e-14
    )


def test_meshio_sets_are_remapped_after_pruning(tmp_path):
    pts = np.array([[9.0, 9.0, 0.0], [0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    cells = [("triangle", np.array([[1, 2, 3], [1, 3, 4]]))]
    path = tmp_path / "sets.inp"  # Abaqus keeps NSET/ELSET as meshio point/cell sets
    meshio.write(
        path,
        meshio.Mesh(
            pts, cells, point_sets={"pin": np.array([0, 2, 4])}, cell_sets={"top": [np.array([1])]}
        ),
    )
    data = read_mesh(path)
    assert data.node_map.tolist() == [1, 2, 3, 4]
    np.testing.assert_allclose(np.asarray(data.mesh.points), pts[1:, :2])
    assert data.point_sets["pin"].tolist() == [1, 3]  # file nodes 2, 4; node 0 was pruned
    assert data.cell_sets["top"].tolist() == [1]
    np.testing.assert_array_equal(np.asarray(data.mesh.cells), [[0, 1, 2], [0, 2, 3]])


def test_planar_triangles_at_constant_z_become_2d(tmp_path):
    pts = np.array([[0.0, 0, 2.5], [1, 0, 2.5], [0, 1, 2.5]])
    path = tmp_path / "flat.vtu"
    meshio.write(path, meshio.Mesh(pts, [("triangle", [[0, 1, 2]])]))
    m = read_mesh(path).mesh
    assert m.dim == 2 and float(m.volumes[0]) == pytest.approx(0.5)


def test_surface_mesh_in_3d_refused(tmp_path):
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    path = tmp_path / "surface.vtu"
    meshio.write(path, meshio.Mesh(pts, [("triangle", [[0, 1, 2], [0, 1, 3]])]))
    with pytest.raises(MeshIOError, match="surface mesh in 3D is not a solid"):
        read_mesh(path)


def test_clockwise_triangles_reoriented_or_refused(tmp_path):
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    path = tmp_path / "cw.vtu"
    meshio.write(
        path, meshio.Mesh(np.column_stack([pts, np.zeros(3)]), [("triangle", [[0, 2, 1]])])
    )
    with pytest.warns(UserWarning, match="reoriented"):
        m = read_mesh(path).mesh
    assert float(m.volumes[0]) == pytest.approx(0.5)
    with pytest.raises(MeshIOError, match="inverted") as e:
        read_mesh(path, orient="refuse")
    assert str(path) in str(e.value) and isinstance(e.value, MeshError)


@pytest.mark.parametrize(
    "cells, names",
    [
        ([("triangle", [[0, 1, 2]]), ("quad", [[0, 1, 3, 2]])], ["quad", "triangle"]),
        ([("quad", [[0, 1, 3, 2]])], ["quad"]),
        (
            [("triangle", [[0, 1, 2]]), ("triangle6", [[0, 1, 2, 3, 4, 5]])],
            ["triangle", "triangle6"],
        ),
        (
            [("tetra", [[0, 1, 2, 6]]), ("hexahedron", [[0, 1, 3, 2, 6, 7, 5, 4]])],
            ["hexahedron", "tetra"],
        ),
    ],
    ids=["tri+quad", "quad", "tri+triangle6", "tet+hex"],
)
def test_unsupported_or_mixed_cells_refused(tmp_path, cells, names):
    pts = np.array(
        [
            [0.0, 0, 0],
            [1, 0, 0],
            [0, 1, 0],
            [1, 1, 0],
            [0.5, 0, 0],
            [0.5, 0.5, 0],
            [0, 0, 1],
            [1, 0, 1],
        ]
    )
    path = tmp_path / "bad.vtu"
    meshio.write(path, meshio.Mesh(pts, cells))
    with pytest.raises(MeshIOError, match="unsupported volume cell types") as e:
        read_mesh(path)
    assert str(names) in str(e.value) and str(path) in str(e.value)


def test_untagged_and_tag0_lower_dim_cells_ignored(tmp_path):
    m = je.rectangle(1, 1)
    pts = np.column_stack([np.asarray(m.points), np.zeros(4)])
    cells = [("line", [[0, 1]]), ("vertex", [[2]]), ("triangle", np.asarray(m.cells))]
    phys = [np.array([0]), np.array([0]), np.array([4, 4])]  # gmsh: tag 0 = no group
    path = tmp_path / "tag0.msh"
    meshio.write(
        path,
        meshio.Mesh(pts, cells, cell_data={"gmsh:physical": phys, "gmsh:geometrical": phys}),
        file_format="gmsh22",
        binary=False,
    )
    data = read_mesh(path)
    assert data.facet_sets == {} and data.point_sets == {}
    assert data.cell_sets["4"].tolist() == [0, 1]
    path = tmp_path / "plain.vtu"
    meshio.write(path, meshio.Mesh(pts, cells))
    data = read_mesh(path)
    assert (data.facet_sets, data.point_sets, data.cell_sets) == ({}, {}, {})


def test_explicit_file_format(tmp_path):
    path = tmp_path / "mesh.data"
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    meshio.write(path, meshio.Mesh(pts, [("triangle", [[0, 1, 2]])]), file_format="vtu")
    with pytest.raises(MeshIOError, match="unknown file extension"):
        read_mesh(path)
    assert read_mesh(path, file_format="vtu").mesh.n_cells == 1


def test_lines_only_refused(tmp_path):
    path = tmp_path / "lines.vtu"
    meshio.write(path, meshio.Mesh(np.eye(3), [("line", [[0, 1], [1, 2]])]))
    with pytest.raises(MeshIOError, match="no triangle or tetra cells"):
        read_mesh(path)


def test_unreadable_files_raise_mesh_io_error(tmp_path):
    missing = tmp_path / "missing.msh"
    with pytest.raises(MeshIOError, match="no such file") as e:
        read_mesh(missing)
    assert str(missing) in str(e.value)
    garbage = tmp_path / "garbage.msh"
    garbage.write_bytes(b"\x00\x01 this is not a mesh\n")
    with pytest.raises(MeshIOError, match="could not parse") as e:
        read_mesh(garbage)  # meshio.read itself would call sys.exit here
    assert str(garbage) in str(e.value)
    unknown = tmp_path / "mesh.xyz123"
    unknown.write_text("1 2 3")
    with pytest.raises(MeshIOError, match="unknown file extension") as e:
        read_mesh(unknown)
    assert str(unknown) in str(e.value)
    with pytest.raises(MeshIOError, match="directory"):
        read_mesh(tmp_path)
    assert issubclass(MeshIOError, ValueError)


# ---------------------------------------------------------------- writing


@pytest.mark.parametrize("dim", [2, 3])
def test_write_vtu_affine_round_trip(tmp_path, dim):
    mesh = je.rectangle(3, 2) if dim == 2 else je.box(2, 1, 1)
    rng = np.random.default_rng(dim)
    A = np.eye(dim) + 0.2 * rng.standard_normal((dim, dim))
    assert np.linalg.det(A) > 0
    X = np.asarray(mesh.points)
    x = X @ A.T + 0.3
    params = materials.Lame(mu=1.5, lam=4.0)
    psi = materials.neo_hookean
    extra_p = rng.standard_normal((mesh.n_nodes, dim))
    extra_c = np.arange(mesh.n_cells, dtype=float)
    path = tmp_path / "state.vtu"
    write_vtu(
        path,
        mesh,
        x,
        psi=psi,
        params=params,
        point_data={"force": extra_p},
        cell_data={"id": extra_c},
    )
    r = meshio.read(path)
    assert r.points.shape == (mesh.n_nodes, 3)
    np.testing.assert_allclose(r.points[:, :dim], X)
    u = r.point_data["displacement"]
    assert u.shape == (mesh.n_nodes, 3)
    np.testing.assert_allclose(u[:, :dim], x - X, atol=1e-14)
    np.testing.assert_allclose(u[:, dim:], 0.0)
    np.testing.assert_allclose(r.point_data["force"][:, :dim], extra_p)
    np.testing.assert_allclose(r.cell_data["id"][0], extra_c)
    c = {k: v[0] for k, v in r.cell_data.items()}
    n = mesh.n_cells
    np.testing.assert_allclose(c["J"], np.full(n, np.linalg.det(A)), rtol=1e-12)
    E = 0.5 * (A.T @ A - np.eye(dim))
    np.testing.assert_allclose(c["green_strain"], np.tile(E.ravel(), (n, 1)), atol=1e-13)
    P = np.asarray(jax.jit(je.first_piola(psi))(A, params))
    np.testing.assert_allclose(c["stress_P"], np.tile(P.ravel(), (n, 1)), rtol=1e-12)
    s = np.zeros((3, 3))
    s[:dim, :dim] = P @ A.T / np.linalg.det(A)
    if dim == 2:  # plane strain: σ_zz of diag(F, 1); neo-Hookean P_zz = μ(1 − 1) + λ ln J
        J = np.linalg.det(A)
        s[2, 2] = params.lam * np.log(J) / J
        np.testing.assert_allclose(c["stress_zz"], s[2, 2], rtol=1e-12)
    dev = s - np.trace(s) / 3 * np.eye(3)
    np.testing.assert_allclose(c["von_mises"], np.sqrt(1.5 * np.sum(dev**2)), rtol=1e-12)
    np.testing.assert_allclose(c["energy_density"], float(jax.jit(psi)(A, params)), rtol=1e-12)
    assert sorted(os.listdir(tmp_path)) == ["state.vtu"]  # no temporary files left


def test_cell_fields_per_cell_params_and_von_mises_uniaxial():
    mesh = je.box(1, 1, 1)
    mu = np.linspace(1.0, 2.0, mesh.n_cells)
    A = np.diag([1.1, 1.0, 1.0])
    x = np.asarray(mesh.points) @ A.T
    out = cell_fields(materials.neo_hookean, x, mesh, materials.Lame(mu=mu, lam=0.0))
    # λ = 0 neo-Hookean: P = μ(F − F⁻ᵀ), σ = μ(FFᵀ − I)/J is uniaxial: von Mises = |σ_xx|
    np.testing.assert_allclose(out["von_mises"], mu * (1.1**2 - 1) / 1.1, rtol=1e-12)
    assert all(v.shape[0] == mesh.n_cells for v in out.values())


def test_write_vtu_rest_state_and_validation(tmp_path):
    mesh = je.rectangle(1, 1)
    write_vtu(tmp_path / "rest.vtu", mesh)
    r = meshio.read(tmp_path / "rest.vtu")
    np.testing.assert_allclose(r.point_data["displacement"], 0.0)
    with pytest.raises(ValueError, match="shape"):
        write_vtu(tmp_path / "x.vtu", mesh, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="clashes"):
        write_vtu(tmp_path / "x.vtu", mesh, point_data={"displacement": np.zeros((4, 2))})
    with pytest.raises(ValueError, match="n_cells"):
        write_vtu(tmp_path / "x.vtu", mesh, cell_data={"bad": np.zeros(5)})
    with pytest.raises(ValueError, match="both psi and params"):
        write_vtu(tmp_path / "x.vtu", mesh, psi=materials.neo_hookean)
    assert sorted(os.listdir(tmp_path)) == ["rest.vtu"]
    with pytest.raises(MeshIOError, match="exists"):
        write_vtu(tmp_path / "rest.vtu", mesh, overwrite=False)


def test_failed_write_keeps_old_file_and_leaves_no_temp(tmp_path, monkeypatch):
    mesh = je.rectangle(1, 1)
    path = tmp_path / "out.vtu"
    write_vtu(path, mesh)
    before = path.read_bytes()

    def boom(*args, **kwargs):
        with open(args[0], "w") as fh:
            fh.write("partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(meshio, "write", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        write_vtu(path, mesh, np.asarray(mesh.points) + 1.0)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["out.vtu"]


def test_protected_input_is_never_overwritten(tmp_path):
    m, _ = _square_with_groups()
    src = tmp_path / "input.vtu"
    meshio.write(src, m)
    data = read_mesh(src)
    before = src.read_bytes()
    with pytest.raises(MeshIOError, match="protected"):
        write_vtu(src, data.mesh, protect=[data])
    link = tmp_path / "alias.vtu"
    link.symlink_to(src)
    with pytest.raises(MeshIOError, match="protected"):
        write_vtu(link, data.mesh, protect=[str(src)])
    assert src.read_bytes() == before
    write_vtu(tmp_path / "output.vtu", data.mesh, protect=[data])  # other paths are fine


def test_time_series_writer(tmp_path):
    mesh = je.rectangle(2, 2)
    out = tmp_path / "series" / "run1"
    X = np.asarray(mesh.points)
    times = [0.0, 0.5, 1.25]
    params = materials.Lame(1.0, 1.0)
    with TimeSeriesWriter(out, "beam", mesh, psi=materials.stvk, params=params) as w:
        for k, t in enumerate(times):
            w.write(
                t,
                X * (1.0 + 0.1 * k),
                speed=np.full((mesh.n_nodes, 2), k),
                damage=np.full(mesh.n_cells, 0.1 * k),
            )
            assert os.path.exists(w.pvd_path)  # readable while running
        with pytest.raises(ValueError, match="point or cell data"):
            w.write(2.0, X, bad=np.zeros(7))
    with pytest.raises(ValueError, match="closed"):
        w.write(3.0, X)
    root = ET.parse(out / "beam.pvd").getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    sets = root.find("Collection").findall("DataSet")
    assert [float(d.get("timestep")) for d in sets] == times
    files = [d.get("file") for d in sets]
    assert files == ["beam_0000.vtu", "beam_0001.vtu", "beam_0002.vtu"]
    assert sorted(os.listdir(out)) == sorted(files + ["beam.pvd"])
    for k, f in enumerate(files):
        r = meshio.read(out / f)
        np.testing.assert_allclose(r.point_data["displacement"][:, :2], 0.1 * k * X, atol=1e-14)
        np.testing.assert_allclose(r.point_data["speed"][:, :2], k)
        np.testing.assert_allclose(r.cell_data["damage"][0], 0.1 * k)
        np.testing.assert_allclose(r.cell_data["J"][0], (1.0 + 0.1 * k) ** 2, rtol=1e-12)


def test_time_series_writer_validation(tmp_path):
    mesh = je.rectangle(1, 1)
    with pytest.raises(ValueError, match="basename"):
        TimeSeriesWriter(tmp_path, "a/b", mesh)
    with pytest.raises(ValueError, match="both psi and params"):
        TimeSeriesWriter(tmp_path, "a", mesh, params=materials.Lame(1.0, 1.0))
    w = TimeSeriesWriter(tmp_path, "a", mesh)
    with pytest.raises(ValueError, match="finite"):
        w.write(float("nan"), mesh.points)
    w.close()
    assert ET.parse(tmp_path / "a.pvd").getroot().find("Collection").findall("DataSet") == []


def test_cell_fields_is_jittable_with_mesh_argument():
    mesh = je.rectangle(2, 2)
    x = np.asarray(mesh.points) * 1.1
    f = jax.jit(lambda x, m: je.energy(materials.stvk, x, m, materials.Lame(1.0, 1.0)))
    out = cell_fields(materials.stvk, x, mesh, materials.Lame(1.0, 1.0))
    total = float(np.sum(out["energy_density"] * np.asarray(mesh.volumes)))
    assert total == pytest.approx(float(f(x, mesh)), rel=1e-12)


# ---- atomic writer and JSON ------------------------------------------------------------


@pytest.mark.parametrize("exc", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_write_atomic_failure_keeps_old_file_and_leaves_no_temp(tmp_path, exc):
    path = tmp_path / "data.txt"
    path.write_text("old")
    seen = []

    def write(tmp):
        seen.append(tmp)
        assert os.path.dirname(tmp) == str(tmp_path)  # same directory: os.replace is atomic
        with open(tmp, "w") as fh:
            fh.write("partial")
        raise exc

    with pytest.raises(type(exc)):
        je.io.write_atomic(path, write)
    assert path.read_text() == "old"
    assert sorted(os.listdir(tmp_path)) == ["data.txt"]
    assert seen and not os.path.exists(seen[0])


def test_write_atomic_creates_and_replaces(tmp_path):
    path = tmp_path / "new.txt"

    def write(text):
        def fn(tmp):
            with open(tmp, "w") as fh:
                fh.write(text)

        return fn

    je.io.write_atomic(str(path), write("one"))
    assert path.read_text() == "one"
    assert os.stat(path).st_mode & 0o777 == 0o644
    je.io.write_atomic(path, write("two"))
    assert path.read_text() == "two"
    assert sorted(os.listdir(tmp_path)) == ["new.txt"]


def test_to_jsonable_converts_numpy_jax_namedtuples_enums_paths():
    import enum
    import json
    import pathlib
    from typing import NamedTuple

    import jax.numpy as jnp

    class Pair(NamedTuple):
        a: int
        b: float

    class Color(enum.Enum):
        RED = 1

    obj = {
        "f": np.float32(1.5),
        "i": np.int64(3),
        "b": np.bool_(True),
        "arr": np.array([[1.0, np.nan], [np.inf, -2.0]]),
        "jax": jnp.arange(3),
        "jax_scalar": jnp.asarray(2.5),
        "pair": Pair(1, float("nan")),
        "status": je.Status.MAX_STEPS,
        "color": Color.RED,
        "path": pathlib.Path("/tmp/x"),
        "tuple": (1, "s", None),
        7: "int key",
        Color.RED: "enum key",
    }
    out = je.io.to_jsonable(obj)
    assert out == {
        "f": 1.5,
        "i": 3,
        "b": True,
        "arr": [[1.0, None], [None, -2.0]],
        "jax": [0, 1, 2],
        "jax_scalar": 2.5,
        "pair": {"a": 1, "b": None},
        "status": "MAX_STEPS",
        "color": "RED",
        "path": "/tmp/x",
        "tuple": [1, "s", None],
        "7": "int key",
        "RED": "enum key",
    }
    json.dumps(out, allow_nan=False)  # strictly valid JSON
    assert type(out["i"]) is int and type(out["f"]) is float and type(out["b"]) is bool
    strings = je.io.to_jsonable([np.nan, np.inf, -np.inf, 1.0], nonfinite="string")
    assert strings == ["nan", "inf", "-inf", 1.0]


def test_to_jsonable_rejects_unknown_types():
    with pytest.raises(TypeError, match=r"obj\['k'\]\[1\].*object"):
        je.io.to_jsonable({"k": [1, object()]})
    with pytest.raises(ValueError, match="nonfinite"):
        je.io.to_jsonable(1.0, nonfinite="zero")


def test_write_json_round_trip(tmp_path):
    import json

    path = tmp_path / "s.json"
    je.io.write_json(path, {"x": np.array([1.0, np.nan]), "status": je.Status.SUCCESS})
    text = path.read_text()
    assert text.endswith("\n")
    assert json.loads(text) == {"x": [1.0, None], "status": "SUCCESS"}
    assert sorted(os.listdir(tmp_path)) == ["s.json"]


# ---- recovered nodal stresses ------------------------------------------------------------


@pytest.mark.parametrize(
    "dim, order, formulation", [(2, 2, "standard"), (2, 1, "fbar"), (3, 2, "standard")]
)
def test_nodal_stress_of_a_uniform_state_is_exact(dim, order, formulation):
    # patch test: an affine deformation has one Cauchy stress everywhere; every node must
    # recover it, and the VTU carries it as point data beside the cell averages
    mesh = (
        je.rectangle(3, 2, order=order, formulation=formulation)
        if dim == 2
        else je.box(2, 1, 1, order=order, formulation=formulation)
    )
    A = np.eye(dim) + 0.04 * np.arange(1, dim * dim + 1).reshape(dim, dim) / dim**2
    x = np.asarray(mesh.points) @ A.T
    params = materials.Lame(1.0, 2.0)
    cells = cell_fields(materials.neo_hookean, x, mesh, params)
    nodal = nodal_stress(materials.neo_hookean, x, mesh, params)
    sig = cells["cauchy_stress"][0]
    np.testing.assert_allclose(cells["cauchy_stress"], np.tile(sig, (mesh.n_cells, 1)), atol=1e-13)
    assert nodal["cauchy_stress_nodal"].shape == (mesh.n_nodes, 9)
    np.testing.assert_allclose(
        nodal["cauchy_stress_nodal"], np.tile(sig, (mesh.n_nodes, 1)), atol=1e-13
    )
    np.testing.assert_allclose(nodal["von_mises_nodal"], cells["von_mises"][0], rtol=1e-12)
    P = np.asarray(jax.jit(je.first_piola(materials.neo_hookean))(A, params))
    np.testing.assert_allclose(
        sig.reshape(3, 3)[:dim, :dim], P @ A.T / np.linalg.det(A), rtol=1e-12
    )
    if dim == 2:  # σ_zz of the plane-strain embedding is in the tensor too
        np.testing.assert_allclose(sig[8], cells["stress_zz"][0], rtol=1e-12)


def test_nodal_stress_of_a_linear_field_on_p2_is_exact(tmp_path):
    # u quadratic -> strain and (linear elastic) stress linear in x: a P2 element holds it
    # exactly, so the recovered nodal stress is the exact stress at every node (corners and
    # mid-edge nodes); cell averages and P1 cannot do that. Tiny amplitude: the Cauchy
    # stress σ = P Fᵀ / J of the linear model then differs from the linear one by O(|∇u|).
    mesh = je.rectangle(4, 3, size=(2.0, 1.0), order=2)
    X = np.asarray(mesh.points)
    a, mu, lam = 1e-7, 1.0, 2.0
    xs, ys = X[:, 0], X[:, 1]
    u = a * np.stack([xs**2 + 0.5 * xs * ys, ys**2 - 0.3 * xs**2], axis=1)
    G = a * np.stack(
        [np.stack([2 * xs + 0.5 * ys, 0.5 * xs], 1), np.stack([-0.6 * xs, 2 * ys], 1)], 1
    )
    eps = 0.5 * (G + np.swapaxes(G, 1, 2))
    tr = eps[:, 0, 0] + eps[:, 1, 1]
    exact = 2 * mu * eps + lam * tr[:, None, None] * np.eye(2)
    params = materials.Lame(mu, lam)
    write_vtu(tmp_path / "p2.vtu", mesh, X + u, psi=materials.linear, params=params)
    back = meshio.read(tmp_path / "p2.vtu")
    s = back.point_data["cauchy_stress_nodal"].reshape(-1, 3, 3)
    scale = np.abs(exact).max()
    assert np.abs(s[:, :2, :2] - exact).max() < 1e-5 * scale
    np.testing.assert_allclose(s[:, 2, 2], lam * tr, atol=1e-5 * scale)  # plane strain σ_zz
    assert back.point_data["von_mises_nodal"].shape == (mesh.n_nodes,)
    # the cell averages at the nodes of their cells are off by O(h · ∇σ)
    cell = back.cell_data["cauchy_stress"][0].reshape(-1, 3, 3)
    cells = np.asarray(mesh.cells)
    assert np.abs(cell[:, None, :2, :2] - exact[cells]).max() > 0.05 * scale
    # P1 on the same field (σ piecewise constant) is not exact either
    p1 = je.rectangle(8, 6, size=(2.0, 1.0))
    X1 = np.asarray(p1.points)
    u1 = a * np.stack([X1[:, 0] ** 2, X1[:, 1] ** 2], axis=1)
    n1 = nodal_stress(materials.linear, X1 + u1, p1, params)["cauchy_stress_nodal"]
    ex1 = 2 * mu * a * 2 * X1[:, 0] + lam * a * 2 * (X1[:, 0] + X1[:, 1])
    assert np.abs(n1[:, 0] - ex1).max() > 0.05 * np.abs(ex1).max()


def test_pvd_times_are_rounded_to_the_step():
    # t accumulated as k·h in floating point: 0.30000000000000004, 0.7000000000000001, …
    from jaxelastic.io.vtk import time_labels

    times, t = [], 0.0
    for _ in range(12):
        times.append(t)
        t += 0.1
    labels = time_labels(times)
    assert labels[3] == "0.3" and labels[7] == "0.7" and labels[11] == "1.1"
    assert all(len(s) <= 4 for s in labels)
    assert time_labels([1.0, 1.0 + 1e-14]) == ["1.0", repr(1.0 + 1e-14)]  # kept apart


@pytest.mark.slow
def test_nodal_stress_reads_the_kirsch_concentration_at_a_hole(tmp_path):
    # quarter of a 80 x 80 plate with a hole of radius 1 under remote σ0 = 1 (plane stress,
    # linear), P2, h = 0.03 at the hole: σ_xx/σ0 at the hole's top is 3 (Kirsch; 3.002 for
    # this width). The recovered nodal value is within 1 %, the largest cell average is not.
    gmsh = pytest.importorskip("gmsh")
    from jaxelastic.scene import run_scene

    W, a = 40.0, 1.0
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        occ = gmsh.model.occ
        cut, _ = occ.cut([(2, occ.addRectangle(0, 0, 0, W, W))], [(2, occ.addDisk(0, 0, 0, a, a))])
        occ.synchronize()
        s = cut[0][1]
        gmsh.model.addPhysicalGroup(2, [s], name="body")
        curves = [c for _, c in gmsh.model.getBoundary([(2, s)], oriented=False)]
        arc = [c for c in curves if np.hypot(*occ.getCenterOfMass(1, abs(c))[:2]) < a]
        f = gmsh.model.mesh.field
        f.add("Distance", 1)
        f.setNumbers(1, "CurvesList", [abs(c) for c in arc])
        f.add("Threshold", 2)
        for k, v in dict(InField=1, SizeMin=0.03, SizeMax=W / 10, DistMin=0.0, DistMax=6.0).items():
            f.setNumber(2, k, v)
        f.setAsBackgroundMesh(2)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.model.mesh.generate(2)
        gmsh.model.mesh.setOrder(2)
        gmsh.option.setNumber("Mesh.MshFileVersion", 2.2)
        gmsh.write(str(tmp_path / "plate.msh"))
    finally:
        gmsh.finalize()
    scene = {
        "name": "kirsch",
        "mesh": {"file": str(tmp_path / "plate.msh")},
        "material": {"model": "linear", "E": 1000.0, "nu": 0.3, "plane": "stress"},
        "dirichlet": [
            {"nodes": {"plane": {"axis": "x", "value": 0.0}}, "components": ["x"]},
            {"nodes": {"plane": {"axis": "y", "value": 0.0}}, "components": ["y"]},
        ],
        "traction": [{"facets": {"plane": {"axis": "x", "value": W}}, "traction": [1.0, 0.0]}],
        "output": {"png": False},
    }
    assert run_scene(scene, tmp_path / "out", progress=False)["mesh"]["element"] == "tri6"
    v = meshio.read(tmp_path / "out" / "static_0000.vtu")
    top = int(np.argmin(np.hypot(v.points[:, 0], v.points[:, 1] - a)))  # (0, a)
    nodal = v.point_data["cauchy_stress_nodal"][:, 0]
    assert abs(nodal[top] / 3.0 - 1.0) < 0.01, nodal[top]
    assert nodal.max() == nodal[top] or abs(nodal.max() / 3.0 - 1.0) < 0.01
    assert v.cell_data["cauchy_stress"][0][:, 0].max() < 0.985 * 3.0  # cell averages: low


def test_write_vtu_precomputed_fields_and_uncompressed_match(tmp_path):
    """fields= (one stress evaluation shared with a picture) and compression=None write
    the same arrays as the default; the uncompressed file is a plain binary VTU."""
    from jaxelastic.postprocess import stress_fields

    mesh = je.box(3, 2, 2)
    X = np.asarray(mesh.points)
    x = X + 0.05 * np.sin(3.0 * X[:, [1, 2, 0]])
    params = materials.Lame(1.0, 2.0)
    kw = dict(psi=materials.neo_hookean, params=params)
    write_vtu(tmp_path / "ref.vtu", mesh, x, **kw)
    fields = stress_fields(materials.neo_hookean, x, mesh, params)
    write_vtu(tmp_path / "pre.vtu", mesh, x, fields=fields, **kw)
    write_vtu(tmp_path / "raw.vtu", mesh, x, compression=None, **kw)
    ref = meshio.read(tmp_path / "ref.vtu")
    for name in ("pre.vtu", "raw.vtu"):
        back = meshio.read(tmp_path / name)
        assert list(back.point_data) == list(ref.point_data)
        assert list(back.cell_data) == list(ref.cell_data)
        for k, v in ref.point_data.items():
            np.testing.assert_array_equal(back.point_data[k], v)
        for k, v in ref.cell_data.items():
            np.testing.assert_array_equal(back.cell_data[k][0], v[0])
        np.testing.assert_array_equal(back.cells[0].data, ref.cells[0].data)
    assert "compressor" in ET.parse(tmp_path / "ref.vtu").getroot().attrib
    assert "compressor" not in ET.parse(tmp_path / "raw.vtu").getroot().attrib
    nodal = nodal_stress(materials.neo_hookean, x, mesh, params)
    np.testing.assert_allclose(
        ref.point_data["von_mises_nodal"], nodal["von_mises_nodal"], rtol=1e-14
    )
    with pytest.raises(ValueError, match="fields"):
        write_vtu(tmp_path / "bad.vtu", mesh, x, fields=fields)
    with pytest.raises(ValueError, match="compression"):
        write_vtu(tmp_path / "bad.vtu", mesh, x, compression="lz4", **kw)
    assert not (tmp_path / "bad.vtu").exists()
