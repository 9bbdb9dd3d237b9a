"""Skinning: barycentric embedding of a render surface in the tet mesh, numpy and Warp."""

import os
import time

import numpy as np
import pytest
import warp as wp

from warpfem.skinning import (
    SurfaceError,
    SurfaceSkinner,
    embed_points,
    load_surface,
    mesh_boundary_surface,
    point_tet_distance,
)

MESH_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples", "meshes")
BUNNY_TET = os.path.join(MESH_DIR, "bunny.mesh")
BUNNY_OFF = os.path.join(MESH_DIR, "bunny.off")

# Kuhn subdivision of the unit cube into 6 tets (conforming across cubes); corner c = x + 2y + 4z.
_KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def box_mesh(cells=(2, 2, 2), size=(1.0, 1.0, 1.0)):
    nx, ny, nz = cells
    g = np.stack(np.meshgrid(*[np.linspace(0.0, s, c + 1) for s, c in zip(size, cells)], indexing="ij"), -1)
    vertices = g.reshape(-1, 3)

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    tets = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                corners = [vid(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1)) for c in range(8)]
                tets.extend([[corners[a] for a in t] for t in _KUHN])
    return vertices, np.array(tets, dtype=np.int64)


def random_affine(rng):
    A = np.eye(3) + 0.5 * rng.standard_normal((3, 3))
    c = rng.standard_normal(3)
    return A, c


@pytest.fixture(scope="module")
def bunny():
    import meshio

    m = meshio.read(BUNNY_TET)
    vertices = np.asarray(m.points, dtype=np.float64)
    tets = np.asarray(m.cells_dict["tetra"], dtype=np.int64)
    surf_v, surf_t = load_surface(BUNNY_OFF)
    t0 = time.perf_counter()
    emb = embed_points(surf_v, vertices, tets)
    elapsed = time.perf_counter() - t0
    return vertices, tets, surf_v, surf_t, emb, elapsed


def test_bunny_embedding_inside_within_reported_distance(bunny):
    vertices, tets, surf_v, surf_t, emb, elapsed = bunny
    assert surf_v.shape == (3485, 3) and surf_t.shape == (6966, 3)
    assert emb.num_points == 3485
    used = np.unique(tets)
    diag = float(np.linalg.norm(vertices[used].max(0) - vertices[used].min(0)))
    rel = emb.max_outside_distance / diag
    print(f"bunny embed: {elapsed:.3f} s, outside {emb.num_outside}, max dist {emb.max_outside_distance:.3e} "
          f"({rel:.2e} of bbox diagonal)")
    # speed is measured in kernels_bench/, never asserted here (the time is printed for information)
    assert rel < 1e-6  # the surface vertices are (float32 copies of) tet mesh vertices
    # every point is inside its tet or within the reported distance
    assert np.all(emb.distances <= emb.max_outside_distance)
    assert np.all(emb.distances[~emb.outside] == 0.0)
    assert np.all(emb.weights[~emb.outside].min(axis=1) >= -1e-10)
    # the reported distance is the distance to the chosen tet
    d = point_tet_distance(surf_v, vertices[emb.vertex_ids], emb.weights)
    np.testing.assert_allclose(d, emb.distances, atol=1e-15)
    # W X reproduces the rest positions (also for extrapolated points)
    W = emb.matrix()
    assert W.shape == (3485, vertices.shape[0])
    assert np.all(np.diff(W.indptr) == 4)
    np.testing.assert_allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0, atol=1e-13)
    np.testing.assert_allclose(W @ vertices, surf_v, atol=1e-12)


def test_bunny_affine_reproduction_numpy_and_warp(bunny):
    vertices, tets, surf_v, _, emb, _ = bunny
    rng = np.random.default_rng(0)
    A, c = random_affine(rng)
    x = vertices @ A.T + c
    expected = surf_v @ A.T + c
    np.testing.assert_allclose(emb.matrix() @ x, expected, atol=1e-10, rtol=0)
    np.testing.assert_allclose(emb.apply(x), expected, atol=1e-10, rtol=0)

    sk64 = SurfaceSkinner(emb, tets, device="cpu", precision="float64")
    xw = wp.array(x, dtype=wp.vec3d, device="cpu")
    out = sk64.apply(xw)
    assert out.dtype == wp.vec3d and out.shape == (3485,)
    np.testing.assert_allclose(out.numpy(), expected, atol=1e-10, rtol=0)

    sk32 = SurfaceSkinner(emb, tets, device="cpu", precision="float32")
    out32 = sk32.apply_numpy(x)
    assert out32.dtype == np.float32
    np.testing.assert_allclose(out32, expected, atol=1e-5, rtol=0)


