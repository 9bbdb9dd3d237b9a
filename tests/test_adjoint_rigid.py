"""Gradients through steps with rigid bodies (docs/rigid.md, docs/gradients.md) against central
finite differences, float64, direct solver, Newton to 1e-12 or tighter: a spinning free rigid body
(its initial velocity and angular velocity), a rigid box sliding on a collider plane with friction
(its initial velocity and its density: mass, second moments and weight), and a rigid box pressed
onto a soft slab through surface contact with friction (its initial velocity). Losses are fixed
random linear functionals of the final vertex positions (``model.rigid.pull_back`` maps their
gradient to the unknown)."""

from __future__ import annotations

import numpy as np
import pytest

import warpfem as wf
from warpfem.solvers.adjoint import Recording

SOLVER = dict(linear_solver="direct", linear_solver_options={"backend": "superlu"}, tol=1e-12, max_iters=300,
              friction_iterations=0)  # friction lagged once from the step start, as recorded steps do
BOX = wf.box_tet_mesh(size=(0.2, 0.1, 0.05), cells=(1, 1, 1))
CUBE = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1))
SLAB = wf.box_tet_mesh(size=(0.2, 0.04, 0.2), cells=(2, 1, 2), origin=(-0.1, 0.0, -0.1))


def _run(bodies, *, steps, weights, grads, integrator="backward_euler", setup=None, gravity=(0.0, -9.81, 0.0)):
    model = wf.Model.from_bodies(bodies, gravity=gravity)
    if setup is not None:
        setup(model)
    sim = wf.Simulator(model, dt=0.01, integrator=integrator, **SOLVER)
    if setup is not None:
        setup(sim)
    rec = Recording(sim)
    with rec:
        for _ in range(steps):
            assert sim.step().converged
    X = sim.vertex_positions()
    loss = float(np.sum(weights * X))
    if not grads:
        return loss
    return loss, rec.backward({steps: model.rigid.pull_back(weights)}), rec, sim


def _check(run, base, cases, rng):
    """Relative errors of the adjoint against central differences for each (key, gradient, step)."""
    _, g, _, _ = run(base, grads=True)
    errors = {}
    for key, name, h in cases:
        d = rng.standard_normal(np.shape(base[key])) if np.ndim(base[key]) else 1.0
        plus, minus = dict(base), dict(base)
        plus[key], minus[key] = base[key] + h * d, base[key] - h * d
        fd = (run(plus, grads=False) - run(minus, grads=False)) / (2.0 * h)
        an = float(np.sum(np.asarray(g[name]) * d))
        errors[key] = abs(an - fd) / abs(fd)
    return errors, g


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_spinning_free_rigid_body_gradients_of_its_initial_velocities(integrator):
    rng = np.random.default_rng(3)
    W = rng.standard_normal((BOX.num_vertices, 3))
    base = {"v": np.array([0.1, 0.2, -0.1]), "w": np.array([1.0, 2.0, 0.5])}

    def run(p, grads):
        b = wf.RigidBody(BOX, density=800.0, name="b", initial_velocity=p["v"], initial_angular_velocity=p["w"],
                         stiffness=1e6)
        return _run([b], steps=5, weights=W, grads=grads, integrator=integrator)

    errors, g = _check(run, base, [("v", "rigid_initial_velocity", 1e-6),
                                   ("w", "rigid_initial_angular_velocity", 1e-6)], rng)
    print(integrator, {k: f"{e:.1e}" for k, e in errors.items()})
    assert g["rigid_initial_velocity"].shape == (1, 3)
    assert max(errors.values()) <= 1e-5, errors


def test_rigid_box_sliding_on_a_plane_with_friction_gradients_of_velocity_and_density():
    rng = np.random.default_rng(5)
    W = rng.standard_normal((CUBE.num_vertices, 3))
    base = {"v": np.array([0.5, -0.05, 0.2]), "rho": 800.0}
    plane = dict(point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0), friction=0.4, stiffness=1e3, dhat=0.01)
    active = []

    def setup(obj):
        if isinstance(obj, wf.Simulator):
            obj.add_collider(wf.Plane(**plane))

    def run(p, grads):
        b = wf.RigidBody(CUBE, density=p["rho"], name="box", offset=(0.0, 0.005, 0.0), initial_velocity=p["v"],
                         stiffness=1e6)
        out = _run([b], steps=6, weights=W, grads=grads, setup=setup)
        if grads:
            sim = out[3]
            active.append(sim.vertex_positions()[:, 1].min())
        return out

    errors, g = _check(run, base, [("v", "rigid_initial_velocity", 1e-6), ("rho", "density", 1e-2)], rng)
    print({k: f"{e:.1e}" for k, e in errors.items()})
    assert 0.0 < active[0] < 0.01  # still within dhat of the plane at the end: the barrier and friction act
    assert max(errors.values()) <= 1e-5, errors


