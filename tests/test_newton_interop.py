"""warpfem as a newton solver (warpfem.interop.newton.SolverFEM, docs/newton.md): a newton soft mesh
stepped by SolverFEM matches the same mesh and material run as a warpfem Model/Simulator to float32
round-off; a block sliding on newton's ground plane decelerates at the plane material's mu g and
never goes below it; bad models get one-line errors naming what is supported; a state edited by
the caller is read again."""

from __future__ import annotations

import numpy as np
import pytest

newton = pytest.importorskip("newton")
wp = pytest.importorskip("warp")

import warpfem as wf  # noqa: E402
from warpfem.interop.newton import NewtonInteropError, SolverFEM, lame_to_youngs  # noqa: E402

E, NU, RHO = 1.0e5, 0.3, 1000.0


def _material(E=E, nu=NU):
    return wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=nu, density=RHO)


def _add_mesh(builder, mesh, material, *, pos=(0.0, 0.0, 0.0), vel=(0.0, 0.0, 0.0)):
    builder.add_soft_mesh(pos=wp.vec3(*pos), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(*vel),
                          vertices=np.asarray(mesh.vertices).tolist(), indices=np.asarray(mesh.elements).ravel().tolist(),
                          density=RHO, k_mu=material.mu_lame, k_lambda=material.lam_lame, k_damp=0.0)


def _run(solver, model, steps, dt, *, start=None):
    s0, s1 = (start or model.state()), model.state()
    control = model.control()
    for _ in range(steps):
        s0.clear_forces()
        solver.step(s0, s1, control, None, dt)
        s0, s1 = s1, s0
    return s0


def _cantilever_model(meshes_and_materials, fix_x0=True):
    b = newton.ModelBuilder()
    for mesh, mat, pos in meshes_and_materials:
        _add_mesh(b, mesh, mat, pos=pos)
    model = b.finalize(device="cpu")
    if fix_x0:  # zero mass: newton's fixed particles
        q = model.particle_q.numpy()
        m = model.particle_mass.numpy()
        m[q[:, 0] < 1e-9] = 0.0
        model.particle_mass.assign(m)
        model.particle_inv_mass.assign(np.where(m > 0, 1.0 / np.maximum(m, 1e-30), 0.0).astype(np.float32))
    return model


def test_lame_to_youngs_inverts_warpfem_lame_parameters():
    m = _material(2.5e6, 0.45)
    assert lame_to_youngs(m.mu_lame, m.lam_lame) == pytest.approx((2.5e6, 0.45), rel=1e-14)


def test_soft_mesh_matches_a_warpfem_simulator_to_float32_round_off():
    """Two bodies of different materials (two add_soft_mesh calls, two tet_materials groups) as a
    cantilever pair under gravity: SolverFEM's float32 output against Model.from_bodies run by a
    warpfem Simulator (the same float32-rounded vertices) after 8 steps."""
    soft, stiff = _material(), _material(4.0e5, 0.35)
    mesh = wf.box_tet_mesh(size=(0.3, 0.1, 0.1), cells=(3, 1, 1))
    V = np.asarray(mesh.vertices, dtype=np.float32).astype(np.float64)
    mesh32 = wf.TetMesh(V, np.asarray(mesh.elements))
    model = _cantilever_model([(mesh32, soft, (0.0, 0.0, 0.0)), (mesh32, stiff, (0.0, 0.3, 0.0))])
    dt, steps = 1.0 / 60.0, 8
    solver = SolverFEM(model, tol=1e-10)
    assert len(solver.materials) == 2 and solver.resyncs == 0
    got = _run(solver, model, steps, dt).particle_q.numpy().astype(np.float64)

    ref = wf.Model.from_bodies([wf.Body(mesh32, soft, name="soft"), wf.Body(mesh32, stiff, name="stiff", offset=(0, 0.3, 0))],
                               gravity=(0.0, 0.0, -9.81))
    X = ref.rest_positions
    ref.fix(np.flatnonzero(X[:, 0] < 1e-9))
    sim = wf.Simulator(ref, dt=dt, tol=1e-10)
    for _ in range(steps):
        sim.step()
    x = sim.positions()
    disp = np.abs(x - X).max()
    assert disp > 0.01  # the bars bend
    err = np.abs(got - x).max() / disp
    assert err < 1e-6, err  # measured 2.0e-7: the float32 rounding of the output
    assert np.abs(solver.positions() - x).max() / disp < 1e-6  # warpfem's own float64 state


@pytest.fixture(scope="module")
def sliding_block():
    """A 0.1 m block launched at 1 m/s along x 2 mm above newton's ground plane (mu = 0.4), dt = 0.01 s:
    (model, masses, the particle momentum after each of 40 steps, the lowest z after each step)."""
    b = newton.ModelBuilder()
    b.add_ground_plane(cfg=newton.ModelBuilder.ShapeConfig(mu=0.4))
    _add_mesh(b, wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2)), _material(), pos=(0.0, 0.0, 0.002),
              vel=(1.0, 0.0, 0.0))
    model = b.finalize(device="cpu")
    solver = SolverFEM(model)
    mass = model.particle_mass.numpy().astype(np.float64)
    s0, s1 = model.state(), model.state()
    momentum, zmin = [], []
    for _ in range(40):
        s0.clear_forces()
        solver.step(s0, s1, model.control(), None, 0.01)
        s0, s1 = s1, s0
        momentum.append((mass[:, None] * s0.particle_qd.numpy()).sum(axis=0))
        zmin.append(float(s0.particle_q.numpy()[:, 2].min()))
    return solver, mass, np.array(momentum), np.array(zmin), s0


def test_block_on_the_ground_plane_slides_with_the_plane_friction_and_stays_above_it(sliding_block):
    solver, mass, P, zmin, _ = sliding_block
    assert [c.friction for _, c in solver._colliders] == pytest.approx([0.4])
    assert zmin.min() > 0.0  # no vertex below the plane
    # sliding (steps 11 to 20): Coulomb, dp_x = -mu (M g T + dp_z) (the normal impulse)
    M, T = mass.sum(), 10 * 0.01
    dpx, dpz = P[19, 0] - P[9, 0], P[19, 2] - P[9, 2]
    assert P[19, 0] > 0.0
    ratio = dpx / (-0.4 * (M * 9.81 * T + dpz))
    assert abs(ratio - 1.0) < 0.005, ratio  # measured 1.0001
    # then it stops (v0 / (mu g) = 0.25 s) and sticks: velocity below 1 cm/s after 0.35 s
    assert np.abs(P[35:, 0] / M).max() < 0.01


