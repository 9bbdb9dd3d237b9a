"""Tests for warpfem.mesh (pure numpy / scipy / meshio, no Warp)."""

import os
import warnings

import numpy as np
import pytest

from warpfem.mesh import (
    MeshError,
    TetMesh,
    box_tet_mesh,
    boundary_faces,
    consistent_mass,
    load_mesh,
    lumped_mass,
    save_mesh,
    select_vertices_in_box,
)

MESH_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples", "meshes")
BUNNY = os.path.join(MESH_DIR, "bunny.mesh")
OCTOPUS = os.path.join(MESH_DIR, "octopus-low.mesh")

UNIT_TET_X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


def divergence_volume(x, faces):
    """Volume enclosed by outward triangles: sum of area-weighted normal . centroid / 3."""
    a, b, c = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    return np.einsum("ij,ij->", np.cross(b - a, c - a) / 2.0, (a + b + c) / 3.0) / 3.0


def two_tets():
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    t = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    return x, t


# ----------------------------------------------------------------------------- box generator
@pytest.mark.parametrize("cells", [(1, 1, 1), (2, 3, 4), (5, 1, 2)])
def test_box_counts_volumes(cells):
    size = (2.0, 0.5, 3.0)
    m = box_tet_mesh(size=size, cells=cells, origin=(-1.0, 2.0, 0.5))
    nx, ny, nz = cells
    assert m.num_vertices == (nx + 1) * (ny + 1) * (nz + 1)
    assert m.num_tets == 6 * nx * ny * nz
    assert m.element_type == "tet4" and m.elements is m.tets
    assert m.vertices.dtype == np.float64 and m.tets.dtype == np.int64
    v = m.rest_volumes()
    assert np.all(v > 0)
    np.testing.assert_allclose(v, np.prod(size) / (6 * nx * ny * nz), rtol=1e-12)
    assert v.sum() == pytest.approx(np.prod(size), rel=1e-13)
    lo, hi = m.bounds()
    np.testing.assert_array_equal(lo, [-1.0, 2.0, 0.5])
    np.testing.assert_array_equal(hi, [1.0, 2.5, 3.5])
    assert m.characteristic_length() == pytest.approx(np.linalg.norm(size))
    assert not m.vertices.flags.writeable and not m.tets.flags.writeable


def test_box_vertex_numbering_and_split():
    nx, ny, nz = 3, 2, 4
    m = box_tet_mesh(size=(3.0, 2.0, 4.0), cells=(nx, ny, nz))
    for i, j, k in [(0, 0, 0), (3, 0, 0), (1, 2, 3), (3, 2, 4)]:
        np.testing.assert_array_equal(m.vertices[i + (nx + 1) * (j + (ny + 1) * k)], [i, j, k])
    # First cell: corners 0..7 in the reference order, 6 tets around diagonal 0-6.
    c = [0, 1, 5, 4, 12, 13, 17, 16]  # grid ids of (0,0,0),(1,0,0),(1,1,0),(0,1,0),(0,0,1),...
    expect = [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]]
    np.testing.assert_array_equal(m.tets[:6], np.array(c)[np.array(expect)])


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(cells=(0, 1, 1)), ">= 1"),
        (dict(cells=(1.5, 1, 1)), "integers"),
        (dict(cells=(1, 1)), "integers"),
        (dict(size=(1.0, -1.0, 1.0)), "size"),
        (dict(size=(1.0, 0.0, 1.0)), "size"),
    ],
)
def test_box_validation(kw, match):
    with pytest.raises(MeshError, match=match):
        box_tet_mesh(**kw)


# ----------------------------------------------------------------------------- boundary faces
@pytest.mark.parametrize("cells", [(1, 1, 1), (2, 3, 4)])
def test_box_boundary_faces_outward(cells):
    size = (1.5, 2.0, 0.7)
    m = box_tet_mesh(size=size, cells=cells, origin=(0.3, -0.2, 1.0))
    nx, ny, nz = cells
    f = m.boundary_faces()
    assert f.shape == (4 * (nx * ny + ny * nz + nx * nz), 3)
    assert divergence_volume(m.vertices, f) == pytest.approx(np.prod(size), rel=1e-12)
    # every outward normal points away from the box centre
    x = m.vertices
    n = np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])
    centre = np.mean(m.bounds(), axis=0)
    assert np.all(np.einsum("ij,ij->i", n, x[f].mean(axis=1) - centre) > 0)
    np.testing.assert_array_equal(boundary_faces(m), f)
    assert len(m.boundary_vertices()) == m.num_vertices - max(nx - 1, 0) * max(ny - 1, 0) * max(nz - 1, 0)


