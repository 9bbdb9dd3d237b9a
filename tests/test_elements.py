"""Element library (Tet4, Tet10, Hex8, Hex27): quadrature, shape functions, patch tests, cantilever,
selective reduced integration, masses, meshes, file I/O and embedding."""

from math import factorial

import numpy as np
import pytest
import scipy.sparse.linalg as spla

import warpfem as wf
from warpfem.elements import ElementError, precompute_quadrature
from warpfem.mesh import ElementMesh, box_hex_mesh, embed_points_in_elements, load_element_mesh, save_element_mesh, tet10_from_tet4
from warpfem.mesh import consistent_mass as consistent_mass_matrix, lumped_mass as lumped_mass_vector
from warpfem.mesh.element_types import ELEMENTS, gauss_rule, shape_functions, shape_gradients

ELEMENT_TYPES = tuple(ELEMENTS)
REFERENCE_NODES = {n: e.reference_nodes for n, e in ELEMENTS.items()}
RULE_DEGREE = {(n, purpose): d for n, e in ELEMENTS.items() for purpose, d in e.rule_degree.items()}

TIMOSHENKO = 1.512


def _box(et, cells, size=(1.0, 1.0, 1.0)):
    if et == "tet4":
        return wf.box_tet_mesh(size=size, cells=cells)
    if et == "tet10":
        return tet10_from_tet4(wf.box_tet_mesh(size=size, cells=cells))
    return box_hex_mesh(size=size, cells=cells, order=1 if et == "hex8" else 2)


# -- reference element --------------------------------------------------------------------------
@pytest.mark.parametrize("et,purpose", sorted(RULE_DEGREE))
def test_quadrature_exact_to_stated_degree(et, purpose):
    if purpose == "volumetric":
        pts, w = gauss_rule(et, "volumetric")
    else:
        pts, w = gauss_rule(et, purpose)
    deg = RULE_DEGREE[(et, purpose)]
    worst = 0.0
    for a in range(deg + 1):
        for b in range(deg + 1):
            for c in range(deg + 1):
                if et.startswith("tet"):
                    if a + b + c > deg:
                        continue
                    exact = factorial(a) * factorial(b) * factorial(c) / factorial(a + b + c + 3)
                else:  # tensor degree per variable on [-1, 1]^3
                    exact = np.prod([0.0 if p % 2 else 2.0 / (p + 1) for p in (a, b, c)])
                val = np.sum(w * pts[:, 0] ** a * pts[:, 1] ** b * pts[:, 2] ** c)
                worst = max(worst, abs(val - exact))
    assert worst < 1e-14
    if et.startswith("tet"):  # and the rule is not exact one degree higher (the stated degree is sharp)
        exact = factorial(deg + 1) / factorial(deg + 4)
        assert abs(np.sum(w * pts[:, 0] ** (deg + 1)) - exact) > 1e-8