def test_box_affine_weight_one_at_vertex():
    vertices, tets = box_mesh((2, 2, 2))
    rng = np.random.default_rng(1)
    inside = rng.uniform(0.0, 1.0, (200, 3))
    corners = vertices[[0, 5, 13, 26]]  # mesh vertices (corner, edge, centre, far corner)
    pts = np.concatenate([inside, corners])
    emb = embed_points(pts, vertices, tets)
    assert emb.num_outside == 0 and emb.max_outside_distance == 0.0
    assert np.all(emb.weights.min(axis=1) >= -1e-12)
    for row, v in zip(range(200, 204), [0, 5, 13, 26]):
        j = np.nonzero(emb.vertex_ids[row] == v)[0]
        assert j.size == 1
        assert abs(emb.weights[row, j[0]] - 1.0) < 1e-12
        assert np.abs(np.delete(emb.weights[row], j[0])).max() < 1e-12
    A, c = random_affine(rng)
    np.testing.assert_allclose(emb.apply(vertices @ A.T + c), pts @ A.T + c, atol=1e-12, rtol=0)
    sk = SurfaceSkinner(emb, tets, device="cpu", precision="float64")
    np.testing.assert_allclose(sk.apply_numpy(vertices @ A.T + c), pts @ A.T + c, atol=1e-12, rtol=0)


def _brute_force_nearest_distance(p, vertices, tets):
    X = vertices[tets]
    return point_tet_distance(np.repeat(p[None], len(tets), 0), X).min()


def test_box_outside_points_extrapolate():
    vertices, tets = box_mesh((3, 3, 3), size=(1.0, 1.0, 1.0))
    pts = np.array([[1.5, 0.5, 0.5], [-0.2, -0.3, 0.5], [2.0, 2.0, 2.0], [0.5, 0.5, 0.5], [0.5, 1.0 + 1e-3, 0.25]])
    expected_d = np.array([0.5, np.sqrt(0.13), np.sqrt(3.0), 0.0, 1e-3])
    emb = embed_points(pts, vertices, tets)
    np.testing.assert_allclose(emb.distances, expected_d, atol=1e-12, rtol=0)
    assert emb.outside.tolist() == [True, True, True, False, True]
    assert emb.num_outside == 4
    assert emb.max_outside_distance == pytest.approx(np.sqrt(3.0), abs=1e-12)
    for i in range(5):
        np.testing.assert_allclose(emb.distances[i], _brute_force_nearest_distance(pts[i], vertices, tets), atol=1e-12)
    # extrapolated: some coordinate negative, still sum to 1, still reproduce affine maps
    assert np.all(emb.weights[emb.outside].min(axis=1) < 0.0)
    np.testing.assert_allclose(emb.weights.sum(axis=1), 1.0, atol=1e-14)
    rng = np.random.default_rng(2)
    A, c = random_affine(rng)
    np.testing.assert_allclose(emb.matrix() @ (vertices @ A.T + c), pts @ A.T + c, atol=1e-10, rtol=0)
    sk = SurfaceSkinner(emb, tets, device="cpu", precision="float32")
    np.testing.assert_allclose(sk.apply_numpy(vertices @ A.T + c), pts @ A.T + c, atol=1e-5, rtol=0)