def test_single_tet_boundary_is_its_four_faces():
    m = TetMesh(UNIT_TET_X, [[0, 1, 2, 3]])
    f = m.boundary_faces()
    assert len(f) == 4
    assert divergence_volume(m.vertices, f) == pytest.approx(1.0 / 6.0, rel=1e-14)


# ----------------------------------------------------------------------------- mass
def test_mass_box():
    rho = 7.5
    m = box_tet_mesh(size=(2.0, 1.0, 3.0), cells=(3, 2, 2))
    ml = lumped_mass(m, rho)
    M = consistent_mass(m, rho)
    assert ml.shape == (m.num_vertices,) and np.all(ml > 0)
    assert M.shape == (m.num_vertices, m.num_vertices) and M.format == "csr"
    assert ml.sum() == pytest.approx(rho * 6.0, rel=1e-13)
    assert M.sum() == pytest.approx(rho * 6.0, rel=1e-13)
    np.testing.assert_allclose(np.asarray(M.sum(axis=1)).ravel(), ml, rtol=1e-13)
    assert abs(M - M.T).max() == 0.0
    assert np.all(M.diagonal() > 0)
    assert np.linalg.eigvalsh(M.toarray()).min() > 0
    # a rigid translation's kinetic energy is 1/2 m v^2
    assert np.ones(m.num_vertices) @ (M @ np.ones(m.num_vertices)) == pytest.approx(rho * 6.0)


def test_consistent_mass_single_tet():
    rho = 3.0
    x = np.array([[0.0, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, 3]])
    m = TetMesh(x, [[0, 1, 2, 3]])
    V = 1.0
    assert m.rest_volumes()[0] == pytest.approx(V)
    np.testing.assert_allclose(consistent_mass(m, rho).toarray(),
                               rho * V / 20.0 * (np.ones((4, 4)) + np.eye(4)), rtol=1e-14)
    np.testing.assert_allclose(lumped_mass(m, rho), rho * V / 4.0, rtol=1e-14)


def test_mass_bad_density():
    m = box_tet_mesh()
    with pytest.raises(ValueError, match="density"):
        lumped_mass(m, -1.0)
    with pytest.raises(ValueError, match="density"):
        consistent_mass(m, np.ones(3))


# ----------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "x, t, match",
    [
        (np.zeros((4, 2)), [[0, 1, 2, 3]], r"vertices must have shape \(n, 3\)"),
        (UNIT_TET_X, [[0, 1, 2]], r"tets must have shape \(m, 4\)"),
        (UNIT_TET_X, np.zeros((0, 4), int), "no tets"),
        (UNIT_TET_X, [], "no tets"),
        (UNIT_TET_X, [[0, 1, 2, 3], [0, 1, 2, 7]], r"tet 1 references vertex index 7 out of range"),
        (UNIT_TET_X, [[0, 1, 2, 3], [-1, 1, 2, 3]], r"tet 1 references vertex index -1"),
        (UNIT_TET_X, [[0, 1, 2, 3], [0, 1, 1, 3]], r"tet 1 repeats a vertex"),
        (UNIT_TET_X, [[0, 1, 2.5, 3]], r"tet 0 has non-integer"),
    ],
)
def test_validation_errors(x, t, match):
    with pytest.raises(MeshError, match=match):
        TetMesh(x, t)


@pytest.mark.parametrize("bad, word", [(np.nan, "NaN"), (np.inf, "inf"), (-np.inf, "inf")])
def test_non_finite_vertex(bad, word):
    x = np.array(UNIT_TET_X)
    x[2, 1] = bad
    with pytest.raises(MeshError, match=rf"vertex 2 has non-finite \({word}\)"):
        TetMesh(x, [[0, 1, 2, 3]])


def test_zero_volume_tets_named():
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0.5, 0.5, 0]])
    t = [[0, 1, 2, 3], [0, 1, 2, 4], [1, 2, 3, 4], [0, 1, 4, 5]]  # tets 1, 3 flat (z = 0)
    with pytest.raises(MeshError, match=r"2 degenerate \(zero-volume\) tets.*tets 1, 3"):
        TetMesh(x, t)
    # scale awareness: a tiny but well-shaped mesh is fine
    m = TetMesh(UNIT_TET_X * 1e-5, [[0, 1, 2, 3]])
    assert m.rest_volumes()[0] == pytest.approx(1e-15 / 6)
    # a sliver just above the threshold passes, one below fails
    for h, ok in [(1e-9, True), (1e-13, False)]:
        xs = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, h]])
        if ok:
            assert TetMesh(xs, [[0, 1, 2, 3]]).num_tets == 1
        else:
            with pytest.raises(MeshError, match="tets 0"):
                TetMesh(xs, [[0, 1, 2, 3]])