@pytest.mark.parametrize("et", ELEMENT_TYPES)
def test_shape_functions_partition_of_unity_kronecker_and_gradients(et, rng):
    nodes = REFERENCE_NODES[et]
    np.testing.assert_allclose(shape_functions(et, nodes), np.eye(len(nodes)), atol=1e-14)
    xi = rng.uniform(0.0, 0.3, (20, 3)) if et.startswith("tet") else rng.uniform(-1, 1, (20, 3))
    N, dN = shape_functions(et, xi), shape_gradients(et, xi)
    np.testing.assert_allclose(N.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(dN.sum(axis=1), 0.0, atol=1e-13)
    # linear completeness: sum_a N_a X_a = xi, sum_a X_a dN_a^T = I
    np.testing.assert_allclose(N @ nodes, xi, atol=1e-14)
    np.testing.assert_allclose(np.einsum("ai,paj->pij", nodes, dN), np.broadcast_to(np.eye(3), (20, 3, 3)), atol=1e-13)
    # gradients are the derivatives of the shape functions (central differences)
    h = 1e-6
    for d in range(3):
        e = np.zeros(3)
        e[d] = h
        fd = (shape_functions(et, xi + e) - shape_functions(et, xi - e)) / (2 * h)
        np.testing.assert_allclose(dN[:, :, d], fd, atol=1e-8)


def test_inverted_element_is_rejected_by_name():
    mesh = box_hex_mesh(size=(2, 1, 1), cells=(2, 1, 1))
    el = mesh.elements.copy()
    el[1] = el[1][[4, 5, 6, 7, 0, 1, 2, 3]]  # mirrored: det J < 0
    with pytest.raises(ElementError, match=r"hex8 .*first: \[1\]"):
        precompute_quadrature(mesh.vertices, el, "hex8")
    with pytest.raises(wf.MeshError, match=r"element 0 references vertex index \d+ out of range \[0, "):
        ElementMesh(mesh.vertices, el + 100, "hex8")
    with pytest.raises(ValueError, match="only available for hex8"):
        wf.Model(_box("tet10", (1, 1, 1)), wf.LinearElastic(youngs_modulus=1.0, poisson_ratio=0.3, density=1.0),
                 volumetric_integration="reduced")
    with pytest.raises(ValueError, match=r"poisson_ratio >= 0.*got poisson_ratio=-0.2 for Corotated"):
        wf.Model(mesh, wf.Corotated(youngs_modulus=1.0, poisson_ratio=-0.2, density=1.0),
                 volumetric_integration="reduced")

    class NoSplit(wf.LinearElastic):
        volumetric_split = None

    with pytest.raises(ValueError, match="volumetric_split.*NoSplit has none"):
        wf.Model(mesh, NoSplit(youngs_modulus=1.0, poisson_ratio=0.3, density=1.0), volumetric_integration="reduced")


# -- linear patch test --------------------------------------------------------------------------
def _jittered(et, seed=0, *, curved=True, hex_cells=2):
    """Unit cube with interior nodes jittered by up to 12 % of the node spacing (hexes: hex_cells^3
    cells; 2 leaves a single interior node, 3 gives 8).

    Tet10 is built from a jittered Tet4 mesh (straight edges: a curved Tet10 is not integrated
    exactly by the 4-point rule). Hex8 and curved Hex27 elements are non-affine; ``curved=False``
    places the Hex27 nodes by the trilinear map of jittered corners instead."""
    rng = np.random.default_rng(seed)
    if et in ("tet4", "tet10"):
        base = wf.box_tet_mesh(size=(1, 1, 1), cells=(3, 3, 3))
        X = base.vertices.copy()
        inner = np.all((X > 1e-9) & (X < 1 - 1e-9), axis=1)
        X[inner] += rng.uniform(-0.12, 0.12, (inner.sum(), 3)) / 3
        mesh = ElementMesh(X, base.tets, "tet4")
        if et == "tet10":
            mesh = tet10_from_tet4(mesh)
    else:
        mesh = box_hex_mesh(size=(1, 1, 1), cells=(hex_cells,) * 3, order=1 if et == "hex8" else 2)
        X = mesh.vertices.copy()
        inner = np.all((X > 1e-9) & (X < 1 - 1e-9), axis=1)
        spacing = (1.0 if et == "hex8" else 0.5) / hex_cells
        if et == "hex27" and not curved:
            corner = np.zeros(len(X), bool)
            corner[mesh.elements[:, :8].ravel()] = True
            X[inner & corner] += rng.uniform(-0.12, 0.12, ((inner & corner).sum(), 3)) * spacing
            N8 = shape_functions("hex8", REFERENCE_NODES["hex27"])  # (27, 8)
            X[mesh.elements] = np.einsum("qa,mai->mqi", N8, X[mesh.elements[:, :8]])
        else:
            X[inner] += rng.uniform(-0.12, 0.12, (inner.sum(), 3)) * spacing
        mesh = ElementMesh(X, mesh.elements, et)
    X = mesh.vertices
    interior = np.all((X > 1e-9) & (X < 1 - 1e-9), axis=1)
    return mesh, interior


@pytest.mark.parametrize("et,vi", [(et, "full") for et in ELEMENT_TYPES] + [("hex8", "reduced")])
def test_linear_patch_test(et, vi):
    mesh, interior = _jittered(et, hex_cells=3 if vi == "reduced" else 2)
    X = mesh.vertices
    if et.startswith("hex"):  # the jitter made the hexes non-affine: det J varies inside an element
        det = precompute_quadrature(X, mesh.elements, et).qp_weight.reshape(mesh.num_elements, -1)
        assert np.ptp(det, axis=1).max() > 1e-3 * det.max()
    A = 1e-3 * np.array([[1, 0.2, 0.1], [0.3, -0.5, 0.4], [0, 0.1, 0.7]])
    c = np.array([0.01, -0.02, 0.005])
    exact = X + X @ A.T + c
    boundary = np.flatnonzero(~interior)
    mat = wf.LinearElastic(youngs_modulus=21.0, poisson_ratio=0.45, density=1.0)
    model = wf.Model(mesh, mat, volumetric_integration=vi)
    model.fix(boundary)
    sim = wf.Simulator(model, precision="float64", tol=1e-10, cg_tol=1e-12, max_iters=20)
    sim.set_targets(boundary, exact[boundary])
    assert sim.solve_static().converged
    u, u_exact = sim.positions() - X, exact - X
    assert np.abs(u[interior] - u_exact[interior]).max() < 1e-9 * np.abs(u_exact).max()
    eps = 0.5 * (A + A.T)
    sigma = mat.lam_lame * np.trace(eps) * np.eye(3) + 2 * mat.mu_lame * eps
    assert np.abs(sim.stresses() - sigma).max() < 1e-8 * np.abs(sigma).max()
    f = sim.elastic_forces()
    assert np.abs(f.sum(axis=0)).max() < 1e-9 * np.abs(f).max()


# -- cantilever under self-weight (shared/reference section 1) ---------------------------------------
def _cantilever(et, cells, *, nu=0.0, vi="full", consistent_load=False, iterative=False):
    mesh = _box(et, cells, size=(10.0, 1.0, 1.0))
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=1e4, poisson_ratio=nu, density=1.0), gravity=(0, 0, -1.0),
                     volumetric_integration=vi)
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 2, 2)))
    if consistent_load:  # rho g int N_a dV (row sums of the consistent mass) instead of the lumped mass
        model.forces[:] = (np.asarray(consistent_mass_matrix(mesh, 1.0).sum(axis=1)).ravel() - model.gravity_mass)[:, None] \
            * model.gravity[None, :]
    sim = wf.Simulator(model, precision="float64", tol=1e-8, cg_tol=1e-10)
    X = mesh.vertices
    if iterative:
        assert sim.solve_static().converged
        u = sim.positions() - X
    else:  # direct solve of the Warp-assembled stiffness (nu -> 0.5 makes CG very slow)
        K = sim.stiffness_matrix().tocsr()
        f = model.external_forces().ravel()
        free = ~model.fixed.ravel()
        u = np.zeros_like(f)
        u[free] = spla.spsolve(K[free][:, free].tocsc(), f[free])
        u = u.reshape(-1, 3)
    tip = np.abs(X[:, 0] - 10) < 1e-9
    return -u[tip, 2].mean(), model


