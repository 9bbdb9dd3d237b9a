"""Rigid bodies as affine bodies (warpfem.rigid, docs/rigid.md): mass properties, the orthogonality
energy and the map E by finite differences, free flight invariants, friction on an incline."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from warpfem import Model, Plane, RigidBody, Simulator, box_tet_mesh
from warpfem.mesh import TetMesh

G = 9.81


def _box(size=(0.2, 0.1, 0.05), **kw):
    return RigidBody(box_tet_mesh(size=size, cells=(2, 1, 1)), density=1000.0, name="box", **kw)


def _moments(sim, body):
    """(linear momentum, angular momentum about the origin) of rigid body 0 from the unknown:
    P = m p-dot, L = m p x p-dot + sum_kl S_kl a_k x a_l-dot."""
    k = int(sim.model.rigid.node_of[0])
    q, v = sim.positions()[k:k + 4], sim.velocities()[k:k + 4]
    S = body.second_moment
    L = body.mass * np.cross(q[0], v[0]) + sum(S[a, b] * np.cross(q[1 + a], v[1 + b]) for a in range(3) for b in range(3))
    return body.mass * v[0], L


def test_mass_properties_of_a_box_and_the_initial_state():
    b = _box(offset=(1.0, 2.0, 3.0), initial_velocity=(0.5, 0.0, 0.0), initial_angular_velocity=(0.0, 0.0, 2.0))
    assert b.mass == pytest.approx(1000.0 * 0.2 * 0.1 * 0.05, rel=1e-12)
    np.testing.assert_allclose(b.center_of_mass, [1.1, 2.05, 3.025], atol=1e-12)
    # S = int rho X X^T dV = m / 12 diag(a^2, b^2, c^2)
    np.testing.assert_allclose(b.second_moment, b.mass / 12.0 * np.diag([0.04, 0.01, 0.0025]), atol=1e-15)
    m = Model.from_bodies([b])
    assert m.num_vertices == 4 and list(m.body_offsets) == [0, len(b.local_positions)]
    np.testing.assert_allclose(m.rigid.positions(m.rest_positions), m.vertex_rest_positions, atol=1e-14)
    sim = Simulator(m, dt=0.01)
    # vertex velocities v + w x (x - c) at t = 0
    X = sim.vertex_positions()
    np.testing.assert_allclose(sim.vertex_velocities(), [0.5, 0, 0] + np.cross([0, 0, 2.0], X - b.center_of_mass),
                               atol=1e-14)


def test_orthogonality_energy_gradient_and_hessian_by_finite_differences():
    b = _box(stiffness=3.0)
    sim = Simulator(Model.from_bodies([b]), dt=0.01)
    form, dev = sim.rigid.form, sim.device
    rng = np.random.default_rng(4)
    q = sim.positions()
    q[1:4] = np.eye(3) + 0.3 * rng.standard_normal((3, 3))  # A far from a rotation: C indefinite
    kv = 3.0 * b.volume
    acc = wp.zeros(8, dtype=wp.float64, device=dev)
    form.bind(acc, 0)

    def energy(qq):
        acc.zero_()
        form.energy(None, wp.array(qq, dtype=wp.vec3d, device=dev), acc)
        return float(acc.numpy()[0])

    def gradient(qq):
        g = wp.zeros(4, dtype=wp.vec3d, device=dev)
        form.gradient(None, wp.array(qq, dtype=wp.vec3d, device=dev), 1.0, g, acc)
        return g.numpy().ravel()

    def hessian(qq, project):
        vals = sim.new_matrix_values()
        form.project = project
        form.hessian(None, wp.array(qq, dtype=wp.vec3d, device=dev), 1.0, vals)
        form.project = True
        return sim.pattern.to_scipy(vals).toarray()

    A = q[1:4].T  # columns a_k
    C = A.T @ A - np.eye(3)
    assert energy(q) == pytest.approx(kv * np.sum(C * C), rel=1e-12)
    h, g = 1e-6, gradient(q)
    fd = np.array([(energy(q + h * e) - energy(q - h * e)) / (2 * h) for e in np.eye(12).reshape(12, 4, 3)])
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-9 * np.abs(g).max())
    assert np.all(g[:3] == 0.0)  # p does not enter
    H = hessian(q, False)
    fdH = np.array([(gradient(q + h * e) - gradient(q - h * e)) / (2 * h) for e in np.eye(12).reshape(12, 4, 3)])
    np.testing.assert_allclose(H, fdH.T, rtol=1e-6, atol=1e-7 * np.abs(H).max())
    assert np.linalg.eigvalsh(C).min() < 0.0 and np.linalg.eigvalsh(H).min() < -1e-3 * np.abs(H).max()
    Hp = hessian(q, True)  # Gauss-Newton + clamped curvature: PSD, = exact minus 4 kv (C- (x) I)
    assert np.linalg.eigvalsh(Hp).min() > -1e-12 * np.abs(Hp).max()
    w, V = np.linalg.eigh(C)
    Cm = V @ np.diag(np.minimum(w, 0.0)) @ V.T
    np.testing.assert_allclose(Hp[3:, 3:], H[3:, 3:] - 4 * kv * np.kron(Cm, np.eye(3)), atol=1e-12 * np.abs(H).max())


def _incline(mu, theta, *, precision="float64", height=0.01):
    """A rigid cube (side 0.1 m) dropped from ``height`` onto a plane of slope theta: (sim, down-slope unit)."""
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    L = 0.1
    box = box_tet_mesh(size=(L, L, L), cells=(1, 1, 1), origin=(-0.5 * L, height, -0.5 * L))
    model = Model.from_bodies([RigidBody(TetMesh(np.asarray(box.vertices) @ R.T, box.tets), density=1000.0, name="cube")],
                              gravity=(0.0, -G, 0.0))
    sim = Simulator(model, dt=0.01, precision=precision, colliders=[Plane(point=(0, 0, 0), normal=R[:, 1], friction=mu)])
    return sim, -R[:, 0]


def test_potential_gradient_through_the_map_by_finite_differences():
    """The whole potential (inertia, gravity, orthogonality, barrier + friction through E) of a
    step of a rigid cube in contact with an incline: its gradient in the 12 rigid unknowns against
    central differences, and the Hessian's contact blocks equal E^T H_v E."""
    sim, _ = _incline(0.5, math.radians(30.0), height=0.002)
    sim.step()
    pot = sim.potential()
    rng = np.random.default_rng(1)
    y0 = sim.velocities() + 0.01 * rng.standard_normal((4, 3))
    dev = sim.device

    def E(y):
        return pot.energy(wp.array(y, dtype=wp.vec3d, device=dev))[0]

    g = wp.zeros(4, dtype=wp.vec3d, device=dev)
    pot.gradient(wp.array(y0, dtype=wp.vec3d, device=dev), g)
    g = g.numpy().ravel()
    h = 1e-7
    fd = np.array([(E(y0 + h * e) - E(y0 - h * e)) / (2 * h) for e in np.eye(12).reshape(12, 4, 3)])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(g).max())
    # the contact form's Hessian in the unknown's pattern: E^T H_v E
    form = next(f for f in pot.forms if f.name == "contact")
    vals = sim.new_matrix_values()
    y = wp.array(y0, dtype=wp.vec3d, device=dev)
    form.hessian(y, pot.x_of(y), 1.0, vals)
    space = sim.rigid.space
    Hv = space.system.pattern.to_scipy(space.system.hessian_values)
    Em = sim.model.rigid.matrix()
    assert abs(Hv).max() > 0.0
    np.testing.assert_allclose(sim.pattern.to_scipy(vals).toarray(), (Em.T @ Hv @ Em).toarray(),
                               atol=1e-12 * abs(Hv).max())


