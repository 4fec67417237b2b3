"""Mesh generators, rest-shape preprocessing, boundary facets and input validation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxelastic as je
from jaxelastic.mesh import MeshError, boundary_facets, boundary_nodes, from_arrays


def _signed_measures(mesh):
    x = np.asarray(mesh.points)[np.asarray(mesh.cells)]  # (c, k, d)
    Dm = np.swapaxes(x[:, 1:] - x[:, :1], 1, 2)  # columns x_k − x_0
    fact = 2.0 if mesh.dim == 2 else 6.0
    return np.linalg.det(Dm) / fact, Dm


def _facet_area_normals(mesh, facets):
    """Area-weighted right-hand-rule normals of facets, ``(m, dim)``."""
    p = np.asarray(mesh.points)[facets]
    if mesh.dim == 2:
        t = p[:, 1] - p[:, 0]
        return np.stack([t[:, 1], -t[:, 0]], axis=1)
    return 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


GENERATED = {
    "rectangle": lambda: je.rectangle(4, 3, size=(2.0, 1.5), origin=(-1.0, 0.5)),
    "box": lambda: je.box(3, 2, 2, size=(1.0, 0.5, 2.0)),
    "cook": lambda: je.cook_membrane(4),
}


# ---------------------------------------------------------------- generators


@pytest.mark.parametrize(
    "mesh, n_nodes, n_cells, measure",
    [
        (lambda: je.rectangle(4, 3, size=(2.0, 1.5)), 5 * 4, 2 * 4 * 3, 3.0),
        (lambda: je.box(3, 2, 2, size=(1.0, 0.5, 2.0)), 4 * 3 * 3, 6 * 3 * 2 * 2, 1.0),
        (lambda: je.cook_membrane(5), 6 * 6, 2 * 25, (44.0 + 16.0) / 2 * 48.0),
    ],
    ids=["rectangle", "box", "cook"],
)
def test_generator_counts_and_measure(mesh, n_nodes, n_cells, measure):
    m = mesh()
    assert m.n_nodes == n_nodes and m.n_cells == n_cells
    assert m.cells.shape == (n_cells, m.dim + 1)
    assert float(m.volumes.sum()) == pytest.approx(measure, rel=1e-12)
    assert m.weights.dtype == jnp.float64


def test_cook_membrane_corners_and_area():
    m = je.cook_membrane(2)
    pts = {tuple(p) for p in np.asarray(m.points).tolist()}
    assert {(0.0, 0.0), (48.0, 44.0), (48.0, 60.0), (0.0, 44.0), (48.0, 52.0)} <= pts
    assert float(m.volumes.sum()) == pytest.approx(1440.0, rel=1e-13)


@pytest.mark.parametrize("name", list(GENERATED))
def test_cells_positively_oriented_and_measures_match(name):
    m = GENERATED[name]()
    vol, _ = _signed_measures(m)
    assert np.all(vol > 0)
    np.testing.assert_allclose(np.asarray(m.volumes), vol, rtol=1e-12)


@pytest.mark.parametrize("name", list(GENERATED))
def test_dm_inv_consistent_with_points(name):
    m = GENERATED[name]()
    _, Dm = _signed_measures(m)
    np.testing.assert_allclose(np.asarray(m.Dm_inv), np.linalg.inv(Dm), rtol=1e-12, atol=1e-12)
    # shape-function gradients sum to zero (partition of unity) and reproduce F = I at rest
    dN = np.asarray(m.dN)
    np.testing.assert_allclose(dN.sum(axis=2), 0.0, atol=1e-12)
    F = np.asarray(jax.jit(je.kinematics.deformation_gradients)(m.points, m))
    np.testing.assert_allclose(F, np.broadcast_to(np.eye(m.dim), F.shape), atol=1e-12)


def test_box_is_conforming():
    nx, ny, nz = 3, 2, 2
    m = je.box(nx, ny, nz)
    cells = np.asarray(m.cells)
    faces = np.sort(cells[:, np.asarray(m.element_type.facet_nodes)].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert set(counts.tolist()) <= {1, 2}
    n_boundary = 2 * 2 * (nx * ny + ny * nz + nx * nz)
    assert np.count_nonzero(counts == 1) == n_boundary
    assert len(boundary_facets(m)) == n_boundary
    # Euler characteristic of a ball: V − E + F − T = 1
    edges = np.sort(cells[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2), 1)
    n_edges = len(np.unique(edges, axis=0))
    assert m.n_nodes - n_edges + len(counts) - m.n_cells == 1


@pytest.mark.parametrize("name", list(GENERATED))
def test_incidence_reproduces_scatter_add(name):
    m = GENERATED[name]()
    rng = np.random.default_rng(0)
    per_el = jnp.asarray(rng.standard_normal((m.n_cells, m.dim + 1, m.dim)))
    scatter = jax.jit(lambda m, pe: jnp.zeros((m.n_nodes, m.dim)).at[m.cells].add(pe))
    expected = scatter(m, per_el)
    np.testing.assert_allclose(
        jax.jit(je.mechanics.assemble)(m, per_el), expected, rtol=1e-12, atol=1e-12
    )
    # every (cell, local node) slot appears exactly once in the incidence table
    inc = np.asarray(m.incidence)
    slots = inc[inc < m.n_cells * (m.dim + 1)]
    assert np.array_equal(np.sort(slots), np.arange(m.n_cells * (m.dim + 1)))


@pytest.mark.parametrize("name", list(GENERATED))
def test_boundary_normals_close_and_point_outward(name):
    m = GENERATED[name]()
    bf = boundary_facets(m)
    n = _facet_area_normals(m, bf)
    np.testing.assert_allclose(n.sum(axis=0), 0.0, atol=1e-10)  # closed surface
    # all three domains are convex: outward ⇔ (facet centroid − body centroid)·n > 0
    pts = np.asarray(m.points)
    centre = pts.mean(axis=0)
    assert np.all(np.einsum("fd,fd->f", pts[bf].mean(axis=1) - centre, n) > 0)
    # total boundary measure equals the perimeter / surface area
    if name == "rectangle":
        assert np.linalg.norm(n, axis=1).sum() == pytest.approx(2 * (2.0 + 1.5))
    if name == "box":
        assert np.linalg.norm(n, axis=1).sum() == pytest.approx(2 * (0.5 + 2.0 + 1.0))


def test_box_facets_on_x1_have_normal_plus_x():
    m = je.box(2, 2, 3)
    bf = boundary_facets(m)
    pts = np.asarray(m.points)
    on = np.all(np.isclose(pts[bf][..., 0], 1.0), axis=1)
    assert on.sum() == 2 * 2 * 3
    n = _facet_area_normals(m, bf[on])
    unit = n / np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(unit, np.broadcast_to([1.0, 0.0, 0.0], unit.shape), atol=1e-12)
    assert n[:, 0].sum() == pytest.approx(1.0)


def test_boundary_nodes_rectangle():
    m = je.rectangle(3, 2)
    assert len(boundary_nodes(m)) == 2 * (3 + 2)


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2"])
def test_generators_refuse_bad_counts(bad):
    with pytest.raises(ValueError):
        je.rectangle(bad, 2)


# ---------------------------------------------------------------- validation

TRI_PTS = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
TRI_CELLS = np.array([[0, 1, 2], [1, 3, 2]])


def test_valid_input_builds_mesh():
    m = from_arrays(TRI_PTS, TRI_CELLS)
    assert m.element == "tri3" and m.n_cells == 2
    assert float(m.volumes.sum()) == pytest.approx(1.0)


def test_zero_measure_cell_refused():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 1.0]])
    with pytest.raises(MeshError, match="zero rest measure"):
        from_arrays(pts, [[0, 1, 2], [0, 1, 3]])


def test_inverted_cell_refused_or_reoriented():
    cells = np.array([[0, 2, 1], [1, 3, 2]])  # first one clockwise
    with pytest.raises(MeshError, match="inverted"):
        from_arrays(TRI_PTS, cells, orient="refuse")
    with pytest.warns(UserWarning, match="reoriented 1 of 2"):
        m = from_arrays(TRI_PTS, cells)
    vol, _ = _signed_measures(m)
    assert np.all(vol > 0)
    assert sorted(np.asarray(m.cells)[0].tolist()) == [0, 1, 2]


def test_inverted_tet_reoriented():
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    with pytest.warns(UserWarning, match="reoriented"):
        m = from_arrays(pts, [[0, 2, 1, 3]])
    assert float(m.volumes[0]) == pytest.approx(1.0 / 6.0)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_coordinates_refused(value):
    pts = TRI_PTS.copy()
    pts[3, 1] = value
    with pytest.raises(MeshError, match="NaN/inf"):
        from_arrays(pts, TRI_CELLS)


@pytest.mark.parametrize(
    "cells, match",
    [
        ([[0, 1, 2], [1, 4, 2]], "outside"),
        ([[0, 1, 2], [1, -1, 2]], "outside"),
        ([[0, 1, 2], [1, 1, 3]], "repeat a node"),
        ([[0, 1, 3]], "belong to no cell"),
        ([[0, 1, 2, 3]], "cannot infer the element"),
        (np.zeros((0, 3), dtype=int), "no cells"),
        ([[0.0, 1.0, 2.0], [1.0, 3.5, 2.0]], "integer node indices"),
        ([0, 1, 2], "cells must have shape"),
    ],
    ids=["out-of-range", "negative", "duplicate", "unused", "node-count", "empty", "float", "1d"],
)
def test_bad_cells_refused(cells, match):
    with pytest.raises(MeshError, match=match):
        from_arrays(TRI_PTS, cells)


def test_integer_valued_float_cells_accepted():
    m = from_arrays(TRI_PTS, TRI_CELLS.astype(float))
    assert np.array_equal(np.asarray(m.cells), TRI_CELLS)


def test_wrong_node_count_for_named_element_refused():
    with pytest.raises(MeshError, match="3 nodes per cell"):
        from_arrays(TRI_PTS, [[0, 1, 2, 3]], "tri3")


@pytest.mark.parametrize("dim", [1, 4])
def test_wrong_dimension_refused(dim):
    pts = np.random.default_rng(0).random((5, dim))
    with pytest.raises(MeshError, match="points must have shape"):
        from_arrays(pts, [[0, 1, 2]])


def test_element_dimension_mismatch_refused():
    with pytest.raises(MeshError, match="3D but points are 2D"):
        from_arrays(TRI_PTS, [[0, 1, 2, 3]], "tet4")


@pytest.mark.parametrize("element", ["quad", "quad9", "hex8"])
def test_unsupported_element_refused(element):
    with pytest.raises(MeshError, match="unsupported element type"):
        from_arrays(TRI_PTS, TRI_CELLS, element)


def test_meshio_element_names_accepted():
    assert from_arrays(TRI_PTS, TRI_CELLS, "triangle").element == "tri3"


def test_bad_orient_option():
    with pytest.raises(ValueError, match="orient"):
        from_arrays(TRI_PTS, TRI_CELLS, orient="flip")


@pytest.mark.parametrize("name", list(GENERATED))
def test_boundary_facets_are_those_of_one_cell(name):
    """The int64-key uniqueness in boundary_facets equals a plain count of every facet's
    corner set over all cells (independent of the encoding), facet order included."""
    from collections import Counter

    m = GENERATED[name]()
    local = np.asarray(m.element_type.facet_nodes)
    facets = np.asarray(m.cells)[:, local].reshape(-1, local.shape[1])
    keys = [tuple(sorted(f[: m.dim])) for f in facets.tolist()]
    count = Counter(keys)
    expected = facets[[count[k] == 1 for k in keys]]
    assert np.array_equal(boundary_facets(m), expected)