def test_cantilever_tet10_matches_timoshenko_and_independent_fe():
    d, model = _cantilever("tet10", (20, 2, 2), iterative=True)
    assert abs(d / TIMOSHENKO - 1) < 0.002
    # with the consistent load vector the independent FE code's Tet10 value is reproduced
    d1, _ = _cantilever("tet10", (10, 1, 1), consistent_load=True)
    assert d1 == pytest.approx(1.50884, rel=2e-5)


@pytest.mark.parametrize("et", ELEMENT_TYPES)
@pytest.mark.parametrize("mass", ["lumped", "consistent"])
def test_total_body_force_is_rho_g_v_and_free_fall_is_exact(et, mass):
    mesh = _box(et, (4, 1, 1), size=(10.0, 1.0, 1.0))
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=1e4, poisson_ratio=0.3, density=1.0), gravity=(0, 0, -1.0),
                     mass_matrix=mass)
    np.testing.assert_allclose(model.external_forces().sum(axis=0), [0, 0, -10.0], rtol=1e-12, atol=1e-12)
    assert model.total_mass == pytest.approx(10.0, rel=1e-12)
    # one backward Euler step of an unconstrained body from rest: v = g h at every node
    sim = wf.Simulator(model, precision="float64", dt=0.1, tol=1e-12, cg_tol=1e-12)
    assert sim.step().converged
    np.testing.assert_allclose(sim.velocities(), np.tile([0, 0, -0.1], (mesh.num_vertices, 1)), atol=1e-10)