@pytest.mark.parametrize("integrator", ["newmark", "bdf2"])
def test_free_flight_spinning_about_a_non_principal_axis(integrator):
    """Zero gravity, 2 s at dt = 1/240: linear momentum exact (to 1e-10), the body's pairwise
    vertex distances within 1e-5 m, angular momentum within 1e-3 (measured: Newmark 1.8e-5, BDF2
    7.4e-5; backward Euler loses 2.7 %: docs/rigid.md)."""
    b = _box(initial_velocity=(0.1, -0.2, 0.05), initial_angular_velocity=(1.0, 2.0, 0.5))
    sim = Simulator(Model.from_bodies([b]), dt=1.0 / 240.0, integrator=integrator)
    P0, L0 = _moments(sim, b)
    X0 = sim.vertex_positions()
    D0 = np.linalg.norm(X0[:, None] - X0[None], axis=2)
    for _ in range(480):
        sim.step()
    P, L = _moments(sim, b)
    X = sim.vertex_positions()
    assert np.abs(P - P0).max() < 1e-10
    assert np.abs(np.linalg.norm(X[:, None] - X[None], axis=2) - D0).max() < 1e-5
    assert np.linalg.norm(L - L0) < 1e-3 * np.linalg.norm(L0)
    # it did turn: the body's frame moved by more than 1 rad
    A = sim.positions()[1:4].T
    assert np.arccos(np.clip((np.trace(A) - 1.0) / 2.0, -1, 1)) > 1.0