def test_a_state_the_caller_changed_is_read_again(sliding_block):
    """Steps continue from warpfem's own float64 state while state_in is what SolverFEM wrote;
    a fresh state (a reset) is read again and gives the first steps again."""
    solver, *_ , last = sliding_block
    model = solver.model
    before = solver.resyncs
    first = _run(solver, model, 2, 0.01).particle_q.numpy()
    assert solver.resyncs == before + 1  # the reset state
    fresh = SolverFEM(model)
    again = _run(fresh, model, 2, 0.01).particle_q.numpy()
    np.testing.assert_array_equal(first, again)  # deterministic, and the resync restarted the history
    assert fresh.resyncs == 1


def test_particle_forces_act_as_external_loads():
    """state.particle_f: a force of 0.5 N on every particle of a free-floating block changes its
    momentum by n F t (the particles' masses differ, so the block also deforms)."""
    b = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    _add_mesh(b, wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1)), _material())
    model = b.finalize(device="cpu")
    solver = SolverFEM(model, tol=1e-12)
    s0, s1 = model.state(), model.state()
    M = float(model.particle_mass.numpy().sum())
    for _ in range(3):
        s0.particle_f.assign(np.tile(np.array([[0.5, 0.0, 0.0]], dtype=np.float32), (model.particle_count, 1)))
        solver.step(s0, s1, model.control(), None, 0.01)
        s0, s1 = s1, s0
    m = model.particle_mass.numpy().astype(np.float64)
    p = (m[:, None] * s0.particle_qd.numpy()).sum(axis=0)
    assert p == pytest.approx([3 * 0.01 * 0.5 * model.particle_count, 0.0, 0.0], rel=1e-5, abs=1e-9)
    assert M > 0


def test_bad_models_get_one_line_errors():
    b = newton.ModelBuilder()
    b.add_particle(wp.vec3(0.0, 0.0, 1.0), wp.vec3(0.0, 0.0, 0.0), 1.0)
    with pytest.raises(NewtonInteropError, match=r"tetrahedra \(ModelBuilder.add_soft_mesh / add_soft_grid\); it has no tetrahedra"):
        SolverFEM(b.finalize(device="cpu"))
    c = newton.ModelBuilder()
    c.add_cloth_grid(pos=wp.vec3(0.0, 0.0, 1.0), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0), dim_x=2, dim_y=2,
                     cell_x=0.1, cell_y=0.1, mass=0.1)
    with pytest.raises(NewtonInteropError, match=r"it has 8 triangles and no tetrahedra \(cloth and shells: use SolverVBD"):
        SolverFEM(c.finalize(device="cpu"))
    d = newton.ModelBuilder()
    _add_mesh(d, wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1)), _material())
    model = d.finalize(device="cpu")
    q = model.particle_q.numpy()
    q[3, 1] = np.nan
    model.particle_q.assign(q)
    with pytest.raises(NewtonInteropError, match=r"model.particle_q of particle 3 is not finite"):
        SolverFEM(model)
    for e in (NewtonInteropError("x"),):
        assert "\n" not in str(e)


def test_solver_fem_is_an_entry_of_newtons_coupled_solver():
    """SolverCoupled (newton's experimental coupled framework) with a SolverFEM entry owning the
    soft block and the ground plane and a SolverXPBD entry owning a rigid box: the block's particles
    are bit-identical to SolverFEM alone on the same model, the box falls freely (v = -g t)."""
    coupled = pytest.importorskip("newton.solvers.experimental.coupled")
    mesh = wf.box_tet_mesh(size=(0.2, 0.1, 0.1), cells=(2, 1, 1))

    def build():
        b = newton.ModelBuilder()
        b.add_ground_plane(cfg=newton.ModelBuilder.ShapeConfig(mu=0.5))
        _add_mesh(b, mesh, _material(), pos=(0.0, 0.0, 0.01))
        body = b.add_body(xform=wp.transform(wp.vec3(1.0, 0.0, 1.0), wp.quat_identity()))
        b.add_shape_box(body, hx=0.05, hy=0.05, hz=0.05)
        return b.finalize(device="cpu"), body

    model, body = build()
    solver = coupled.SolverCoupled(model=model, entries=[
        coupled.SolverCoupled.Entry(name="fem", solver=lambda v: SolverFEM(v, shapes=[0]),
                                    particles=list(range(model.particle_count)), shapes=[0]),
        coupled.SolverCoupled.Entry(name="xpbd", solver=lambda v: newton.solvers.SolverXPBD(model=v), bodies=[body],
                                    shapes=[1])])
    got = _run(solver, model, 10, 0.01)
    alone_model, _ = build()
    alone = _run(SolverFEM(alone_model, shapes=[0]), alone_model, 10, 0.01)
    np.testing.assert_array_equal(got.particle_q.numpy(), alone.particle_q.numpy())
    assert got.particle_q.numpy()[:, 2].min() > 0.0
    assert got.body_qd.numpy()[0][2] == pytest.approx(-9.81 * 0.1, rel=1e-5)


def _record_falling_box(make_viewer):
    """A soft box 5 cm above newton's ground plane stepped by SolverFEM for 3 frames of 1/60 s,
    each frame's state logged to the viewer ``make_viewer()`` makes (closed after); returns the
    model and the logged particle positions."""
    b = newton.ModelBuilder()
    b.add_ground_plane()
    _add_mesh(b, wf.box_tet_mesh(size=(0.2, 0.1, 0.1), cells=(2, 1, 1)), _material(), pos=(0.0, 0.0, 0.05))
    model = b.finalize(device="cpu")
    viewer = make_viewer()
    viewer.set_model(model)
    solver = SolverFEM(model)
    s0, s1 = model.state(), model.state()
    logged = []
    for frame in range(3):
        viewer.begin_frame(frame / 60.0)
        viewer.log_state(s0)
        viewer.end_frame()
        logged.append(s0.particle_q.numpy().copy())
        solver.step(s0, s1, model.control(), None, 1.0 / 60.0)
        s0, s1 = s1, s0
    viewer.close()
    return model, logged


def test_newton_viewer_usd_draws_the_solver_fem_model(tmp_path):
    """newton's ViewerUSD writes the SolverFEM-stepped model as it would any other: the soft
    body's points at each time sample are the state's particle positions."""
    pytest.importorskip("pxr")
    viewer_mod = pytest.importorskip("newton.viewer")
    from pxr import Usd

    path = tmp_path / "fem.usda"
    model, logged = _record_falling_box(lambda: viewer_mod.ViewerUSD(output_path=str(path), fps=60, up_axis="Z"))
    stage = Usd.Stage.Open(str(path))
    points = [p for p in stage.Traverse() if p.GetAttribute("points") and len(p.GetAttribute("points").GetTimeSamples()) == 3]
    assert len(points) == 1
    attr = points[0].GetAttribute("points")
    for t, q in zip(attr.GetTimeSamples(), logged):
        np.testing.assert_allclose(np.asarray(attr.Get(t)), q, atol=1e-7)
    assert logged[2][:, 2].min() < logged[0][:, 2].min() - 1e-3  # it fell