def test_cantilever_hex8_and_tet4_lock_from_below_and_converge_monotonically():
    h = [_cantilever("hex8", (10 * r, r, r))[0] for r in (1, 2, 4)]
    assert h[0] < h[1] < h[2] < TIMOSHENKO
    assert h[2] > 0.95 * TIMOSHENKO  # 40x4x4 gives 0.9695 x 1.512
    t = [_cantilever("tet4", (10 * r, r, r))[0] for r in (1, 2)]
    assert t[0] < t[1] < h[1]
    d27, _ = _cantilever("hex27", (10, 1, 1))
    assert abs(d27 / TIMOSHENKO - 1) < 0.002


def test_selective_reduced_hex8_does_not_lock_near_incompressible():
    nu = 0.4999
    tet10, _ = _cantilever("tet10", (20, 2, 2), nu=nu)
    red, _ = _cantilever("hex8", (20, 2, 2), nu=nu, vi="reduced")
    full, _ = _cantilever("hex8", (20, 2, 2), nu=nu)
    tet4, _ = _cantilever("tet4", (20, 2, 2), nu=nu)
    assert abs(red / tet10 - 1) < 0.03  # 1.3829 vs 1.4054
    assert full < 0.2 * tet10 and tet4 < 0.05 * tet10  # locked: 0.234 and 0.021
    # with lambda = 0 (nu = 0) the split is exact: reduced == full
    a, _ = _cantilever("hex8", (10, 1, 1), vi="reduced")
    b, _ = _cantilever("hex8", (10, 1, 1))
    assert a == pytest.approx(b, rel=1e-10)


def test_reduced_integration_force_is_energy_gradient_and_dynamic_step(rng):
    mesh = box_hex_mesh(size=(2, 1, 1), cells=(2, 1, 1))
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=100.0, poisson_ratio=0.49, density=2.0),
                     gravity=(0, 0, -9.81), volumetric_integration="reduced", mass_matrix="consistent")
    sim = wf.Simulator(model, precision="float64", dt=0.01)
    x = mesh.vertices + 0.01 * rng.standard_normal(mesh.vertices.shape)
    f = sim.elastic_forces(x)
    for d in rng.choice(x.size, 6, replace=False):
        xp, xm = x.copy(), x.copy()
        xp.flat[d] += 1e-6
        xm.flat[d] -= 1e-6
        assert abs(-(sim.elastic_energy(xp) - sim.elastic_energy(xm)) / 2e-6 - f.flat[d]) < 1e-6 * np.abs(f).max()
    # energy: psi = mu eps:eps on 2x2x2 + lam/2 tr(eps)^2 at the centre, for a homogeneous strain the full value
    A = 1e-3 * np.array([[1, 0.2, 0.1], [0.3, -0.5, 0.4], [0, 0.1, 0.7]])
    eps = 0.5 * (A + A.T)
    mat = model.material
    psi = mat.mu_lame * np.sum(eps * eps) + 0.5 * mat.lam_lame * np.trace(eps) ** 2
    assert sim.elastic_energy(mesh.vertices + mesh.vertices @ A.T) == pytest.approx(2.0 * psi, rel=1e-10)
    st = sim.step()  # free fall of the whole body for one backward Euler step: v = g h
    assert st.converged
    np.testing.assert_allclose(sim.velocities(), np.tile([0, 0, -9.81 * 0.01], (mesh.num_vertices, 1)), atol=1e-9)


# -- masses ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("et", ELEMENT_TYPES)
def test_masses_positive_and_total(et):
    mesh, _ = _jittered(et, seed=5, curved=False)
    rho = 7.0
    vol = mesh.total_volume()
    assert vol == pytest.approx(1.0, rel=1e-12)
    m = lumped_mass_vector(mesh, rho)
    assert m.min() > 0 and m.sum() == pytest.approx(rho * vol, rel=1e-12)
    M = consistent_mass_matrix(mesh, rho)
    ones = np.ones(mesh.num_vertices)
    assert ones @ M @ ones == pytest.approx(rho * vol, rel=1e-12)
    # the consistent mass integrates the kinetic energy of a linear velocity field exactly
    X = mesh.vertices
    v = X[:, 0] - 0.5 * X[:, 2]  # int (x - z/2)^2 over the unit cube = 1/3 + 1/12 - 1/4
    assert v @ M @ v == pytest.approx(rho * (1 / 3 + 1 / 12 - 1 / 4), rel=1e-10)
    if et == "tet10":  # row sums would make corner masses negative: HRZ keeps them positive
        rows = np.asarray(M.sum(axis=1)).ravel()
        assert rows.min() < 0
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=1.0, poisson_ratio=0.3, density=rho), mass_matrix="consistent")
    np.testing.assert_allclose(model.lumped_mass, m, rtol=1e-12)
    assert abs(model.mass - M).max() < 1e-12