def test_orientation_does_not_matter():
    vertices, tets = box_mesh((2, 1, 1), size=(2.0, 1.0, 1.0))
    flipped = tets.copy()
    flipped[::2, [0, 1]] = flipped[::2, [1, 0]]  # half the tets negatively oriented
    pts = np.array([[0.3, 0.2, 0.7], [1.7, 0.9, 0.1], [2.5, 0.5, 0.5]])
    a = embed_points(pts, vertices, tets)
    b = embed_points(pts, vertices, flipped)
    np.testing.assert_allclose(a.matrix().toarray(), b.matrix().toarray(), atol=1e-14)
    np.testing.assert_allclose(b.distances, [0.0, 0.0, 0.5], atol=1e-12)
    # boundary surface is the same (outward) for both orientations
    for t in (tets, flipped):
        ids, tri = mesh_boundary_surface(vertices, t)
        assert tri.shape == (20, 3)
        Y = vertices[ids][tri]
        volume = np.einsum("ij,ij->i", np.cross(Y[:, 1], Y[:, 2]), Y[:, 0]).sum() / 6.0
        assert volume == pytest.approx(2.0, abs=1e-12)  # positive: outward normals
        normals = np.cross(Y[:, 1] - Y[:, 0], Y[:, 2] - Y[:, 0])
        assert np.all(np.einsum("ij,ij->i", normals, Y.mean(axis=1) - np.array([1.0, 0.5, 0.5])) > 0)


def test_boundary_surface_box_counts():
    vertices, tets = box_mesh((3, 2, 2))
    ids, tri = mesh_boundary_surface(vertices, tets)
    assert tri.shape[0] == 2 * 2 * (3 * 2 + 3 * 2 + 2 * 2)
    on_boundary = np.any((vertices == 0.0) | (vertices == 1.0), axis=1)
    assert set(ids.tolist()) == set(np.nonzero(on_boundary)[0].tolist())
    assert tri.min() == 0 and tri.max() == ids.size - 1