@wp.kernel
def _tip_height(q: wp.array(dtype=wp.vec3), tip: int, loss: wp.array(dtype=float)):
    loss[0] = q[tip][2]


def test_a_tape_over_solver_fem_steps_gives_warpfem_adjoint_gradients():
    """wp.Tape over three SolverFEM steps of a clamped bar: d(tip z)/d(initial velocities) and
    d(tip z)/d(the second step's particle_f) from tape.backward equal central differences of
    untaped runs (eps 0.01 m/s, 0.5 N: the loss is float32) to 1e-4, d(tip z)/d(k_mu, k_lambda)
    (tet_material_gradients) those of solvers rebuilt on changed tet_materials (2 %) to 1e-3."""
    mesh = wf.box_tet_mesh(size=(0.2, 0.05, 0.05), cells=(2, 1, 1))
    b = newton.ModelBuilder()
    _add_mesh(b, mesh, _material())
    for i in range(b.particle_count):
        if b.particle_q[i][0] < 1e-9:
            b.particle_mass[i] = 0.0
    model = b.finalize(device="cpu", requires_grad=True)
    q0 = model.particle_q.numpy()
    tip = int(np.argmax(q0[:, 0] + q0[:, 2]))
    solver = SolverFEM(model, linear_solver="direct", tol=1e-10)

    def run(qd0, tape=None, f1=None):
        states = [model.state(requires_grad=True) for _ in range(4)]
        states[0].particle_qd.assign(qd0)
        if f1 is not None:
            states[1].particle_f.assign(f1)
        loss = wp.zeros(1, dtype=float, requires_grad=True)
        with tape or wp.ScopedDevice("cpu"):
            for k in range(3):
                solver.step(states[k], states[k + 1], None, None, 0.01)
            wp.launch(_tip_height, 1, inputs=[states[3].particle_q, tip, loss])
        return states, loss

    qd0 = np.zeros((model.particle_count, 3), dtype=np.float32)
    tape = wp.Tape()
    states, loss = run(qd0, tape)
    tape.backward(loss)
    grad = states[0].particle_qd.grad.numpy()[tip].astype(np.float64)
    assert grad[2] > 1e-3
    for comp in (0, 2):
        plus, minus = qd0.copy(), qd0.copy()
        plus[tip, comp] += 0.01
        minus[tip, comp] -= 0.01
        fd = (float(run(plus)[1].numpy()[0]) - float(run(minus)[1].numpy()[0])) / 0.02
        assert grad[comp] == pytest.approx(fd, rel=1e-4, abs=1e-7)  # measured 4e-5 relative
    assert np.abs(states[0].particle_q.grad.numpy()).max() > 0.0
    f_grad = states[1].particle_f.grad.numpy().astype(np.float64)
    assert f_grad[tip, 2] > 1e-5 and np.all(f_grad[q0[:, 0] < 1e-9] == 0.0)  # clamped particles: no effect
    f0 = np.zeros((model.particle_count, 3), dtype=np.float32)
    for comp in (0, 2):
        plus, minus = f0.copy(), f0.copy()
        plus[tip, comp] += 0.5
        minus[tip, comp] -= 0.5
        fd = (float(run(qd0, f1=plus)[1].numpy()[0]) - float(run(qd0, f1=minus)[1].numpy()[0])) / 1.0
        assert f_grad[tip, comp] == pytest.approx(fd, rel=1e-4, abs=1e-9)  # measured 6e-6 and 3.5e-7
    # d(tip z)/d(k_mu, k_lambda) of tet_materials: central differences of rebuilt solvers (2 %)
    grads = solver.tet_material_gradients()[0]
    rows = model.tet_materials.numpy().copy()  # (numpy() on the CPU is a view)
    for k in (0, 1):
        z = []
        for h in (0.02, -0.02):
            changed = rows.copy()
            changed[:, k] *= 1.0 + h
            model.tet_materials.assign(changed)
            other = SolverFEM(model, linear_solver="direct", tol=1e-10)
            z.append(float(_run(other, model, 3, 0.01).particle_q.numpy()[tip, 2]))
        model.tet_materials.assign(rows)
        assert grads[k] == pytest.approx((z[0] - z[1]) / (0.04 * rows[0, k]), rel=1e-3)  # measured 1.4e-4, 3.3e-4


def test_a_failed_step_writes_nothing_and_float32_runs():
    """require_convergence with one Newton iteration: SolveFailed, state_out and warpfem's state
    untouched; the same bar in float32 follows the float64 run to 1e-5 of its sag (measured 2.9e-7)."""
    mesh = wf.box_tet_mesh(size=(0.3, 0.1, 0.1), cells=(3, 1, 1))
    model = _cantilever_model([(mesh, _material(), (0.0, 0.0, 0.0))])
    strict = SolverFEM(model, require_convergence=True, max_iters=1, tol=1e-12)
    s0, s1 = model.state(), model.state()
    out_before = s1.particle_q.numpy().copy()
    x_before = strict.positions()
    with pytest.raises(wf.SolveFailed):
        strict.step(s0, s1, model.control(), None, 1.0 / 60.0)
    np.testing.assert_array_equal(s1.particle_q.numpy(), out_before)
    np.testing.assert_array_equal(strict.positions(), x_before)
    x64 = _run(SolverFEM(model, tol=1e-8), model, 4, 1.0 / 60.0).particle_q.numpy()
    x32 = _run(SolverFEM(model, precision="float32", tol=1e-5), model, 4, 1.0 / 60.0).particle_q.numpy()
    sag = np.abs(x64 - model.particle_q.numpy()).max()
    assert sag > 1e-3
    assert np.abs(x32 - x64).max() < 1e-5 * sag