def test_tiny_well_shaped_tet_beside_large_ones_is_not_degenerate():
    """Degenerate means both tiny against the mesh (1e-12 of its bounding box cubed) and flat for
    its own size: a TetGen-refined 2e-5-sized tet in a unit mesh passes, a flat one of that size fails."""
    big = np.array(UNIT_TET_X, dtype=np.float64)
    s = 2e-5  # volume s^3 / 6 = 1.3e-15 < 1e-12 * diag^3
    tiny = np.array([[2.0, 0, 0], [2 + s, 0, 0], [2, s, 0], [2, 0, s]])
    x = np.concatenate([big, tiny])
    m = TetMesh(x, [[0, 1, 2, 3], [4, 5, 6, 7]])
    assert m.rest_volumes()[1] == pytest.approx(s ** 3 / 6, rel=1e-9)
    flat = tiny.copy()
    flat[3, 2] = s * 1e-7  # the same size, 1e-7 of its height
    with pytest.raises(MeshError, match=r"1 degenerate \(zero-volume\) tets.*tets 1"):
        TetMesh(np.concatenate([big, flat]), [[0, 1, 2, 3], [4, 5, 6, 7]])


def test_error_names_file(tmp_path):
    import meshio

    p = tmp_path / "bad.vtu"
    meshio.write(str(p), meshio.Mesh(UNIT_TET_X, [("tetra", np.array([[0, 1, 1, 3]]))]))
    with pytest.raises(MeshError, match=r"bad\.vtu: tet 0 repeats a vertex"):
        load_mesh(p)