# -- meshes, I/O, embedding -------------------------------------------------------------------------
def test_generators_share_nodes_and_boundary_is_closed_outward():
    t10 = tet10_from_tet4(wf.box_tet_mesh(size=(1, 1, 1), cells=(2, 2, 2)))
    assert t10.num_vertices == 5 ** 3  # shared edge mid-nodes fill the doubled grid exactly
    h27 = box_hex_mesh(size=(2, 1, 1), cells=(2, 1, 1), order=2)
    assert h27.num_vertices == 5 * 3 * 3 and h27.num_elements == 2
    for mesh in (t10, h27, box_hex_mesh(size=(2, 1, 3), cells=(2, 2, 3)), _jittered("hex27")[0]):
        F = mesh.boundary_faces()
        X = mesh.vertices
        a, b, c = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
        # divergence theorem: 1/6 sum (a . (b x c)) = enclosed volume for a closed outward surface
        assert np.einsum("ij,ij->", a, np.cross(b, c)) / 6 == pytest.approx(mesh.total_volume(), rel=1e-12)
        edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        assert (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()  # watertight


@pytest.mark.parametrize("et", ELEMENT_TYPES)
@pytest.mark.parametrize("ext", [".vtu", ".msh"])
def test_meshio_roundtrip(et, ext, tmp_path):
    mesh, _ = _jittered(et, seed=2)
    path = save_element_mesh(mesh, tmp_path / f"m{ext}")
    back = load_element_mesh(path)
    assert back.element_type == et
    np.testing.assert_array_equal(back.elements, mesh.elements)
    np.testing.assert_allclose(back.vertices, mesh.vertices, rtol=1e-15)


def test_load_element_mesh_errors(tmp_path):
    import meshio

    p = tmp_path / "tri.vtu"
    meshio.write(p, meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(wf.MeshError, match="no supported volume cells.*triangle"):
        load_element_mesh(p)


@pytest.mark.parametrize("et", ELEMENT_TYPES)
def test_embedding_reproduces_points_and_follows_deformation(et, rng):
    mesh, _ = _jittered(et, seed=3)
    X = mesh.vertices
    pts = rng.uniform(0.02, 0.98, (40, 3))
    ids, w, elem = embed_points_in_elements(pts, mesh)
    k = mesh.elements.shape[1]
    assert ids.shape == (40, k) and w.shape == (40, k)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("pa,pai->pi", w, X[ids]), pts, atol=1e-12)
    # an affine deformation of the mesh moves the embedded points affinely
    A = np.array([[1.1, 0.2, 0], [0, 0.9, 0.1], [0.05, 0, 1.2]])
    x = X @ A.T
    np.testing.assert_allclose(np.einsum("pa,pai->pi", w, x[ids]), pts @ A.T, atol=1e-12)


def test_boundary_surface_of_hex27_exports_to_usd_and_follows_simulation(tmp_path):
    from warpfem.io.usd import UsdMeshWriter, read_usd_mesh_frames, usd_validation_errors

    mesh = wf.box_hex_mesh(size=(2, 1, 1), cells=(2, 1, 1), order=2)
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e4, poisson_ratio=0.3, density=100.0), gravity=(0, 0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 2, 2)))
    sim = wf.Simulator(model, precision="float64", dt=0.02)
    faces = mesh.boundary_faces()
    path = tmp_path / "hex27.usda"
    with UsdMeshWriter(path, fps=50) as w:
        w.add_mesh("beam", faces, mesh.num_vertices)
        for frame in range(3):
            w.write_frame(frame, {"beam": sim.positions()})
            assert sim.step().converged
    assert usd_validation_errors(path) == []
    times, frames = read_usd_mesh_frames(path, "beam")
    assert len(frames) == 3 and frames[0].shape == (mesh.num_vertices, 3)
    np.testing.assert_allclose(frames[0], mesh.vertices, atol=1e-6)
    # the tip sagged under gravity (nodes with x = 2 moved down)
    tip = np.abs(mesh.vertices[:, 0] - 2) < 1e-9
    assert (sim.positions() - mesh.vertices)[tip, 2].max() < 0