def _slope_run(mu, precision, steps):
    theta = math.radians(30.0)
    sim, t = _incline(mu, theta, precision=precision)
    p, v = [], []
    for _ in range(steps):
        sim.step()
        assert sim.contact.distances().min() > 0.0
        p.append(sim.positions()[0] @ t)
        v.append(sim.velocities()[0] @ t)
    return np.array(p), np.array(v)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_rigid_cube_slides_down_a_30_degree_incline_with_coulomb_acceleration(precision):
    _, v = _slope_run(0.2, precision, 40)
    a = (v[39] - v[9]) / 0.3
    assert a == pytest.approx(G * (0.5 - 0.2 * math.cos(math.radians(30.0))), rel=0.01)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_rigid_cube_sticks_on_a_30_degree_incline(precision):
    p, _ = _slope_run(0.8, precision, 36)
    assert abs(p[35] - p[5]) < 5e-4  # 0.3 s after it settled (measured 0.15 mm, float32 0.28 mm)


def test_bad_rigid_bodies_are_refused_with_one_line_errors():
    mesh = box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1))
    for rho in (0.0, -1.0):
        with pytest.raises(ValueError, match="density must be > 0"):
            RigidBody(mesh, density=rho, name="b")
    open_surface = (np.asarray(mesh.vertices), np.asarray(mesh.boundary_faces())[:-1])
    with pytest.raises(ValueError, match="surface is open"):
        RigidBody(open_surface, density=1.0, name="b")
    inward = (np.asarray(mesh.vertices), np.asarray(mesh.boundary_faces())[:, ::-1])
    with pytest.raises(ValueError, match="no positive volume"):
        RigidBody(inward, density=1.0, name="b")
    from warpfem import Body, make_material

    soft = Body(box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1), origin=(0, 0.5, 0)),
                make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0), name="soft")
    with pytest.raises(ValueError, match="list the soft bodies first"):
        Model.from_bodies([RigidBody(mesh, density=1.0, name="r"), soft])
    m = Model.from_bodies([soft, RigidBody(mesh, density=1.0, name="r")])
    m.fix([0, 1])  # soft vertices: fine
    with pytest.raises(ValueError, match="belongs to rigid body 'r'"):
        m.fix(m.body_vertices("r", [2]))
    sim = Simulator(m, dt=0.01)
    with pytest.raises(ValueError, match="belongs to rigid body 'r'"):
        sim.set_targets(m.body_vertices("r", [0]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="does not handle rigid bodies"):
        sim.solve_static()
    sim.add_collider(Plane(point=(0, -1, 0), normal=(0, 1, 0), stiffness="auto"))
    x0 = sim.positions()
    with pytest.raises(ValueError, match="stiffness 'auto' is not available with rigid bodies"):
        sim.step()
    assert np.array_equal(sim.positions(), x0) and sim.step_count == 0


def test_rigid_ball_resting_on_a_soft_slab_on_a_floor_weighs_what_both_weigh():
    """A rigid ball (icosphere) dropped 2 mm onto a soft slab on a floor plane, damped: after
    0.3 s the floor's reaction (barrier + friction forces on the vertices) equals the total weight
    within 1 % (measured 3e-5), the ball at rest above the slab."""
    from warpfem import Body, make_material
    from warpfem.mesh.box import icosphere_surface

    slab = Body(box_tet_mesh(size=(0.3, 0.04, 0.3), cells=(2, 1, 2), origin=(-0.15, 0.001, -0.15)),
                make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=500.0), name="slab")
    ball = RigidBody(icosphere_surface(0.05, 1), density=1000.0, name="ball", offset=(0.0, 0.093, 0.0))
    m = Model.from_bodies([slab, ball], gravity=(0.0, -G, 0.0))
    sim = Simulator(m, dt=0.01, damping_mass=10.0, colliders=[Plane(point=(0, 0, 0), normal=(0, 1, 0))])
    sim.set_contact(bodies=True)
    for _ in range(30):
        sim.step()
    reaction = sim.contact.forces().sum(axis=0)
    assert reaction[1] == pytest.approx(m.total_mass * G, rel=0.01)
    assert abs(sim.velocities()[m.rigid.node_of[0], 1]) < 1e-3
    X = sim.vertex_positions()
    assert X[m.body_vertices("ball"), 1].min() > X[m.body_vertices("slab"), 1].max()