def test_reorientation_warning():
    x, t = two_tets()
    t = t.copy()
    t[0] = [0, 2, 1, 3]  # negative
    t[1] = t[1][[1, 0, 2, 3]]
    v_abs = np.abs([1.0 / 6, 1.0 / 3])
    with pytest.warns(UserWarning, match=r"reoriented 2 of 2 negatively oriented tets"):
        m = TetMesh(x, t)
    np.testing.assert_allclose(m.rest_volumes(), v_abs)
    np.testing.assert_array_equal(m.reoriented_tets, [0, 1])
    assert set(m.tets[0]) == {0, 1, 2, 3}
    assert divergence_volume(m.vertices, m.boundary_faces()) == pytest.approx(v_abs.sum())
    with pytest.raises(MeshError, match="2 negatively oriented tets: 0, 1"):
        TetMesh(x, t, reorient=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        TetMesh(*two_tets())  # positive mesh: no warning


def test_unreferenced_vertices_removed():
    x, t = two_tets()
    x = np.vstack([[9.0, 9, 9], x[:2], [7.0, 7, 7], x[2:], [8.0, 8, 8]])  # unused: 0, 3, 7
    t = np.array([[1, 2, 4, 5], [2, 4, 5, 6]])
    with pytest.warns(UserWarning, match=r"3 unreferenced vertices removed.*: 0, 3, 7"):
        m = TetMesh(x, t)
    assert m.num_vertices == 5
    np.testing.assert_array_equal(m.vertex_map, [-1, 0, 1, -1, 2, 3, 4, -1])
    np.testing.assert_array_equal(m.unreferenced_vertices, [0, 3, 7])
    np.testing.assert_array_equal(m.vertices, two_tets()[0])
    np.testing.assert_array_equal(m.tets, two_tets()[1])
    # the bounding box no longer sees the stray vertices
    assert m.characteristic_length() == pytest.approx(np.sqrt(3.0))
    with pytest.warns(UserWarning, match="3 unreferenced vertices kept"):
        k = TetMesh(x, t, remove_unreferenced=False)
    assert k.num_vertices == 8
    np.testing.assert_array_equal(k.vertex_map, np.arange(8))


def test_input_is_copied():
    x, t = two_tets()
    m = TetMesh(x, t)
    x[0] = 100.0
    t[0, 0] = 4
    assert m.vertices[0, 0] == 0.0 and m.tets[0, 0] == 0
    with pytest.raises(ValueError):
        m.vertices[0, 0] = 1.0


# ----------------------------------------------------------------------------- selection
def test_select_vertices_in_box():
    m = box_tet_mesh(size=(10.0, 1.0, 1.0), cells=(10, 2, 2))
    left = select_vertices_in_box(m.vertices, (0, 0, 0), (0, 1, 1))
    assert left.dtype == np.int64 and len(left) == 9
    assert np.all(m.vertices[left, 0] == 0.0)
    # relative tolerance catches round-off, the next layer (x = 1) is excluded
    xs = np.array(m.vertices)
    xs[left, 0] = -1e-12
    assert len(select_vertices_in_box(xs, (0, 0, 0), (0, 1, 1))) == 9
    inf = np.inf
    assert len(select_vertices_in_box(m, (9.5, -inf, -inf), (inf, inf, inf))) == 9
    assert len(select_vertices_in_box(m, (-inf,) * 3, (inf,) * 3)) == m.num_vertices
    with pytest.raises(ValueError, match="invalid box"):
        select_vertices_in_box(m, (1, 0, 0), (0, 1, 1))


# ----------------------------------------------------------------------------- I/O
@pytest.mark.parametrize("ext", [".vtu", ".msh", ".vtk", ".mesh"])
def test_save_load_round_trip(tmp_path, ext):
    m = box_tet_mesh(size=(1.0, 2.0, 3.0), cells=(2, 1, 3), origin=(0.1, 0.2, 0.3))
    p = save_mesh(m, tmp_path / f"box{ext}")
    r = load_mesh(p)
    assert (r.num_vertices, r.num_tets) == (m.num_vertices, m.num_tets)
    np.testing.assert_allclose(r.vertices, m.vertices, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(r.tets, m.tets)
    assert r.name == str(p)


def test_missing_file(tmp_path):
    p = tmp_path / "nope.mesh"
    with pytest.raises(FileNotFoundError, match="nope.mesh"):
        load_mesh(p)


def test_no_tetra_cells(tmp_path):
    import meshio

    p = tmp_path / "surf.vtu"
    meshio.write(str(p), meshio.Mesh(UNIT_TET_X, [("triangle", np.array([[0, 1, 2], [0, 2, 3]]))]))
    with pytest.raises(MeshError, match=r"surf\.vtu: no tetra cells found; cell types in file: triangle \(2\)"):
        load_mesh(p)


def test_triangles_ignored_and_unreferenced_warned(tmp_path):
    import meshio

    x = np.vstack([UNIT_TET_X, [[5.0, 5, 5]]])
    p = tmp_path / "mixed.vtu"
    meshio.write(str(p), meshio.Mesh(x, [("triangle", np.array([[0, 1, 4]])),
                                         ("tetra", np.array([[0, 2, 1, 3]]))]))
    with pytest.warns(UserWarning) as rec:
        m = load_mesh(p)
    msgs = " | ".join(str(w.message) for w in rec)
    assert "mixed.vtu: 1 unreferenced vertices removed" in msgs
    assert "mixed.vtu: reoriented 1 of 1" in msgs
    assert m.num_vertices == 4 and m.num_tets == 1 and m.rest_volumes()[0] > 0


def test_load_bunny():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # clean file: no reorientation, no unreferenced vertices
        m = load_mesh(BUNNY)
    assert (m.num_vertices, m.num_tets) == (5433, 34055)
    v = m.rest_volumes()
    assert np.all(v > 0)
    assert v.min() == pytest.approx(2.179e-12, rel=1e-3)  # sliver, above the degeneracy threshold
    assert m.quality().min() < 1e-4
    # quirk: the tets fill the convex hull; the bunny surface is embedded as interior faces
    f = m.boundary_faces()
    assert len(f) == 670
    assert divergence_volume(m.vertices, f) == pytest.approx(v.sum(), rel=1e-12)
    from scipy.spatial import ConvexHull

    assert v.sum() == pytest.approx(ConvexHull(m.vertices).volume, rel=1e-9)
    b = load_mesh(BUNNY, inside_surface=True)
    assert (b.num_vertices, b.num_tets) == (5433, 22874)
    assert b.total_volume() == pytest.approx(7.539342e-4, rel=1e-6)
    assert len(b.boundary_faces()) == 6966
    assert b.quality().min() > 0.02
    ml = lumped_mass(b, 1000.0)
    assert ml.sum() == pytest.approx(1000.0 * b.total_volume(), rel=1e-13) and np.all(ml > 0)


def test_load_octopus():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = load_mesh(OCTOPUS)
    assert (m.num_vertices, m.num_tets) == (452, 1140)
    assert np.all(m.rest_volumes() > 0)
    f = m.boundary_faces()
    assert len(f) == 898
    assert divergence_volume(m.vertices, f) == pytest.approx(m.total_volume(), rel=1e-12)
    assert m.total_volume() == pytest.approx(9.135548e-3, rel=1e-6)