@pytest.mark.parametrize("et", ["tet10", "hex8", "hex27"])
def test_finite_strain_patch_test_nonlinear_material(et):
    mesh, interior = _jittered(et, seed=7, curved=False)
    X = mesh.vertices
    F0 = np.array([[1.3, 0.2, 0.0], [0.0, 0.8, 0.1], [0.0, 0.0, 1.1]])
    exact = X @ F0.T + np.array([0.1, 0.2, -0.3])
    boundary = np.flatnonzero(~interior)
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=21.0, poisson_ratio=0.45, density=1.0))
    model.fix(boundary)
    sim = wf.Simulator(model, precision="float64", tol=1e-10, cg_tol=1e-12, max_iters=40)
    sim.set_targets(boundary, exact[boundary])
    assert sim.solve_static(load_steps=2).converged
    np.testing.assert_allclose(sim.positions(), exact, atol=1e-8)


@pytest.mark.parametrize("et", ["tet10", "hex27"])
def test_higher_order_force_and_hessian_match_finite_differences(et, rng):
    mesh = _box(et, (1, 1, 1))
    sim = wf.Simulator(wf.Model(mesh, wf.Corotated(youngs_modulus=10.0, poisson_ratio=0.3, density=1.0)), precision="float64")
    _check_energy_force_hessian_fd(sim, mesh.vertices + 0.05 * rng.standard_normal(mesh.vertices.shape), rng)


def _check_energy_force_hessian_fd(sim, x, rng, eps=1e-6):
    """-dV/dx = force and -dforce/dx = unprojected stiffness, central differences on 6 random DOFs."""
    f = sim.elastic_forces(x)
    K = sim.stiffness_matrix(x, project=False).toarray()
    for d in rng.choice(x.size, 6, replace=False):
        xp, xm = x.copy(), x.copy()
        xp.flat[d] += eps
        xm.flat[d] -= eps
        assert abs(-(sim.elastic_energy(xp) - sim.elastic_energy(xm)) / (2 * eps) - f.flat[d]) < 1e-6 * np.abs(f).max()
        col = -(sim.elastic_forces(xp) - sim.elastic_forces(xm)).ravel() / (2 * eps)
        np.testing.assert_allclose(K[:, d], col, atol=1e-6 * np.abs(K).max())
    return f


# -- selective reduced integration for every material ------------------------------------------------
MATERIAL_CLASSES = [wf.LinearElastic, wf.StVenantKirchhoff, wf.Corotated, wf.StableNeoHookean]
NONLINEAR = [wf.StVenantKirchhoff, wf.Corotated, wf.StableNeoHookean]


@pytest.mark.parametrize("cls", MATERIAL_CLASSES, ids=lambda c: c.name)
def test_volumetric_split_is_exact_and_each_part_psd_at_rest(cls, rng):
    from warpfem.materials import evaluate

    mat = cls(youngs_modulus=3.0, poisson_ratio=0.45, density=1.0)
    (mf, lf), (mv, lv) = mat.volumetric_split()
    F = np.eye(3) + 0.3 * rng.standard_normal((30, 3, 3))
    F[0] = np.diag([1.2, 0.9, -0.5])  # inverted
    full = evaluate(mat.kind, F, mat.kernel_mu, mat.kernel_lam)
    a = evaluate(mat.kind, F, mf, lf)
    b = evaluate(mat.kind, F, mv, lv)
    for key in ("psi", "pk1", "hessian"):
        np.testing.assert_allclose(a[key] + b[key], full[key], atol=1e-12 * np.abs(full[key]).max())
    assert mv == 0.0 and lv == pytest.approx(mat.lam_lame)  # the 1-point part is lambda_L-scaled only
    # at rest both parts are stress-free and PSD, so the per-part projection is exact there and the
    # split reduces to the linear one: mu eps:eps (+ 0 tr^2) on the full rule, lambda_L/2 tr(eps)^2 on 1 point
    I = np.eye(3)[None]
    lin = wf.LinearElastic(youngs_modulus=3.0, poisson_ratio=0.45, density=1.0)
    Ha = evaluate(mat.kind, I, mf, lf)["hessian_projected"][0]
    Hb = evaluate(mat.kind, I, mv, lv)["hessian_projected"][0]
    np.testing.assert_allclose(Ha, evaluate(0, I, lin.kernel_mu, 0.0)["hessian"][0], atol=1e-12 * lin.kernel_lam)
    np.testing.assert_allclose(Hb, evaluate(0, I, 0.0, lin.kernel_lam)["hessian"][0], atol=1e-12 * lin.kernel_lam)
    assert np.abs(evaluate(mat.kind, I, mf, lf)["pk1"]).max() < 1e-14 and np.abs(evaluate(mat.kind, I, mv, lv)["pk1"]).max() < 1e-14