def test_shapes_on_bodies_become_colliders_at_their_world_pose():
    """A sphere and a box on a body (rotated 90 degrees about z, shapes offset in the body frame)
    and a triangle mesh in the world: after a step with the body moved in state_in, warpfem's
    collider distances of the block's surface vertices equal the analytic distances to the shapes
    at body_q * shape_transform."""
    b = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    _add_mesh(b, wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1)), _material())
    body = b.add_body(xform=wp.transform(wp.vec3(0.5, 0.0, 0.0), wp.quat_identity()))
    b.add_shape_sphere(body, xform=wp.transform(wp.vec3(0.1, 0.0, 0.0), wp.quat_identity()), radius=0.05)
    b.add_shape_box(body, xform=wp.transform(wp.vec3(0.0, 0.0, 0.3), wp.quat_identity()), hx=0.02, hy=0.04, hz=0.06)
    tri = newton.Mesh(np.array([[0.0, 0.0, -0.5], [1.0, 0.0, -0.5], [0.0, 1.0, -0.5]], dtype=np.float32),
                      np.array([0, 1, 2], dtype=np.int32))
    b.add_shape_mesh(-1, mesh=tri)
    model = b.finalize(device="cpu")
    solver = SolverFEM(model)
    assert [type(c).__bases__[1].__name__ for _, c in solver._colliders] == ["Sphere", "Box", "MeshCollider"]
    s0, s1 = model.state(), model.state()
    bq = s0.body_q.numpy()
    angle = np.pi / 2
    bq[0] = [0.6, 0.2, 0.1, 0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)]  # 90 degrees about z
    s0.body_q.assign(bq)
    solver.step(s0, s1, model.control(), None, 0.01)
    contact = solver.simulator.contact
    X = solver.positions()[contact.surface]
    D = contact.distances()
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    p = np.array([0.6, 0.2, 0.1])
    center = p + R @ np.array([0.1, 0.0, 0.0])
    np.testing.assert_allclose(D[:, 0], np.linalg.norm(X - center, axis=1) - 0.05, atol=1e-6)
    local = (X - (p + R @ np.array([0.0, 0.0, 0.3]))) @ R  # into the box frame
    outside = np.maximum(np.abs(local) - np.array([0.02, 0.04, 0.06]), 0.0)
    np.testing.assert_allclose(D[:, 1], np.linalg.norm(outside, axis=1), atol=1e-6)
    np.testing.assert_allclose(D[:, 2], X[:, 2] + 0.5, atol=1e-6)  # above the triangle's interior


def test_a_capsule_shape_is_a_capsule_collider_along_its_local_z():
    """newton's capsule (radius, half height along its local z) on a body turned 90 degrees about x:
    warpfem's collider distances of the block's surface vertices equal the distances to the
    segment minus the radius, at body_q * shape_transform."""
    b = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    _add_mesh(b, wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1)), _material())
    body = b.add_body(xform=wp.transform(wp.vec3(0.0, 0.0, 0.3), wp.quat_identity()))
    b.add_shape_capsule(body, xform=wp.transform(wp.vec3(0.05, 0.0, 0.0), wp.quat_identity()), radius=0.04,
                        half_height=0.15)
    model = b.finalize(device="cpu")
    solver = SolverFEM(model)
    assert [type(c).__bases__[1].__name__ for _, c in solver._colliders] == ["Capsule"]
    s0, s1 = model.state(), model.state()
    bq = s0.body_q.numpy()
    bq[0] = [0.0, 0.1, 0.3, np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)]  # 90 degrees about x: local z -> -y
    s0.body_q.assign(bq)
    solver.step(s0, s1, model.control(), None, 0.01)
    contact = solver.simulator.contact
    X = solver.positions()[contact.surface]
    c = np.array([0.05, 0.1, 0.3])
    e = np.array([0.0, -1.0, 0.0])
    t = np.clip((X - c) @ e, -0.15, 0.15)
    expected = np.linalg.norm(X - c - t[:, None] * e, axis=1) - 0.04
    np.testing.assert_allclose(contact.distances()[:, 0], expected, atol=1e-6)


# -- newton's free rigid bodies stepped inside warpfem's solve (SolverFEM(rigid_bodies=...)) --------------
def _box_on_block(offset=(0.013, -0.021)):
    """A 0.1 x 0.1 x 0.04 m box (800 kg/m^3, a free newton body) 8 mm above a 0.2 x 0.2 x 0.04 m
    soft block (add_soft_grid, 500 kg/m^3) on newton's ground plane; z up."""
    b = newton.ModelBuilder()
    b.add_ground_plane()
    b.add_soft_grid(pos=wp.vec3(-0.1, -0.1, 0.002), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                    dim_x=2, dim_y=2, dim_z=1, cell_x=0.1, cell_y=0.1, cell_z=0.04,
                    density=500.0, k_mu=4.0e4, k_lambda=6.0e4, k_damp=0.0)
    body = b.add_body(xform=wp.transform(wp.vec3(offset[0], offset[1], 0.07), wp.quat_identity()))
    b.add_shape_box(body, hx=0.05, hy=0.05, hz=0.02, cfg=newton.ModelBuilder.ShapeConfig(density=800.0, mu=0.5))
    return b.finalize(device="cpu")


def test_a_newton_rigid_box_rests_on_a_soft_block_inside_the_implicit_solve():
    """SolverFEM(rigid_bodies=True) steps the box as a warpfem rigid body in the block's solve:
    newton's mass and inertia equal the box surface's (800 kg/m^3), it comes to rest (< 1 mm/s),
    the ground carries box + block within 2 % (measured 6e-6), the box stays above the block and
    its rest height equals a warpfem Model.from_bodies scene of the same bodies within 1e-6."""
    from warpfem.contact.colliders import Plane

    model = _box_on_block()
    contact = {"dhat": 0.002}
    solver = SolverFEM(model, rigid_bodies=True, damping_mass=10.0, friction=0.5, contact=contact)
    mass, com, inertia = solver.rigid_surface_properties[0]
    assert mass == pytest.approx(float(model.body_mass.numpy()[0]), rel=1e-6)
    assert np.allclose(com, model.body_com.numpy()[0], atol=1e-7)
    assert np.allclose(inertia, model.body_inertia.numpy()[0], rtol=1e-5, atol=1e-12)
    end = _run(solver, model, 40, 0.01)
    qd = end.body_qd.numpy()[0]
    assert np.linalg.norm(qd[:3]) < 1e-3 and np.linalg.norm(qd[3:]) * 0.07 < 1e-3
    g = -float(model.gravity.numpy().reshape(-1, 3)[0, 2])
    weight = (float(model.body_mass.numpy().sum()) + float(model.particle_mass.numpy().sum())) * g
    assert solver.contact_forces().sum(axis=0)[2] == pytest.approx(weight, rel=0.02)
    assert np.allclose(solver.rigid_contact_forces(), 0.0)  # the box touches the block only
    assert solver.last_orthogonality_error < 1e-5
    z_box = float(end.body_q.numpy()[0, 2])
    assert z_box - 0.02 > end.particle_q.numpy()[:, 2].max()
    # the same bodies as a warpfem scene
    q0 = model.particle_q.numpy().astype(np.float64)
    mesh = wf.VolumeMesh(q0, model.tet_indices.numpy().reshape(-1, 4), "tet4")
    Em, num = lame_to_youngs(4.0e4, 6.0e4)
    block = wf.Body(mesh, wf.StableNeoHookean(youngs_modulus=Em, poisson_ratio=num, density=500.0), name="block")
    surface = solver.warpfem_model.bodies[1].mesh  # the box's 12 triangles, at its initial pose
    box = wf.RigidBody((surface.vertices, surface.faces), density=800.0, name="box")
    ref = wf.Model.from_bodies([block, box], gravity=(0.0, 0.0, -g))
    import scipy.sparse

    n, m = len(q0), model.particle_mass.numpy().astype(np.float64)  # newton's grid masses are uniform
    ref.lumped_mass[:n], ref.gravity_mass[:n] = m, m
    ref.mass = scipy.sparse.block_diag([scipy.sparse.diags(m), ref.mass[n:, n:]], format="csr")
    sim = wf.Simulator(ref, dt=0.01, damping_mass=10.0, colliders=[Plane(point=(0, 0, 0), normal=(0, 0, 1),
                                                                          friction=0.5, **contact)])
    sim.set_contact(bodies=True, friction=0.5, **contact)
    for _ in range(40):
        sim.step()
    assert z_box == pytest.approx(ref.rigid.pose(sim.positions(), 0)[0][2], rel=1e-6)  # measured 2.6e-8