def test_rigid_boxes_dropped_onto_a_soft_slab_never_intersect_with_a_mass_ratio_of_1000():
    """A light rigid box on a soft slab on a floor and a rigid box 1000 times heavier thrown onto
    it at 1 m/s (rigid-rigid, rigid-soft, soft-floor contact with friction): no intersection at
    any step (IPC Toolkit's test on the vertices), every step converged, A a rotation within 1e-4."""
    ipctk = pytest.importorskip("ipctk")
    from warpfem import Body, make_material

    slab = Body(box_tet_mesh(size=(0.3, 0.04, 0.3), cells=(2, 1, 2), origin=(-0.15, 0.001, -0.15)),
                make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=100.0), name="slab")
    light = RigidBody(box_tet_mesh(size=(0.1, 0.02, 0.1), cells=(1, 1, 1), origin=(-0.05, 0.05, -0.05)),
                      density=100.0, name="light", initial_angular_velocity=(0.3, 0.0, 0.2))
    heavy = RigidBody(box_tet_mesh(size=(0.06, 0.02, 0.06), cells=(1, 1, 1), origin=(-0.02, 0.08, -0.03)),
                      density=100.0 * 1000.0 * (0.1 * 0.1) / (0.06 * 0.06), name="heavy", initial_velocity=(0.0, -1.0, 0.0))
    assert heavy.mass / light.mass == pytest.approx(1000.0)
    m = Model.from_bodies([slab, light, heavy], gravity=(0.0, -G, 0.0))
    sim = Simulator(m, dt=0.01, require_convergence=True,
                    colliders=[Plane(point=(0, 0, 0), normal=(0, 1, 0), friction=0.5)])
    sim.set_contact(bodies=True, friction=0.5)
    F = np.asarray(m.mesh.boundary_faces())
    cm = ipctk.CollisionMesh(np.asarray(m.vertex_rest_positions, dtype=np.float64), ipctk.edges(F), F)
    for _ in range(12):
        sim.step()
        assert not ipctk.has_intersections(cm, np.asfortranarray(sim.vertex_positions()))
    for r in range(2):
        k = int(m.rigid.node_of[r])
        A = sim.positions()[k + 1:k + 4].T
        assert np.abs(A.T @ A - np.eye(3)).max() < 1e-4
    assert sim.positions()[int(m.rigid.node_of[1]), 1] > sim.positions()[int(m.rigid.node_of[0]), 1] + 0.02


def test_a_run_continued_from_a_checkpoint_and_a_second_run_are_bit_identical():
    sim, _ = _incline(0.5, math.radians(30.0))
    for _ in range(3):
        sim.step()
    saved = sim.state_dict()
    for _ in range(3):
        sim.step()
    again, _ = _incline(0.5, math.radians(30.0))
    again.load_state_dict(saved)
    for _ in range(3):
        again.step()
    fresh, _ = _incline(0.5, math.radians(30.0))
    for _ in range(6):
        fresh.step()
    assert np.array_equal(again.positions(), sim.positions()) and np.array_equal(fresh.positions(), sim.positions())
    assert np.array_equal(fresh.vertex_velocities(), sim.vertex_velocities())