@pytest.mark.parametrize("cls", NONLINEAR, ids=lambda c: c.name)
def test_sri_energy_force_hessian_consistent(cls, rng):
    mesh = box_hex_mesh(size=(2, 1, 1), cells=(2, 1, 1))
    X = mesh.vertices + 0.05 * rng.standard_normal(mesh.vertices.shape)  # non-affine hexes
    mesh = ElementMesh(X, mesh.elements, "hex8")
    mat = cls(youngs_modulus=10.0, poisson_ratio=0.48, density=1.0)
    sim = wf.Simulator(wf.Model(mesh, mat, volumetric_integration="reduced"), precision="float64")
    full = wf.Simulator(wf.Model(mesh, mat), precision="float64")
    x = X + 0.08 * rng.standard_normal(X.shape)
    f = _check_energy_force_hessian_fd(sim, x, rng)
    # the reduced energy really differs from the fully integrated one away from rest ...
    assert abs(sim.elastic_energy(x) / full.elastic_energy(x) - 1) > 1e-3
    # ... and the projected SRI Hessian (each part projected) is symmetric positive semi-definite
    Kp = sim.stiffness_matrix(x, project=True).toarray()
    np.testing.assert_allclose(Kp, Kp.T, atol=1e-12 * np.abs(Kp).max())
    assert np.linalg.eigvalsh(Kp).min() > -1e-10 * np.abs(Kp).max()
    # a rigid motion of x changes neither the energy nor the force magnitudes (frame invariance)
    R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    R *= np.linalg.det(R)
    assert sim.elastic_energy(x @ R.T + 0.3) == pytest.approx(sim.elastic_energy(x), rel=1e-10)
    np.testing.assert_allclose(sim.elastic_forces(x @ R.T), f @ R.T, atol=1e-10 * np.abs(f).max())


@pytest.mark.parametrize("cls", NONLINEAR, ids=lambda c: c.name)
def test_sri_finite_strain_patch_test(cls):
    mesh, interior = _jittered("hex8", seed=11, hex_cells=3)
    X = mesh.vertices
    assert interior.sum() == 8
    # sharpness: on these non-parallelepiped hexes the centroid gradients would leave interior forces
    # (sum_e w_c dN_a/dX(centre) != 0); the volume-averaged gradients of the 1-point set do not
    from warpfem.mesh.element_types import element_point_data, gauss_rule

    def interior_nodal_sum(w, g):  # max_a |sum_e w_e g_ea| over interior nodes, relative
        nodal = np.zeros_like(X)
        np.add.at(nodal, mesh.elements.ravel(), (w[:, None, None] * g.reshape(-1, 8, 3)).reshape(-1, 3))
        return np.abs(nodal[interior]).max() / np.abs(nodal).max()

    pts, wts = gauss_rule("hex8", "volumetric")
    det, g = element_point_data(X, mesh.elements, "hex8", pts)
    assert interior_nodal_sum(det[:, 0] * wts[0], g[:, 0]) > 1e-4
    vq = precompute_quadrature(X, mesh.elements, "hex8", volumetric_integration="reduced").volumetric
    assert interior_nodal_sum(vq.qp_weight, vq.qp_dNdX) < 1e-13

    c, s_ = np.cos(0.4), np.sin(0.4)
    F0 = np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]) @ np.array([[1.15, 0.1, 0.0], [0.0, 0.9, 0.05], [0.0, 0.0, 1.05]])
    exact = X @ F0.T + np.array([0.1, 0.2, -0.3])
    boundary = np.flatnonzero(~interior)
    model = wf.Model(mesh, cls(youngs_modulus=21.0, poisson_ratio=0.49, density=1.0), volumetric_integration="reduced")
    model.fix(boundary)
    sim = wf.Simulator(model, precision="float64", tol=1e-10, cg_tol=1e-12, max_iters=40)
    # the homogeneous deformation is an equilibrium of the SRI discretisation: no interior force
    f = sim.elastic_forces(exact)
    assert np.abs(f[interior]).max() < 1e-10 * np.abs(f).max()
    sim.set_targets(boundary, exact[boundary])
    assert sim.solve_static(load_steps=2).converged
    np.testing.assert_allclose(sim.positions(), exact, atol=1e-8)