def test_rigid_box_pressing_on_a_soft_slab_gradient_of_its_initial_velocity():
    rng = np.random.default_rng(7)
    slab = wf.Body(SLAB, wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=500.0),
                   name="slab")
    n = SLAB.num_vertices + CUBE.num_vertices
    W = rng.standard_normal((n, 3))
    base = {"v": np.array([0.1, -0.4, 0.05])}

    def setup(obj):
        if isinstance(obj, wf.Simulator):
            obj.set_contact(bodies=True, dhat=0.01, stiffness=1e5, friction=0.3)
        else:
            obj.fix(np.flatnonzero(obj.rest_positions[:SLAB.num_vertices, 1] < 1e-9))

    state = []

    def run(p, grads):
        box = wf.RigidBody(CUBE, density=800.0, name="box", offset=(-0.05, 0.046, -0.05), initial_velocity=p["v"],
                           stiffness=1e6)
        out = _run([slab, box], steps=5, weights=W, grads=grads, setup=setup)
        if grads:
            sim = out[3]
            X, vc = sim.vertex_positions(), sim.velocities()[sim.model.rigid.node_of[0]]  # vc: its centre's velocity
            state.append((X[SLAB.num_vertices:, 1].min() - X[:SLAB.num_vertices, 1].max(), vc))
        return out

    errors, g = _check(run, base, [("v", "rigid_initial_velocity", 1e-6)], rng)
    print({k: f"{e:.1e}" for k, e in errors.items()})
    gap, v = state[0]
    assert 0.0 < gap < 0.01 and v[1] > 0.05  # within dhat, pushed back up by the slab (it was thrown down)
    # friction took most of its sideways speed (0.11 m/s thrown; measured 0.017 m/s left)
    assert np.linalg.norm(v[[0, 2]]) < 0.2 * np.linalg.norm(base["v"][[0, 2]])
    assert max(errors.values()) <= 1e-5, errors


def test_steps_on_a_tape_give_the_recordings_rigid_gradients():
    """The spinning body's steps on a ``wp.Tape`` (a Warp loss on the unknown): the initial state's
    grads, mapped per body by ``initial_velocity_gradients``, equal the Recording's (checked above
    against central differences), and so does the density's."""
    import warp as wp
    from test_adjoint import _weighted_sum  # its Warp loss kernel (no new kernel module to compile)

    rng = np.random.default_rng(13)
    b = wf.RigidBody(BOX, density=800.0, name="b", initial_velocity=(0.1, 0.2, -0.1),
                     initial_angular_velocity=(1.0, 2.0, 0.5), stiffness=1e6)
    model = wf.Model.from_bodies([b], gravity=(0.0, -9.81, 0.0))
    Wq = rng.standard_normal((model.num_vertices, 3))
    sim = wf.Simulator(model, dt=0.01, **SOLVER)
    rec = Recording(sim)
    with rec:
        for _ in range(3):
            sim.step()
    ref = rec.backward({3: Wq})
    sim = wf.Simulator(model, dt=0.01, **SOLVER)
    states = [sim.new_state(requires_grad=True) for _ in range(4)]
    w = wp.array(Wq, dtype=wp.vec3d)
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        for k in range(3):
            sim.step(states[k], states[k + 1], wf.Control(), 0.01)
        wp.launch(_weighted_sum, dim=model.num_vertices, inputs=[states[3].x, w, loss])
    tape.backward(loss)
    lin, ang = model.rigid.initial_velocity_gradients(states[0].v.grad.numpy())
    assert np.allclose(lin, ref["rigid_initial_velocity"], rtol=1e-9, atol=1e-12)
    assert np.allclose(ang, ref["rigid_initial_angular_velocity"], rtol=1e-9, atol=1e-12)
    assert sim.adjoint.parameter_gradients()["density"] == pytest.approx(ref["density"], rel=1e-9)