def test_a_spinning_newton_body_keeps_its_angular_momentum_and_body_q_round_trips():
    """A free box whose centre of mass is off its body origin, spinning in zero gravity (BDF2,
    0.5 s): the angular momentum R I R^T w from body_q / body_qd is conserved within 1e-3 (measured
    4.1e-4), the COM velocity of body_qd stays the initial one, the vertices warpfem moves are
    body_q applied to the body-frame surface, and an edited state is read again."""
    b = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_soft_grid(pos=wp.vec3(2.0, 0.0, 0.0), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                    dim_x=1, dim_y=1, dim_z=1, cell_x=0.05, cell_y=0.05, cell_z=0.05,
                    density=500.0, k_mu=4.0e4, k_lambda=6.0e4, k_damp=0.0)
    rot = wp.quat_from_axis_angle(wp.normalize(wp.vec3(1.0, 1.0, 0.0)), 0.4)
    body = b.add_body(xform=wp.transform(wp.vec3(0.0, 0.0, 1.0), rot))
    b.add_shape_box(body, xform=wp.transform(wp.vec3(0.05, 0.0, 0.0), wp.quat_identity()), hx=0.1, hy=0.05, hz=0.025,
                    cfg=newton.ModelBuilder.ShapeConfig(density=1000.0))
    model = b.finalize(device="cpu")
    qd0 = np.array([[0.1, -0.2, 0.05, 1.0, 2.0, 0.5]], dtype=np.float32)
    model.body_qd.assign(qd0)
    solver = SolverFEM(model, rigid_bodies=[0], integrator="bdf2")
    I_b = model.body_inertia.numpy()[0].astype(np.float64)
    com_b = model.body_com.numpy()[0].astype(np.float64)
    assert np.allclose(com_b, (0.05, 0.0, 0.0), atol=1e-7)

    def momentum(state):
        q, w = state.body_q.numpy()[0].astype(np.float64), state.body_qd.numpy()[0, 3:].astype(np.float64)
        from warpfem.interop.newton import _rotation

        R = _rotation(q[3:])
        return R @ I_b @ R.T @ w

    start = model.state()
    L0 = momentum(start)
    q_start = start.body_q.numpy()[0].astype(np.float64)  # (the run writes into start)
    end = _run(solver, model, 60, 1.0 / 120.0, start=start)
    drift = np.linalg.norm(momentum(end) - L0) / np.linalg.norm(L0)
    assert drift < 1e-3
    assert np.allclose(end.body_qd.numpy()[0, :3], qd0[0, :3], atol=1e-6)
    assert solver.last_orthogonality_error < 1e-5
    # body_q * (body-frame surface) = warpfem's rigid vertices
    from warpfem.interop.newton import _rotation

    q = end.body_q.numpy()[0].astype(np.float64)
    X = solver.simulator.vertex_positions()[solver.warpfem_model.rigid.vertex_rigid]
    Xb = solver._body_surface(model, 0)[0]
    assert np.abs(Xb @ _rotation(q[3:]).T + q[:3] - X).max() < 1e-6
    # the COM moves at the COM velocity: origin + R com_b advances by v t
    com_w = q[:3] + _rotation(q[3:]) @ com_b
    com_start = q_start[:3] + _rotation(q_start[3:]) @ com_b
    assert np.allclose(com_w - com_start, 0.5 * qd0[0, :3], atol=1e-6)
    # an edited state is read again: stopped by hand, it stays put
    n, nb = solver.resyncs, solver.body_reads
    end.body_qd.assign(np.zeros((1, 6), dtype=np.float32))
    after = _run(solver, model, 2, 1.0 / 120.0, start=end)
    assert solver.resyncs == n and solver.body_reads == nb + 1  # the body alone is read again
    assert np.allclose(after.body_q.numpy()[0], q, atol=1e-6)


def test_rigid_bodies_with_joints_or_without_mass_are_refused():
    b = newton.ModelBuilder()
    b.add_soft_grid(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                    dim_x=1, dim_y=1, dim_z=1, cell_x=0.05, cell_y=0.05, cell_z=0.05,
                    density=500.0, k_mu=4.0e4, k_lambda=6.0e4, k_damp=0.0)
    link = b.add_link(xform=wp.transform(wp.vec3(0.0, 0.0, 1.0), wp.quat_identity()))
    b.add_shape_box(link, hx=0.05, hy=0.05, hz=0.05)
    j = b.add_joint_revolute(-1, link, axis=wp.vec3(0.0, 0.0, 1.0))
    b.add_articulation([j])
    model = b.finalize(device="cpu")
    with pytest.raises(NewtonInteropError, match=r"body 0 is in joint 0 \(REVOLUTE\); rigid_bodies steps free bodies"):
        SolverFEM(model, rigid_bodies=True)
    with pytest.raises(NewtonInteropError, match="rigid body index 3 out of range"):
        SolverFEM(model, rigid_bodies=[3])
    with pytest.raises(ValueError, match="rigid_bodies must be None, True or a list"):
        SolverFEM(model, rigid_bodies="all")