def test_load_surface_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.obj"):
        load_surface(tmp_path / "missing.obj")
    p = tmp_path / "points.off"
    p.write_text("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(SurfaceError, match="no triangles"):
        load_surface(p)
    q = tmp_path / "surf.txt"
    q.write_text("x")
    with pytest.raises(SurfaceError, match="unsupported"):
        load_surface(q)
    r = tmp_path / "quad.obj"
    r.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    v, t = load_surface(r)
    assert v.shape == (4, 3) and t.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_skinner_rejects_wrong_input():
    vertices, tets = box_mesh((1, 1, 1))
    emb = embed_points(np.array([[0.2, 0.3, 0.4]]), vertices, tets)
    sk = SurfaceSkinner(emb, tets, device="cpu", precision="float64")
    with pytest.raises(TypeError, match="vec3"):
        sk.apply(wp.array(vertices, dtype=wp.vec3, device="cpu"))
    with pytest.raises(ValueError, match="vertices"):
        sk.apply(wp.zeros(3, dtype=wp.vec3d, device="cpu"))
    with pytest.raises(ValueError, match="precision"):
        SurfaceSkinner(emb, tets, device="cpu", precision="float16")
    with pytest.raises(ValueError, match="points"):
        embed_points(np.zeros((2, 2)), vertices, tets)
    with pytest.raises(ValueError, match="tet 0"):
        embed_points(np.zeros((1, 3)), vertices, tets + 100)


# ----------------------------------------------------------------------------- every element type
def _element_mesh(etype):
    """A small mesh of each element type; hexes with a moved interior node (non-affine elements)."""
    from warpfem.mesh import ElementMesh, box_hex_mesh, tet10_from_tet4
    from warpfem.mesh import box_tet_mesh

    if etype in ("tet4", "tet10"):
        m = box_tet_mesh(size=(2.0, 1.0, 1.0), cells=(2, 1, 1))
        return m if etype == "tet4" else tet10_from_tet4(m)
    m = box_hex_mesh(size=(2.0, 1.0, 1.0), cells=(2, 2, 2), order=1 if etype == "hex8" else 2)
    X = m.vertices.copy()
    centre = np.flatnonzero(np.all(np.abs(X - [1.0, 0.5, 0.5]) < 1e-12, axis=1))[0]
    X[centre] += [0.08, -0.05, 0.03]  # the shared interior node: every element becomes non-affine
    return ElementMesh(X, m.elements, etype)


@pytest.mark.parametrize("etype,k", [("tet4", 4), ("tet10", 10), ("hex8", 8), ("hex27", 27)])
def test_every_element_type_skins_affine_motion_exactly_on_device(etype, k):
    from warpfem.skinning import embed_points_in_mesh

    mesh = _element_mesh(etype)
    rng = np.random.default_rng(7)
    inside = rng.uniform([0.05, 0.05, 0.05], [1.95, 0.95, 0.95], (60, 3))
    nodes = [0, mesh.num_vertices - 1, int(np.argmin(np.linalg.norm(mesh.vertices - [1.0, 0.5, 0.5], axis=1)))]
    if etype in ("tet10", "hex27"):
        nodes.append(mesh.num_vertices // 2)  # a mid-edge / mid-face node as well
    outside = np.array([[2.2, 0.5, 0.5], [-0.1, 1.05, 0.4]])
    pts = np.concatenate([inside, mesh.vertices[nodes], outside])
    emb = embed_points_in_mesh(pts, mesh)
    assert emb.vertex_ids.shape == (len(pts), k) and emb.weights.shape == (len(pts), k)
    assert emb.weights_per_point == k and emb.element_type == etype
    np.testing.assert_allclose(emb.weights.sum(axis=1), 1.0, atol=1e-12)
    assert emb.outside.tolist() == [False] * (len(pts) - 2) + [True, True]
    np.testing.assert_allclose(emb.distances[-2:], [0.2, np.sqrt(0.1 ** 2 + 0.05 ** 2)], atol=1e-12)
    # a point at a node: weight 1 there, 0 elsewhere
    for row, v in zip(range(60, 60 + len(nodes)), nodes):
        j = np.flatnonzero(emb.vertex_ids[row] == v)
        assert j.size == 1, (etype, v, emb.vertex_ids[row])
        assert abs(emb.weights[row, j[0]] - 1.0) < 1e-10
        assert np.abs(np.delete(emb.weights[row], j[0])).max() < 1e-10
    W = emb.matrix()
    assert W.shape == (len(pts), mesh.num_vertices) and np.all(np.diff(W.indptr) == k)
    A, c = random_affine(rng)
    x = mesh.vertices @ A.T + c
    expected = pts @ A.T + c
    np.testing.assert_allclose(W @ x, expected, atol=1e-10, rtol=0)
    sk = SurfaceSkinner(emb, mesh, device="cpu", precision="float64")  # the Warp kernel, k weights a row
    assert sk.weights_per_point == k
    np.testing.assert_allclose(sk.apply_numpy(x), expected, atol=1e-10, rtol=0)
    sk32 = SurfaceSkinner(emb, mesh.elements, device="cpu", precision="float32")
    np.testing.assert_allclose(sk32.apply_numpy(x), expected, atol=2e-5, rtol=0)
    if etype != "tet4":
        with pytest.raises(ValueError, match=rf"\(m, {k}\)"):
            SurfaceSkinner(emb, mesh.corner_tets(), device="cpu")


def test_hex27_skinning_follows_quadratic_motion():
    """Beyond affine: a Hex27 embedding reproduces a quadratic displacement field exactly."""
    from warpfem.skinning import embed_points_in_mesh

    from warpfem.mesh import box_hex_mesh

    # on an undistorted grid the map from reference coordinates is affine, so a field quadratic in X
    # is quadratic in the reference coordinates: exactly representable by the 27 shape functions
    grid = box_hex_mesh(size=(2.0, 1.0, 1.0), cells=(2, 2, 2), order=2)
    pts = np.random.default_rng(3).uniform([0.05, 0.05, 0.05], [1.95, 0.95, 0.95], (40, 3))
    emb = embed_points_in_mesh(pts, grid)

    def bend(X):
        return np.stack([X[:, 0], X[:, 1] + 0.1 * X[:, 0] ** 2, X[:, 2] - 0.2 * X[:, 1] * X[:, 0]], axis=1)

    sk = SurfaceSkinner(emb, grid, device="cpu", precision="float64")
    np.testing.assert_allclose(sk.apply_numpy(bend(grid.vertices)), bend(pts), atol=1e-12, rtol=0)
