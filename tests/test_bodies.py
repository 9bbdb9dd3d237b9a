"""Several bodies in one model and one simulator (``Model.from_bodies``): each body of its own element
type and material moves exactly as it does alone; offsets and initial velocities; the union
pattern; bodies overlapping at the start are refused naming both and the first crossing."""

import numpy as np
import pytest
import scipy.sparse

import warpfem as wf
from warpfem.mesh.intersect import BodyOverlapError, first_body_overlap, surface_crossing, winding_number

G = (0.0, 0.0, -9.81)


def _meshes():
    tet = wf.box_tet_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    hexa = wf.box_hex_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    return tet, hexa


MAT_A = dict(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
MAT_B = dict(youngs_modulus=3e5, poisson_ratio=0.2, density=500.0)
OFFSETS = [(0.0, 0.0, 0.0), (0.0, 1.0, 0.5)]


def _clamp(mesh, off):
    off = np.asarray(off)
    return wf.select_vertices_in_box(mesh, off - 1.0, off + (1e-6, 1.0, 1.0))


def _alone(mesh, material, off, precision, steps):
    body = wf.Body(mesh, material, offset=off)
    model = wf.Model(body.mesh, material, gravity=G)
    model.fix(_clamp(body.mesh, off))
    sim = wf.Simulator(model, dt=0.01, precision=precision, tol=1e-10, cg_tol=1e-10, linear_solver="pcg")
    out = []
    for _ in range(steps):
        sim.step()
        out.append(sim.positions())
    return np.array(out)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_two_bodies_move_as_each_alone(precision):
    tet, hexa = _meshes()
    mats = [wf.StableNeoHookean(**MAT_A), wf.Corotated(**MAT_B)]
    bodies = [wf.Body(tet, mats[0], name="tet_beam", offset=OFFSETS[0]),
              wf.Body(hexa, mats[1], name="hex_beam", offset=OFFSETS[1])]
    model = wf.Model.from_bodies(bodies, gravity=G)
    assert model.num_bodies == 2 and model.body_names == ["tet_beam", "hex_beam"]
    assert model.body_offsets.tolist() == [0, tet.num_vertices, tet.num_vertices + hexa.num_vertices]
    for b, off in enumerate(OFFSETS):
        model.fix(model.body_vertices(b, _clamp(model.bodies[b].mesh, off)))
    # masses: each body's own density x volume (0.004 m^3 each)
    o = model.body_offsets
    assert model.lumped_mass[o[0]:o[1]].sum() == pytest.approx(1000.0 * 0.004, rel=1e-12)
    assert model.lumped_mass[o[1]:o[2]].sum() == pytest.approx(500.0 * 0.004, rel=1e-12)
    sim = wf.Simulator(model, dt=0.01, precision=precision, tol=1e-10, cg_tol=1e-10, linear_solver="pcg")
    steps = 6
    together = []
    for _ in range(steps):
        assert sim.step().converged
        together.append(sim.positions())
    together = np.array(together)
    tol = 1e-9 if precision == "float64" else 2e-6
    for b, (mesh, mat) in enumerate(zip((tet, hexa), mats)):
        alone = _alone(mesh, mat, OFFSETS[b], precision, steps)
        sag = np.abs(alone[-1] - model.bodies[b].mesh.vertices).max()
        assert sag > 5e-3  # the beams do sag (m)
        assert np.abs(together[:, o[b]:o[b + 1]] - alone).max() < tol * max(1.0, sag / 1e-2)
    # stresses: each body's quadrature points in body order (Tet4: 1 per tet, Hex8: 8 per hex)
    assert sim.stresses().shape == (tet.num_elements + 8 * hexa.num_elements, 3, 3)


def test_union_pattern_and_block_diagonal_hessian():
    tet, hexa = _meshes()
    mats = [wf.StableNeoHookean(**MAT_A), wf.LinearElastic(**MAT_B)]
    model = wf.Model.from_bodies([wf.Body(tet, mats[0]), wf.Body(hexa, mats[1], offset=(0.0, 1.0, 0.0))])
    assert model.body_names == ["body1", "body2"]
    sim = wf.Simulator(model, precision="float64", linear_solver="pcg")
    rng = np.random.default_rng(3)
    x = model.rest_positions + 0.01 * rng.standard_normal(model.rest_positions.shape)
    K = sim.stiffness_matrix(x, project=False)
    parts, nnz, energy = [], 0, 0.0
    for b in range(2):
        lo, hi = model.body_offsets[b], model.body_offsets[b + 1]
        s1 = wf.Simulator(wf.Model(model.bodies[b].mesh, mats[b]), precision="float64", linear_solver="pcg")
        parts.append(s1.stiffness_matrix(x[lo:hi], project=False))
        nnz += s1.pattern.nnz
        energy += s1.elastic_energy(x[lo:hi])
    assert sim.pattern.nnz == nnz  # the union of the bodies' patterns, nothing between them
    ref = scipy.sparse.block_diag(parts, format="csr")
    assert abs(K - ref).max() < 1e-9 * abs(ref).max()
    assert energy > 0 and sim.elastic_energy(x) == pytest.approx(energy, rel=1e-12)
    # a block between the bodies (what body-body contact adds): the pattern grows, the groups follow
    o = model.body_offsets
    assert sim.system.ensure_blocks([[0, int(o[1]) + 3]]) and sim.pattern.nnz == nnz + 2
    assert len(sim.pattern.block_indices) == 2
    K2 = sim.stiffness_matrix(x, project=False)
    assert abs(K2 - ref).max() < 1e-9 * abs(ref).max()


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_offset_and_initial_velocity_free_flight(precision):
    tet, hexa = _meshes()
    v = [(1.0, -2.0, 0.5), (0.0, 0.25, -3.0)]
    off = [(0.0, 0.0, 0.0), (2.0, 0.0, 0.0)]
    model = wf.Model.from_bodies([wf.Body(tet, wf.StableNeoHookean(**MAT_A), name="a", offset=off[0],
                                          initial_velocity=v[0]),
                                  wf.Body(hexa, wf.StableNeoHookean(**MAT_B), name="b", offset=off[1],
                                          initial_velocity=v[1])])
    o = model.body_offsets
    np.testing.assert_array_equal(model.rest_positions[o[1]:], hexa.vertices + np.array(off[1]))
    sim = wf.Simulator(model, dt=0.02, precision=precision, integrator="newmark")
    np.testing.assert_allclose(sim.velocities()[o[1]:], np.tile(v[1], (hexa.num_vertices, 1)))
    for _ in range(5):
        sim.step()
    t = sim.time
    assert t == pytest.approx(0.1)
    x = sim.positions()
    tol = 1e-12 if precision == "float64" else 2e-6
    for b, mesh in enumerate((tet, hexa)):
        expect = mesh.vertices + np.array(off[b]) + t * np.array(v[b])
        assert np.abs(x[o[b]:o[b + 1]] - expect).max() < tol
    assert sim.kinetic_energy() == pytest.approx(0.5 * (4.0 * np.dot(v[0], v[0]) + 2.0 * np.dot(v[1], v[1])), rel=1e-5)


def test_free_rigid_motions_per_body_and_errors():
    tet, hexa = _meshes()
    mat = wf.StableNeoHookean(**MAT_A)
    model = wf.Model.from_bodies([wf.Body(tet, mat, name="held"), wf.Body(hexa, mat, name="loose", offset=(0, 1, 0))])
    model.fix(model.body_vertices("held", _clamp(tet, (0, 0, 0))))
    free = model.free_rigid_motions()
    assert free and all(f.startswith("loose: ") for f in free) and len(free) == 6
    with pytest.raises(ValueError, match="loose: translation"):
        wf.Simulator(model).solve_static()
    with pytest.raises(KeyError, match="held, loose"):
        model.body_vertices("nope")
    with pytest.raises(IndexError, match="'loose': vertex index 99"):
        model.body_vertices("loose", [99])
    with pytest.raises(ValueError, match="unique, 'x'"):
        wf.Model.from_bodies([wf.Body(tet, mat, name="x"), wf.Body(hexa, mat, name="x", offset=(0, 1, 0))])
    with pytest.raises(ValueError, match="offset must be 3 finite numbers"):
        wf.Body(tet, mat, offset=(0, 1))
    with pytest.raises(ValueError, match="simulates one body"):
        wf.StiffnessWarpingSimulator(model)


def test_overlapping_bodies_refused_naming_both_and_the_crossing():
    tet, _ = _meshes()
    small = wf.box_tet_mesh(size=(0.1, 0.05, 0.05), cells=(1, 1, 1))
    mat = wf.StableNeoHookean(**MAT_A)
    # the small box pokes out of the beam's top: edges of one cross triangles of the other
    with pytest.raises(BodyOverlapError) as e:
        wf.Model.from_bodies([wf.Body(tet, mat, name="beam"), wf.Body(small, mat, name="cube", offset=(0.13, 0.02, 0.07))])
    msg = str(e.value)
    assert "'beam' and 'cube' overlap at t = 0" in msg and "crosses triangle" in msg
    c = surface_crossing(tet.vertices, tet.boundary_faces(), small.vertices + (0.13, 0.02, 0.07), small.boundary_faces())
    assert c is not None and f"edge {list(c.edge)}" in msg
    # the crossing point lies on the edge and on the plane z = 0.1 of the beam's top or the cube's faces
    p0, p1 = c.edge_points
    assert np.linalg.norm(np.cross(c.point - p0, p1 - p0)) < 1e-12
    # inside: the small box wholly inside the beam
    with pytest.raises(BodyOverlapError, match="'cube' is inside 'beam'"):
        wf.Model.from_bodies([wf.Body(tet, mat, name="beam"), wf.Body(small, mat, name="cube", offset=(0.13, 0.02, 0.02))])
    # touching face to face is not an overlap; apart is not either
    assert first_body_overlap([tet, wf.Body(small, mat, offset=(0.0, 0.1, 0.0)).mesh], ["a", "b"]) == ""
    assert first_body_overlap([tet, wf.Body(small, mat, offset=(0.13, 0.1, 0.02)).mesh], ["a", "b"]) == ""
    assert first_body_overlap([tet, wf.Body(small, mat, offset=(1.0, 0.0, 0.0)).mesh], ["a", "b"]) == ""
    model = wf.Model.from_bodies([wf.Body(tet, mat), wf.Body(small, mat, offset=(0.13, 0.02, 0.02))], check_overlap=False)
    assert model.num_bodies == 2
    # winding numbers: 1 inside, 0 outside
    np.testing.assert_allclose(winding_number([[0.2, 0.05, 0.05], [1.0, 0.0, 0.0], [0.23, 0.1, 0.04]], tet.vertices,
                                              tet.boundary_faces()), [1.0, 0.0, 0.5], atol=1e-9)


def test_combined_surface_for_contact():
    tet, hexa = _meshes()
    mat = wf.StableNeoHookean(**MAT_A)
    model = wf.Model.from_bodies([wf.Body(tet, mat), wf.Body(hexa, mat, offset=(0, 1, 0))])
    faces = model.mesh.boundary_faces()
    nt = len(tet.boundary_faces())
    np.testing.assert_array_equal(faces[:nt], tet.boundary_faces())
    np.testing.assert_array_equal(faces[nt:], np.asarray(hexa.boundary_faces()) + tet.num_vertices)
    assert model.mesh.face_bodies().tolist() == [0] * nt + [1] * (len(faces) - nt)
    assert np.bincount(model.mesh.vertex_bodies()).tolist() == [tet.num_vertices, hexa.num_vertices]
    edges = model.mesh.boundary_edges()
    assert np.all(model.mesh.vertex_bodies()[edges[:, 0]] == model.mesh.vertex_bodies()[edges[:, 1]])
    np.testing.assert_array_equal(model.boundary_edges(), edges)
    np.testing.assert_array_equal(model.vertex_bodies(), model.mesh.vertex_bodies())
    # Euler: every body's closed boundary has V - E + F = 2
    for b in range(2):
        fb = faces[model.mesh.face_bodies() == b]
        eb = edges[model.mesh.vertex_bodies()[edges[:, 0]] == b]
        assert np.unique(fb).size - len(eb) + len(fb) == 2
    single = wf.Model(tet, mat)
    assert single.vertex_bodies().tolist() == [0] * tet.num_vertices and single.num_bodies == 1
    # a collider sees every body's surface vertices
    sim = wf.Simulator(model)
    sim.add_collider(wf.Plane(point=(0.0, 0.0, -0.5), normal=(0.0, 0.0, 1.0)))
    assert sim.contact.surface.size == np.unique(faces).size


def test_static_solve_with_selective_reduced_integration_and_direct_solver():
    """Quasi-static equilibrium of two clamped bodies, the Hex8 one with selective reduced
    integration (two quadrature sets of one body in the pattern's group): each as alone."""
    tet, hexa = _meshes()
    mats = [wf.StableNeoHookean(**MAT_A), wf.StableNeoHookean(**MAT_B)]
    vi = ["full", "reduced"]
    model = wf.Model.from_bodies([wf.Body(tet, mats[0]), wf.Body(hexa, mats[1], offset=(0, 1, 0),
                                                                  volumetric_integration=vi[1])], gravity=G)
    for b in range(2):
        model.fix(model.body_vertices(b, _clamp(model.bodies[b].mesh, model.bodies[b].mesh.vertices.min(axis=0))))
    sim = wf.Simulator(model, linear_solver="direct", tol=1e-10)
    assert sim.solve_static().converged
    x = sim.positions()
    for b in range(2):
        alone = wf.Model(model.bodies[b].mesh, mats[b], gravity=G, volumetric_integration=vi[b])
        alone.fix(_clamp(alone.mesh, alone.mesh.vertices.min(axis=0)))
        s = wf.Simulator(alone, linear_solver="direct", tol=1e-10)
        s.solve_static()
        lo, hi = model.body_offsets[b], model.body_offsets[b + 1]
        assert np.abs(s.positions() - alone.rest_positions).max() > 0.03  # sags (m)
        assert np.abs(s.positions() - x[lo:hi]).max() < 1e-10


def test_a_single_mesh_model_is_the_one_body_case():
    """``Model(mesh, material)`` and ``Model.from_bodies([Body(mesh, material)])`` are one construction:
    the same arrays bit for bit, the body's own mesh and quadrature, and the same trajectory."""
    tet, _ = _meshes()
    mat = wf.StableNeoHookean(**MAT_A)
    a = wf.Model(tet, mat, gravity=G, mass_matrix="consistent")
    b = wf.Model.from_bodies([wf.Body(tet, mat, name="beam")], gravity=G, mass_matrix="consistent")
    for m in (a, b):
        assert m.num_bodies == 1 and m.mesh is tet and m.quadrature is m.quadratures[0]
        assert m.body_offsets.tolist() == [0, tet.num_vertices] and m.volumetric_integration == "full"
    assert a.body_names == ["body"] and b.body_names == ["beam"] and isinstance(a.bodies[0], wf.Body)
    for key in ("rest_positions", "lumped_mass", "gravity_mass"):
        assert np.array_equal(getattr(a, key), getattr(b, key)), key
    assert (a.mass != b.mass).nnz == 0 and np.array_equal(a.quadrature.qp_dNdX, b.quadrature.qp_dNdX)
    xs = []
    for m in (a, b):
        m.fix(_clamp(tet, (0.0, 0.0, 0.0)))
        sim = wf.Simulator(m, dt=0.01, tol=1e-10, linear_solver="pcg")
        for _ in range(2):
            sim.step()
        xs.append(sim.positions())
    assert np.array_equal(xs[0], xs[1])
    assert a.free_rigid_motions() == b.free_rigid_motions() == []  # one body: no name prefix
    a.release(_clamp(tet, (0.0, 0.0, 0.0)))
    assert len(a.free_rigid_motions()) == 6 and not a.free_rigid_motions()[0].startswith("body")