def test_body_f_is_a_world_wrench_at_the_centre_of_mass():
    """newton's body_f (force, torque; world frame, about the COM) on a rigid body at rest in zero
    gravity: one step of 1 ms changes body_qd by (f dt / m, I_world^-1 tau dt) (force to 1e-6,
    torque to 2e-3: the affine body's A turns during the step)."""
    b = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_soft_grid(pos=wp.vec3(2.0, 0.0, 0.0), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                    dim_x=1, dim_y=1, dim_z=1, cell_x=0.05, cell_y=0.05, cell_z=0.05,
                    density=500.0, k_mu=4.0e4, k_lambda=6.0e4, k_damp=0.0)
    rot = wp.quat_from_axis_angle(wp.normalize(wp.vec3(1.0, 1.0, 0.0)), 0.4)
    body = b.add_body(xform=wp.transform(wp.vec3(0.0, 0.0, 1.0), rot))
    b.add_shape_box(body, xform=wp.transform(wp.vec3(0.05, 0.0, 0.0), wp.quat_identity()), hx=0.1, hy=0.05, hz=0.025)
    model = b.finalize(device="cpu")
    solver = SolverFEM(model, rigid_bodies=True)
    s0, s1 = model.state(), model.state()
    f = np.array([[1.0, -2.0, 0.5, 0.01, -0.02, 0.03]], dtype=np.float32)
    s0.body_f.assign(f)
    solver.step(s0, s1, model.control(), None, 1e-3)
    from warpfem.interop.newton import _rotation

    R = _rotation(model.body_q.numpy()[0][3:])
    I_world = R @ model.body_inertia.numpy()[0].astype(np.float64) @ R.T
    qd = s1.body_qd.numpy()[0].astype(np.float64)
    assert np.allclose(qd[:3], f[0, :3] * 1e-3 / float(model.body_mass.numpy()[0]), rtol=1e-5, atol=1e-9)
    dw = np.linalg.solve(I_world, f[0, 3:].astype(np.float64)) * 1e-3
    assert np.linalg.norm(qd[3:] - dw) < 2e-3 * np.linalg.norm(dw)


def _grid_and_box_collision_mesh(ipctk, model, box_min, box_max):
    """IPC Toolkit's collision mesh of the model's tet surface and a box's faces (for
    ``has_intersections``), with the model's rest positions and the box's vertices."""
    Vb, Fb = wf.Box(box_min=box_min, box_max=box_max).surface(1.0)
    q0 = model.particle_q.numpy().astype(np.float64)
    Fs = np.asarray(wf.TetMesh(q0, model.tet_indices.numpy()).boundary_faces())
    F = np.vstack([Fs, Fb + len(q0)])
    return ipctk.CollisionMesh(np.vstack([q0, Vb]), ipctk.edges(F), F), q0, Vb


def test_a_soft_grid_dropped_onto_a_newton_box_on_the_ground_never_intersects_it():
    """A soft grid (add_soft_grid) dropped 2 cm onto a static box shape standing on newton's
    ground plane: no particle below the plane and no intersection of its surface with the box's
    (IPC Toolkit) at any step; it comes to rest on the box's top. (Landing over the box's edge,
    the box's edge can cross the grid's faces between its vertices: a collider keeps the body's
    vertices out, docs/newton.md.)"""
    ipctk = pytest.importorskip("ipctk")
    b = newton.ModelBuilder()
    b.add_ground_plane()
    b.add_shape_box(-1, xform=wp.transform(wp.vec3(0.0, 0.0, 0.05), wp.quat_identity()), hx=0.1, hy=0.1, hz=0.05)
    b.add_soft_grid(pos=wp.vec3(-0.075, -0.05, 0.12), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                    dim_x=6, dim_y=3, dim_z=1, cell_x=0.025, cell_y=0.033, cell_z=0.02,
                    density=300.0, k_mu=2.0e4, k_lambda=3.0e4, k_damp=0.0)
    model = b.finalize(device="cpu")
    solver = SolverFEM(model, damping_mass=5.0)
    cm, _, Vb = _grid_and_box_collision_mesh(ipctk, model, (-0.1, -0.1, 0.0), (0.1, 0.1, 0.1))
    s0, s1 = model.state(), model.state()
    for _ in range(30):
        s0.clear_forces()
        solver.step(s0, s1, model.control(), None, 0.01)
        s0, s1 = s1, s0
        q = s0.particle_q.numpy().astype(np.float64)
        assert q[:, 2].min() > 0.0
        assert not ipctk.has_intersections(cm, np.asfortranarray(np.vstack([q, Vb])))
    q = s0.particle_q.numpy()
    assert 0.1 < q[:, 2].min() < 0.105 and np.abs(s0.particle_qd.numpy()).max() < 0.05  # landed on the top


def test_a_box_moved_by_newtons_xpbd_rests_on_a_solver_fem_block_through_the_proxy_coupler():
    """SolverCoupledProxy (staggered) with SolverXPBD moving the box and SolverFEM the block: the
    box is SolverFEM's proxy body (moved inside its implicit solve, rigid_bodies chosen from the
    PROXY flag). Each step the block's momentum changes by exactly the ground's impulse, its weight
    and minus the coupling impulse the coupler harvests (what XPBD receives next step); the box
    comes to rest on its weight: the coupling force equals m g and the ground carries box + block
    within 2 % (measured 2e-4 and 5e-5), and it rests g dt^2 below the monolithic SolverFEM
    (rigid_bodies=True) rest height (the staggered coupler places the proxy at XPBD's end pose and
    the destination step lifts it by the contact impulse), within 1e-5 m (measured 4e-6)."""
    coupled = pytest.importorskip("newton.solvers.experimental.coupled")
    Proxy = coupled.SolverCoupledProxy
    model, dt, contact = _box_on_block(), 0.01, {"dhat": 0.002}
    solver = Proxy(model=model, entries=[
        Proxy.Entry(name="xpbd", solver=lambda v: newton.solvers.SolverXPBD(model=v), bodies=[0], joints=[0]),
        Proxy.Entry(name="fem", solver=lambda v: SolverFEM(v, contact=contact), particles=list(range(model.particle_count)))],
        coupling=Proxy.Config(proxies=[Proxy.Proxy(source="xpbd", destination="fem", bodies=[0], mode="staggered")]))
    fem, feedback = solver.solver("fem"), solver._proxy_mappings[0].coupling_forces
    assert fem.rigid_bodies == [0]
    g = -float(model.gravity.numpy().reshape(-1, 3)[0, 2])
    m_box, m = float(model.body_mass.numpy()[0]), model.particle_mass.numpy().astype(np.float64)
    s0, s1, control = model.state(), model.state(), model.control()
    residual, largest = 0.0, 0.0
    for _ in range(20):
        p_before = (m[:, None] * s0.particle_qd.numpy()).sum(axis=0)
        s0.clear_forces()
        solver.step(s0, s1, control, None, dt)
        s0, s1 = s1, s0
        F = feedback.numpy()[0, :3].astype(np.float64)
        ground = fem.contact_forces().sum(axis=0)
        dp = (m[:, None] * s0.particle_qd.numpy()).sum(axis=0) - p_before
        expected = (ground - F + np.array([0.0, 0.0, -m.sum() * g])) * dt
        residual, largest = max(residual, np.abs(dp - expected).max()), max(largest, np.abs(F).max() * dt)
    assert fem.resyncs == 1 and fem.body_reads == 19  # the particles stay warpfem's, the proxy box is re-read
    assert largest > 0.02 and residual < 1e-5 * largest
    qd = s0.body_qd.numpy()[0]
    assert np.linalg.norm(qd[:3]) < 1e-3 and np.linalg.norm(qd[3:]) * 0.07 < 1e-3
    assert F[2] == pytest.approx(m_box * g, rel=0.02) and np.abs(F[:2]).max() < 0.02 * m_box * g
    assert ground[2] == pytest.approx((m_box + m.sum()) * g, rel=0.02)
    alone_model = _box_on_block()
    alone = _run(SolverFEM(alone_model, rigid_bodies=True, damping_mass=10.0, contact=contact), alone_model, 40, dt)
    z, z_alone = float(s0.body_q.numpy()[0, 2]), float(alone.body_q.numpy()[0, 2])
    assert z == pytest.approx(z_alone - g * dt * dt, abs=1e-5)