def _static_newton_direct(sim, model, iters=4):
    """Equilibrium f_int(x) + f_ext = 0 on the free components by Newton with direct solves of the
    Warp-assembled (unprojected) stiffness: PCG is too slow at nu = 0.4999."""
    x = model.rest_positions.copy()
    free = ~model.fixed.ravel()
    fext = model.external_forces().ravel()
    for _ in range(iters):
        r = (sim.elastic_forces(x).ravel() + fext)[free]
        K = sim.stiffness_matrix(x, project=False).tocsr()[free][:, free]
        dx = spla.spsolve(K.tocsc(), r)
        x.reshape(-1)[free] += dx
    # converged: the last update is at round-off level (the residual itself is limited by the
    # cancellation of lambda-sized stress terms, ~1e-3 of f_ext for StVK at nu = 0.4999)
    assert np.abs(dx).max() < 1e-8 * np.abs(x - model.rest_positions).max()
    return x


@pytest.mark.parametrize("cls", NONLINEAR, ids=lambda c: c.name)
def test_selective_reduced_hex8_nonlinear_materials_do_not_lock(cls):
    """nu = 0.4999 cantilever (20x2x2) at small strain (rho g = 1e-3, tip deflection ~1.4e-3): every
    material whose small-strain limit is linear elasticity reproduces the linear locking picture."""
    tips = {}
    for et, vi in (("tet10", "full"), ("hex8", "reduced"), ("hex8", "full"), ("tet4", "full")):
        mesh = _box(et, (20, 2, 2), size=(10.0, 1.0, 1.0))
        model = wf.Model(mesh, cls(youngs_modulus=1e4, poisson_ratio=0.4999, density=1.0), gravity=(0, 0, -1e-3),
                         volumetric_integration=vi)
        model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 2, 2)))
        x = _static_newton_direct(wf.Simulator(model, precision="float64"), model)
        tip = np.abs(mesh.vertices[:, 0] - 10) < 1e-9
        tips[et, vi] = -1e3 * (x - mesh.vertices)[tip, 2].mean()  # scaled to rho g = 1
    tet10, red = tips["tet10", "full"], tips["hex8", "reduced"]
    assert tet10 == pytest.approx(1.4054, rel=2e-3)  # the linear value (small strain)
    assert abs(red / tet10 - 1) < 0.03  # linear: 1.3829 vs 1.4054
    assert tips["hex8", "full"] < 0.2 * tet10 and tips["tet4", "full"] < 0.05 * tet10  # locked


@pytest.mark.parametrize("et", ["tet4", "hex8", "hex27"])
def test_hessian_assembly_float32_matches_float64(et, rng):
    """Both hoisted assembly paths (compressed eigen form for Tet4, explicit 9x9 dP/dF for k > 4)
    in float32: the projected stiffness agrees with float64 to float32 round-off."""
    mesh = _box(et, (2, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=10.0, poisson_ratio=0.4, density=1.0))
    x = mesh.vertices + 0.1 * rng.standard_normal(mesh.vertices.shape)
    K64 = wf.Simulator(model, precision="float64").stiffness_matrix(x, project=True).toarray()
    K32 = wf.Simulator(model, precision="float32").stiffness_matrix(x, project=True).toarray()
    assert np.abs(K32 - K64).max() < 1e-5 * np.abs(K64).max()
    assert np.linalg.eigvalsh(K64).min() > -1e-10 * np.abs(K64).max()