def test_a_rigid_body_is_one_contact_group_with_no_pairs_inside_it():
    """Surface contact's groups: each rigid body's surface vertices are one group (connected by its
    triangles; no elements hold them), so a rigid icosphere finer than dhat has no barrier pair
    within itself; the soft slab is one group too."""
    from warpfem import Body, make_material
    from warpfem.mesh.box import icosphere_surface

    slab = Body(box_tet_mesh(size=(0.3, 0.04, 0.3), cells=(2, 1, 2), origin=(-0.15, -0.1, -0.15)),
                make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=500.0), name="slab")
    ball = RigidBody(icosphere_surface(0.05, 2), density=1000.0, name="ball", offset=(0.0, 0.2, 0.0))
    m = Model.from_bodies([slab, ball])
    sim = Simulator(m, dt=0.01)
    sim.set_contact(bodies=True, dhat=0.05)  # dhat above the ball's edge length: its own features are near
    group = sim.surface_contact.surface.group
    assert sim.surface_contact.surface.num_groups == 2
    assert np.unique(group[m.body_vertices("ball")]).size == 1 and np.unique(group[m.body_vertices("slab")]).size == 1
    sim.step()  # the bodies are 0.23 m apart: no pair at all
    assert sim.surface_contact.num_pairs == 0


def test_two_rigid_cubes_collide_conserving_linear_momentum_and_losing_energy():
    """Zero gravity, a spinning 1 kg cube thrown at a 3 kg cube (off centre, friction 0.5), BDF2:
    the total linear momentum is unchanged through the impact (contact forces act in
    equal and opposite pairs through E), the kinetic energy does not grow, they bounce apart."""
    a = RigidBody(box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1), origin=(-0.2, 0.0, 0.0)), density=1000.0,
                  name="a", initial_velocity=(1.0, 0.0, 0.0), initial_angular_velocity=(0.0, 0.0, 3.0))
    b = RigidBody(box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1), origin=(0.05, 0.03, 0.02)), density=3000.0,
                  name="b", initial_velocity=(-1.0, 0.0, 0.0))
    sim = Simulator(Model.from_bodies([a, b]), dt=0.005, integrator="bdf2")
    sim.set_contact(bodies=True, friction=0.5)

    def momentum():
        v = sim.velocities()
        return a.mass * v[0] + b.mass * v[4]

    P0, K0 = momentum(), sim.kinetic_energy()
    for _ in range(40):
        sim.step()
    v = sim.velocities()
    # to round-off with the direct solver (1e-15); to the linear solver's tolerance with PCG (strict
    # device mode: 9e-9 of 2 kg m/s)
    assert np.abs(momentum() - P0).max() < 1e-7
    assert sim.kinetic_energy() < K0
    assert v[4, 0] - v[0, 0] > 0.5  # separating (they approached at 2 m/s)


def test_a_force_on_a_rigid_vertex_gives_its_impulse_and_its_moment():
    """Zero gravity, a constant force F on one vertex of a resting rigid body (``model.add_force``,
    through E^T): after t the linear momentum is F t and the angular momentum about the centre of
    mass (the vertex moves little in 0.02 s) is about (x - c) x F t."""
    b = _box()
    m = Model.from_bodies([b])
    F = np.array([0.0, 0.0, 2.0])
    m.add_force([0], F)
    sim = Simulator(m, dt=0.002, integrator="bdf2")
    r = sim.vertex_positions()[0] - b.center_of_mass
    for _ in range(10):
        sim.step()
    P, L = _moments(sim, b)
    c = sim.positions()[0]
    L_com = L - b.mass * np.cross(c, sim.velocities()[0])  # about the moving centre of mass
    np.testing.assert_allclose(P, F * 0.02, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(L_com, np.cross(r, F) * 0.02, rtol=0.02, atol=1e-4 * np.linalg.norm(np.cross(r, F)) * 0.02)