def test_newton_viewer_file_records_the_solver_fem_model_and_plays_it_back(tmp_path):
    """newton's ViewerFile records a SolverFEM-stepped model; a second ViewerFile loads the
    recording into an empty newton Model and its states carry the same particle positions
    (bit-identical) and the same tetrahedra."""
    viewer_mod = pytest.importorskip("newton.viewer")
    path = str(tmp_path / "fem.json")
    model, logged = _record_falling_box(lambda: viewer_mod.ViewerFile(path, auto_save=False))
    player = viewer_mod.ViewerFile(path)
    player.load_recording()
    assert player.get_frame_count() == 3
    replay = newton.Model(device="cpu")
    player.load_model(replay)
    np.testing.assert_array_equal(replay.tet_indices.numpy(), model.tet_indices.numpy())
    state = replay.state()
    for frame, q in enumerate(logged):
        player.load_state(state, frame)
        np.testing.assert_array_equal(state.particle_q.numpy(), q)
    assert logged[2][:, 2].min() < logged[0][:, 2].min() - 1e-3  # it fell


def test_proxy_masses_rebuild_solver_fem_and_its_mass_damping_is_no_coupling_force():
    """A proxy of mass_scale 2 makes SolverFEM's rigid body twice as heavy (notify_model_changed
    rebuilds it); while the box falls freely (no contact), the harvested coupling force is zero
    although damping_mass = 10 slows the proxy inside SolverFEM's step (the harvest adds back
    alpha m v': without it 0.17 of the proxy's weight after 2 steps)."""
    coupled = pytest.importorskip("newton.solvers.experimental.coupled")
    Proxy = coupled.SolverCoupledProxy
    model = _box_on_block()
    m_box, inertia = float(model.body_mass.numpy()[0]), model.body_inertia.numpy()[0].astype(np.float64)
    solver = Proxy(model=model, entries=[
        Proxy.Entry(name="xpbd", solver=lambda v: newton.solvers.SolverXPBD(model=v), bodies=[0], joints=[0]),
        Proxy.Entry(name="fem", solver=lambda v: SolverFEM(v, damping_mass=10.0, contact={"dhat": 0.002}),
                    particles=list(range(model.particle_count)))],
        coupling=Proxy.Config(proxies=[Proxy.Proxy(source="xpbd", destination="fem", bodies=[0], mass_scale=2.0)]))
    body = solver.solver("fem").warpfem_model.rigid.bodies[0]
    assert body.mass == pytest.approx(2.0 * m_box, rel=1e-6)
    assert np.trace(body.second_moment) * np.eye(3) - body.second_moment == pytest.approx(2.0 * inertia, rel=1e-5)
    s0, s1 = model.state(), model.state()
    for _ in range(2):
        s0.clear_forces()
        solver.step(s0, s1, model.control(), None, 0.01)
        s0, s1 = s1, s0
    assert np.abs(solver._proxy_mappings[0].coupling_forces.numpy()).max() < 1e-5 * m_box * 9.81
    assert s0.body_qd.numpy()[0][2] == pytest.approx(-2 * 0.01 * 9.81, rel=1e-5)


def _grid_across_box_edge():
    """The grid of the test above dropped 2 cm across the box's edge at x = 0.1 m (x from 0.03 to
    0.18 m): the scene of kernels_bench/bench_newton_shape_contact.py."""
    from kernels_bench.bench_newton_shape_contact import build

    return build()


def test_surface_shape_contact_keeps_the_box_edge_out_of_a_grid_landing_across_it():
    """shape_contact="surface": the static box is a kinematic rigid body in warpfem's surface contact
    (edge-edge pairs too), so its edge stays out of the grid's faces: no step intersects (IPC Toolkit;
    the colliders' way intersects from step 7 on, kernels_bench/bench_newton_shape_contact.py) while
    the grid bends over the edge; the box's four nodes stay exactly at its pose; the ground is still
    a collider."""
    ipctk = pytest.importorskip("ipctk")
    model = _grid_across_box_edge()
    solver = SolverFEM(model, damping_mass=5.0, shape_contact="surface")
    assert solver.kinematic_shapes == [1] and [s for s, _ in solver._colliders] == [0]
    cm, _, Vb = _grid_and_box_collision_mesh(ipctk, model, (-0.1, -0.1, 0.0), (0.1, 0.1, 0.1))
    s0, s1 = model.state(), model.state()
    for _ in range(16):
        s0.clear_forces()
        solver.step(s0, s1, model.control(), None, 0.01)
        s0, s1 = s1, s0
        q = s0.particle_q.numpy().astype(np.float64)
        assert not ipctk.has_intersections(cm, np.asfortranarray(np.vstack([q, Vb])))
    over = q[:, 0] > 0.11
    assert q[over, 2].min() < 0.095 < q[~over, 2].min()  # past the edge it hangs below the top
    k = int(solver._kinematic_nodes[0])  # p (newton's float32 0.05), then the columns of A = I
    assert np.array_equal(solver.simulator.positions()[k:k + 4], np.vstack([[0.0, 0.0, np.float32(0.05)], np.eye(3)]))


def _box_behind_grid():
    """(model, body): a box on a massless newton body 1 cm behind a soft grid lying on the ground."""
    b = newton.ModelBuilder()
    b.add_ground_plane()
    body = b.add_body(xform=wp.transform(wp.vec3(-0.03, 0.0, 0.03), wp.quat_identity()), mass=0.0)
    b.add_shape_box(body, hx=0.02, hy=0.06, hz=0.02, cfg=newton.ModelBuilder.ShapeConfig(density=0.0, mu=0.0))
    b.add_soft_grid(pos=wp.vec3(0.0, -0.05, 0.001), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                    dim_x=4, dim_y=3, dim_z=1, cell_x=0.025, cell_y=0.033, cell_z=0.02,
                    density=300.0, k_mu=2.0e4, k_lambda=3.0e4, k_damp=0.0)
    return b.finalize(device="cpu"), body


def test_a_box_moved_into_the_grid_in_one_step_fails_with_surface_shape_contact_and_keeps_the_state():
    """The box of the next test moved by its body transform 3 cm in one step, 2 cm into the grid
    (before: the step converged with the box inside the grid): the step fails with the surface
    contact's one-line error naming the kinematic shape and the grid, and warpfem's state is
    bit-identical to before the call."""
    from warpfem.solvers.nonlinear import SolveFailed

    model, body = _box_behind_grid()
    solver = SolverFEM(model, damping_mass=5.0, shape_contact="surface")
    s0, s1 = model.state(), model.state()
    bq = s0.body_q.numpy()
    bq[body, 0] = 0.0
    s0.body_q.assign(bq)
    x, v = solver.simulator.positions(), solver.simulator.velocities()
    with pytest.raises(SolveFailed, match=r"^step 0: surface contact: a kinematic body or handle moved into a soft body "
                       r"within one step: .*'shape1'.*; use smaller steps or a slower motion; state left unchanged$"):
        solver.step(s0, s1, model.control(), None, 0.01)
    assert np.array_equal(solver.simulator.positions(), x) and np.array_equal(solver.simulator.velocities(), v)
    assert solver.simulator.step_count == 0


def test_a_box_moved_by_its_body_transform_pushes_the_grid_with_surface_shape_contact():
    """A box on a massless newton body, moved 1 mm a step along x by the caller's ``body_q``, pushes a
    soft grid lying on the ground 1 cm ahead of it: each step moves the kinematic box from where it is
    to its new pose (its nodes end exactly there), the grid never intersects it (IPC Toolkit) and is
    pushed on by at least the box's 15 mm of travel beyond the gap (measured 17 mm)."""
    ipctk = pytest.importorskip("ipctk")
    model, body = _box_behind_grid()
    solver = SolverFEM(model, damping_mass=5.0, shape_contact="surface")
    assert solver.kinematic_shapes == [1] and solver.rigid_bodies == []
    cm, q0, Vb = _grid_and_box_collision_mesh(ipctk, model, (-0.02, -0.06, -0.02), (0.02, 0.06, 0.02))
    s0, s1 = model.state(), model.state()
    k = int(solver._kinematic_nodes[0])
    for i in range(25):
        bq = s0.body_q.numpy()
        bq[body, 0] = -0.03 + 0.001 * (i + 1)
        s0.body_q.assign(bq)
        s0.clear_forces()
        solver.step(s0, s1, model.control(), None, 0.01)
        s0, s1 = s1, s0
        q = s0.particle_q.numpy().astype(np.float64)
        p = bq[body, :3].astype(np.float64)
        assert np.array_equal(solver.simulator.positions()[k:k + 4], np.vstack([p, np.eye(3)]))
        assert not ipctk.has_intersections(cm, np.asfortranarray(np.vstack([q, Vb + p])))
    assert q[:, 0].mean() - q0[:, 0].mean() > 0.015 and q[:, 0].min() > p[0] + 0.02


def test_surface_shape_contact_takes_closed_mesh_shapes_and_refuses_open_ones():
    """A closed triangle-mesh shape (a box's 12 triangles) is a kinematic body under
    shape_contact="surface" and holds a small grid dropped onto it (its lowest particle stays above
    the top at z = 0.1 m); an open one (two triangles missing), two stacked (touching) boxes and a bad
    option value get one-line errors."""
    from warpfem.interop.newton import _box_surface

    V, F = _box_surface((0.1, 0.1, 0.05))

    def build(tris):
        b = newton.ModelBuilder()
        b.add_shape_mesh(-1, xform=wp.transform(wp.vec3(0.0, 0.0, 0.05), wp.quat_identity()),
                         mesh=newton.Mesh(V, tris.ravel()))
        b.add_soft_grid(pos=wp.vec3(0.03, -0.05, 0.12), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                        dim_x=2, dim_y=1, dim_z=1, cell_x=0.025, cell_y=0.033, cell_z=0.02,
                        density=300.0, k_mu=2.0e4, k_lambda=3.0e4, k_damp=0.0)
        return b.finalize(device="cpu")

    model = build(F)
    solver = SolverFEM(model, shape_contact="surface")
    assert solver.kinematic_shapes == [0] and solver._colliders == []
    end = _run(solver, model, 10, 0.01)
    assert end.particle_q.numpy()[:, 2].min() > 0.1
    with pytest.raises(NewtonInteropError, match=r"shape 0 cannot be a kinematic body .*open.*shape_contact='collider'"):
        SolverFEM(build(F[:-2]), shape_contact="surface")
    with pytest.raises(ValueError, match="shape_contact must be 'collider' or 'surface'"):
        SolverFEM(model, shape_contact="surfaces")
    b = newton.ModelBuilder()  # two static boxes stacked: touching kinematic bodies
    b.add_shape_box(-1, xform=wp.transform(wp.vec3(0.0, 0.0, 0.05), wp.quat_identity()), hx=0.1, hy=0.1, hz=0.05)
    b.add_shape_box(-1, xform=wp.transform(wp.vec3(0.0, 0.0, 0.125), wp.quat_identity()), hx=0.05, hy=0.05, hz=0.025)
    b.add_soft_grid(pos=wp.vec3(-0.04, -0.03, 0.16), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                    dim_x=1, dim_y=1, dim_z=1, cell_x=0.025, cell_y=0.033, cell_z=0.02,
                    density=300.0, k_mu=2.0e4, k_lambda=3.0e4, k_damp=0.0)
    with pytest.raises(NewtonInteropError, match=r"'shape0' and 'shape1' overlap .*touch or overlap"):
        SolverFEM(b.finalize(device="cpu"), shape_contact="surface")
