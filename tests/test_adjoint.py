"""Adjoint gradients of implicit steps (warpfem.solvers.adjoint, docs/gradients.md) against central
finite differences, float64, every integrator, every parameter kind, over 10 steps.

A 2x1x1-cell tet box (12 vertices, 12 tets), clamped at x = 0 with one clamped vertex driven by a
kinematic target, under gravity, mass damping and applied forces. The loss is a fixed random
linear functional of the positions of every state (so its derivative is the trajectory's own).
Newton solves run to a relative gradient of 1e-13 with the direct solver, so the forward error is
far below the finite-difference step's effect; the central difference's own error (h^2) is below
1e-8 relative at these steps.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpfem as wf
from gradient_checks import assert_central_differences
from warpfem.solvers.state import Control
from warpfem.solvers.adjoint import Recording, set_element_stiffness_scale, set_material_parameters

STEPS = 10
MESH = wf.box_tet_mesh(size=(0.2, 0.1, 0.1), cells=(2, 1, 1))
N = MESH.num_vertices
FIXED = wf.select_vertices_in_box(MESH, (-1, -1, -1), (1e-9, 1, 1))
DRIVEN = int(FIXED[0])
RNG = np.random.default_rng(7)
WEIGHTS = RNG.standard_normal((STEPS + 1, N, 3))
TARGETS = np.array([MESH.vertices[DRIVEN] + [0.0, 0.0, -0.002 * (k + 1)] for k in range(STEPS)])
BASE = dict(E=1e5, nu=0.3, rho=1000.0, scale=np.ones(MESH.num_elements), x0=MESH.vertices.copy(),
            v0=np.zeros((N, 3)), forces=np.zeros((N, 3)), targets=TARGETS)
SOLVER = dict(linear_solver="direct", linear_solver_options={"backend": "superlu"}, tol=1e-13, max_iters=50)


def recorded_run(sim, grads, before_step=None):
    """Step ``sim`` STEPS times (recorded for gradients when ``grads``; ``before_step(k)`` first):
    (positions per state, the WEIGHTS loss, its gradients or None)."""
    xs = [sim.positions()]
    rec = Recording(sim)
    with rec if grads else _null():
        for k in range(STEPS):
            if before_step is not None:
                before_step(k)
            assert sim.step().converged
            xs.append(sim.positions())
    loss = float(sum(np.sum(w * x) for w, x in zip(WEIGHTS, xs)))
    return xs, loss, (rec.backward({k: WEIGHTS[k] for k in range(STEPS + 1)}) if grads else None)


def run(integrator, p, grads=False):
    mat = wf.StableNeoHookean(youngs_modulus=p["E"], poisson_ratio=p["nu"], density=p["rho"])
    model = wf.Model(MESH, mat, gravity=(0.0, 0.0, -9.81))
    model.fix(FIXED)
    model.forces[:] = p["forces"]
    sim = wf.Simulator(model, dt=0.01, integrator=integrator, damping_mass=0.5, **SOLVER)
    set_element_stiffness_scale(sim, p["scale"])
    sim.set_positions(p["x0"])
    sim.set_velocities(p["v0"])
    _, loss, g = recorded_run(sim, grads, lambda k: sim.set_targets([DRIVEN], p["targets"][k][None]))
    return (loss, g) if grads else loss


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        pass


# parameter kind -> (key in BASE, gradient name, direction (None: scalar), finite-difference step)
KINDS = {
    "youngs_modulus": ("E", "youngs_modulus", None, 1e1),
    "poisson_ratio": ("nu", "poisson_ratio", None, 1e-4),
    "density": ("rho", "density", None, 1e-1),
    "element_stiffness_scale": ("scale", "element_stiffness_scale", RNG.standard_normal(MESH.num_elements), 1e-4),
    "initial_positions": ("x0", "initial_positions", RNG.standard_normal((N, 3)), 1e-6),
    "initial_velocities": ("v0", "initial_velocities", RNG.standard_normal((N, 3)), 1e-5),
    "forces": ("forces", "forces", RNG.standard_normal((N, 3)), 1e-3),
    "targets": ("targets", "targets", RNG.standard_normal((STEPS, 3)), 1e-6),
}


def directional(g, name, d):
    if d is None:
        return float(g[name])
    if name == "targets":
        return float(sum(np.dot(g["targets"][k][DRIVEN], d[k]) for k in range(STEPS)))
    return float(np.sum(g[name] * d))


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_gradients_match_central_differences(integrator):
    _, g = run(integrator, BASE, grads=True)
    errors = {}
    for kind, (key, name, d, h) in KINDS.items():
        plus, minus = dict(BASE), dict(BASE)
        plus[key] = BASE[key] + h * (1.0 if d is None else d)
        minus[key] = BASE[key] - h * (1.0 if d is None else d)
        fd = (run(integrator, plus) - run(integrator, minus)) / (2 * h)
        an = directional(g, name, d)
        errors[kind] = abs(an - fd) / abs(fd)
    print(integrator, {k: f"{e:.1e}" for k, e in errors.items()})
    assert max(errors.values()) <= 1e-5, errors


@wp.kernel
def _weighted_sum(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], w[i]))


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_steps_on_a_tape_backpropagate_a_warp_loss(integrator):
    """A Warp loss on every state, steps recorded on a wp.Tape: the tape's gradients (state grads
    and sim.adjoint's parameters) equal the Recording's, which the test above checks against FD."""
    _, ref = run(integrator, BASE, grads=True)
    p = BASE
    mat = wf.StableNeoHookean(youngs_modulus=p["E"], poisson_ratio=p["nu"], density=p["rho"])
    model = wf.Model(MESH, mat, gravity=(0.0, 0.0, -9.81))
    model.fix(FIXED)
    sim = wf.Simulator(model, dt=0.01, integrator=integrator, damping_mass=0.5, **SOLVER)
    states = [sim.new_state(requires_grad=True) for _ in range(STEPS + 1)]
    weights = [wp.array(w, dtype=wp.vec3d) for w in WEIGHTS]
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(_weighted_sum, dim=N, inputs=[states[0].x, weights[0], loss])
        for k in range(STEPS):
            control = Control({DRIVEN: TARGETS[k]})
            sim.step(states[k], states[k + 1], control, 0.01)
            wp.launch(_weighted_sum, dim=N, inputs=[states[k + 1].x, weights[k + 1], loss])
        with pytest.raises(ValueError, match="states of their own"):
            sim.step()
    tape.backward(loss)
    g = sim.adjoint.parameter_gradients()
    for name in ("youngs_modulus", "poisson_ratio", "density", "forces"):
        assert np.allclose(g[name], ref[name], rtol=1e-9, atol=1e-12 * np.max(np.abs(ref[name]))), name
    assert np.allclose(states[0].x.grad.numpy(), ref["initial_positions"], rtol=1e-9, atol=1e-9)
    assert np.allclose(states[0].v.grad.numpy(), ref["initial_velocities"], rtol=1e-9, atol=1e-12)
    assert np.allclose(g["targets"][3][DRIVEN], ref["targets"][3][DRIVEN], rtol=1e-9)
    tape.zero()
    assert not np.any(states[0].x.grad.numpy())


def test_unsupported_runs_say_so():
    model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0))
    model.fix(FIXED)
    sim = wf.Simulator(model, dt=0.01, damping_stiffness=0.01, linear_solver="pcg")
    with pytest.raises(NotImplementedError, match="damping_stiffness"):
        Recording(sim)
    sim = wf.Simulator(model, dt=0.01, linear_solver="pcg")
    sim.add_collider(type="plane", point=(0.0, 0.0, -0.5), normal=(0.0, 0.0, 1.0))
    with pytest.raises(NotImplementedError, match="set its stiffness explicitly"):
        Recording(sim)
    sim = wf.Simulator(model, dt=0.01, linear_solver="pcg")  # boxes, meshes and friction on every collider are
    sim.add_collider(type="box", box_min=(-1.0, -1.0, -2.0), box_max=(1.0, 1.0, -1.0), stiffness=1e4, friction=0.3)
    Recording(sim)  # differentiable (tests/test_adjoint_colliders.py)
    with pytest.raises(ValueError, match="unknown parameter"):
        Recording(wf.Simulator(model, dt=0.01, linear_solver="pcg"), params=["youngs"])
    mat = wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    two = wf.Model.from_bodies([wf.Body(MESH, mat, name="a"), wf.Body(MESH, mat, name="b", offset=(5.0, 0.0, 0.0))])
    sim2 = wf.Simulator(two, dt=0.01, linear_solver="pcg")
    Recording(sim2)  # several bodies are differentiable (tests/test_adjoint_bodies.py), their materials
    with pytest.raises(NotImplementedError, match="model of 2 bodies"):  # are not changed in place
        set_material_parameters(sim2, youngs_modulus=2e5)


def test_reduced_runs_say_gradients_are_not_supported():
    from warpfem.reduced import ReducedSimulator, Subspace
    from warpfem.reduced.cubature import Cubature

    model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0))
    model.fix(FIXED)
    free = np.flatnonzero(~model.fixed.reshape(-1))
    U = np.zeros((3 * N, len(free)))
    U[free, np.arange(len(free))] = 1.0
    basis = wf.reduced.Basis(U=U, linear_frequencies=np.zeros(0), frequencies=np.zeros(0))
    sub = Subspace(basis, Cubature.full(MESH.num_tets), wf.reduced.mesh_hash(model),
                   wf.reduced.subspace.material_parameters(model))
    rs = ReducedSimulator(model, sub, dt=0.01)
    with pytest.raises(NotImplementedError, match="ReducedSimulator"):
        Recording(rs)
    with wp.Tape():
        with pytest.raises(NotImplementedError, match="ReducedSimulator"):
            rs.step()
    rs.step()  # off the tape it steps as before


def _hex_run(E, nu, grads=False):
    mesh = wf.box_hex_mesh(size=(0.2, 0.1, 0.1), cells=(2, 1, 1), order=1)
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=nu, density=1000.0),
                     gravity=(0.0, 0.0, -9.81), volumetric_integration="reduced")
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-9, 1, 1)))
    sim = wf.Simulator(model, dt=0.01, **SOLVER)
    w = np.random.default_rng(1).standard_normal((mesh.num_vertices, 3))
    rec = Recording(sim, params=["youngs_modulus", "poisson_ratio"])
    with rec if grads else _null():
        for _ in range(STEPS):
            assert sim.step().converged
    loss = float(np.sum(w * sim.positions()))
    return (loss, rec.backward({STEPS: w})) if grads else loss


def test_selective_reduced_integration_material_gradients():
    """Hex8 with the volumetric part on its own one-point set: d(mu, lam)/d(E, nu) of both sets."""
    _, g = _hex_run(1e5, 0.3, grads=True)
    for name, (E, nu, h) in {"youngs_modulus": (1e5, 0.3, 10.0), "poisson_ratio": (1e5, 0.3, 1e-4)}.items():
        if name == "youngs_modulus":
            fd = (_hex_run(E + h, nu) - _hex_run(E - h, nu)) / (2 * h)
        else:
            fd = (_hex_run(E, nu + h) - _hex_run(E, nu - h)) / (2 * h)
        assert abs(g[name] - fd) <= 1e-5 * abs(fd), (name, g[name], fd)


def test_float32_gradients_agree_with_float64():
    """float32 (Newton to its precision limit) against float64: 1e-5-level agreement is measured
    (docs/gradients.md); asserted at 1e-3."""
    def grads(precision, tol):
        model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                         gravity=(0.0, 0.0, -9.81))
        model.fix(FIXED)
        sim = wf.Simulator(model, dt=0.01, precision=precision, **{**SOLVER, "tol": tol})
        rec = Recording(sim)
        with rec:
            for _ in range(STEPS):
                sim.step()
        return rec.backward({k: WEIGHTS[k] for k in range(STEPS + 1)})

    g64, g32 = grads("float64", 1e-13), grads("float32", 1e-5)
    for name in ("youngs_modulus", "poisson_ratio", "density", "initial_positions", "initial_velocities"):
        err = np.linalg.norm(np.asarray(g32[name]) - g64[name]) / np.linalg.norm(g64[name])
        assert err < 1e-3, (name, err)


def test_diff_api_on_a_simulator_matches_finite_differences():
    """warpfem.diff.loss_and_gradients on a built Simulator: 2 steps per frame, a subset of vertices
    and frames, handle targets from a callable; E changed in place (set_material_parameters)."""
    from warpfem.diff import loss_and_gradients
    from warpfem.solvers.adjoint import set_material_parameters

    model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, 0.0, -9.81))
    model.fix(FIXED)
    sim = wf.Simulator(model, dt=0.01, integrator="newmark", **SOLVER)
    verts = [3, 7, 11]
    frames = 5  # 10 steps
    obs = MESH.vertices[verts][None] + 0.001 * RNG.standard_normal((frames + 1, len(verts), 3))
    v0 = 0.05 * RNG.standard_normal((N, 3))

    def go(E, v):
        set_material_parameters(sim, youngs_modulus=E)
        sim.set_positions(MESH.vertices)
        sim.set_velocities(v)
        return loss_and_gradients(sim, obs, vertices=verts, frames=[2, 3, 5], steps_per_frame=2,
                                  targets=lambda k: {DRIVEN: TARGETS[k]})

    res = go(1e5, v0)
    assert res.steps == 10 and res.positions.shape == (frames + 1, N, 3)
    fd_E = (go(1e5 + 10.0, v0).loss - go(1e5 - 10.0, v0).loss) / 20.0
    d = RNG.standard_normal((N, 3))
    fd_v = (go(1e5, v0 + 1e-5 * d).loss - go(1e5, v0 - 1e-5 * d).loss) / 2e-5
    assert abs(res.gradients["youngs_modulus"] - fd_E) <= 1e-5 * abs(fd_E)
    assert abs(np.sum(res.gradients["initial_velocities"] * d) - fd_v) <= 1e-5 * abs(fd_v)


def test_parameters_changed_in_place_step_like_a_rebuilt_simulator():
    from warpfem.solvers.adjoint import set_density, set_material_parameters

    def build(E, nu, rho):
        model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=nu, density=rho),
                         gravity=(0.0, 0.0, -9.81))
        model.fix(FIXED)
        return wf.Simulator(model, dt=0.01, integrator="newmark", **SOLVER)

    a = build(1e5, 0.3, 1000.0)
    set_material_parameters(a, youngs_modulus=2e5, poisson_ratio=0.2)
    set_density(a, 1500.0)
    b = build(2e5, 0.2, 1500.0)
    for _ in range(3):
        a.step()
        b.step()
    assert np.allclose(a.positions(), b.positions(), rtol=0, atol=1e-12)
    assert a.model.material.density == 1500.0 and a.model.material.youngs_modulus == 2e5


def _contact_run(integrator, E=1e5, shift=np.zeros(3), v0=None, x0=None, grads=False):
    model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, 0.0, -9.81))
    sim = wf.Simulator(model, dt=0.01, integrator=integrator, **{**SOLVER, "max_iters": 80})
    sim.set_positions(MESH.vertices if x0 is None else x0)
    sim.set_velocities(np.tile([0.0, 0.0, -0.5], (N, 1)) if v0 is None else v0)
    sim.add_collider(type="plane", point=tuple(np.array([0.0, 0.0, -0.01]) + shift), normal=(0.0, 0.0, 1.0),
                     stiffness=1e4, dhat=0.01)
    xs, loss, g = recorded_run(sim, grads)
    assert min(x[:, 2].min() for x in xs) < -0.01 + 0.01  # within dhat of the plane: the barrier acts
    return (loss, g) if grads else loss


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_gradients_through_plane_contact(integrator):
    """A free box thrown onto a frictionless plane (barrier active in most steps): E, the plane's
    translation (all steps), initial velocities and positions against central differences. The
    barrier is stiff on the scale of dhat = 1 cm, so the steps are small (h^2 error ~1e-8)."""
    _, g = _contact_run(integrator, grads=True)
    d3 = np.array([0.3, -0.2, 1.0])
    D = RNG.standard_normal((N, 3))
    v0 = np.tile([0.0, 0.0, -0.5], (N, 1))
    cases = {
        "youngs_modulus": (g["youngs_modulus"], lambda h: _contact_run(integrator, E=1e5 + h), 10.0),
        "collider_translations": (sum(float(np.dot(t["plane"], d3)) for t in g["collider_translations"].values()),
                                  lambda h: _contact_run(integrator, shift=h * d3), 3e-7),
        "initial_velocities": (float(np.sum(g["initial_velocities"] * D)),
                               lambda h: _contact_run(integrator, v0=v0 + h * D), 1e-6),
        "initial_positions": (float(np.sum(g["initial_positions"] * D)),
                              lambda h: _contact_run(integrator, x0=MESH.vertices + h * D), 3e-7),
    }
    assert_central_differences(cases, integrator)


def test_gradients_through_sphere_contact():
    """The box thrown onto a sphere (radius 20 cm): the adjoint adds the barrier's curvature term
    kappa b'(d) (I - n n^T) / L that the forward's projected Hessian leaves out; Newton to 1e-11
    (the projected Hessian makes its last iterations linear)."""
    center = np.array([0.1, 0.05, -0.21])

    def go(shift, E=1e5, grads=False):
        model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=0.3, density=1000.0),
                         gravity=(0.0, 0.0, -9.81))
        sim = wf.Simulator(model, dt=0.01, **{**SOLVER, "tol": 1e-11, "max_iters": 300})
        sim.set_velocities(np.tile([0.0, 0.0, -0.5], (N, 1)))
        sim.add_collider(type="sphere", center=tuple(center + shift), radius=0.2, stiffness=1e4, dhat=0.01)
        xs, loss, g = recorded_run(sim, grads)
        if grads:
            gap = min(np.linalg.norm(x - center, axis=1).min() for x in xs) - 0.2
            assert 0.0 < gap < 0.01  # inside the barrier's range
        return (loss, g) if grads else loss

    _, g = go(np.zeros(3), grads=True)
    d = np.array([0.3, -0.2, 1.0])
    h = 3e-7
    fd = (go(h * d) - go(-h * d)) / (2 * h)
    an = sum(float(np.dot(t["sphere"], d)) for t in g["collider_translations"].values())
    assert abs(an - fd) <= 1e-5 * abs(fd), (an, fd)
    fd_E = (go(np.zeros(3), E=1e5 + 10.0) - go(np.zeros(3), E=1e5 - 10.0)) / 20.0
    assert abs(g["youngs_modulus"] - fd_E) <= 1e-5 * abs(fd_E), (g["youngs_modulus"], fd_E)


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_gradients_through_plane_friction(integrator):
    """The box thrown sideways onto a plane with Coulomb friction 0.4 (lagged from the step's start:
    the normal force lam_n(x_n) and the collider's motion enter the reverse pass through x_n and
    both poses): the plane's translation, the friction coefficient and v_0 against central
    differences."""
    v0 = np.tile([0.4, 0.1, -0.3], (N, 1))

    def go(shift=np.zeros(3), mu=0.4, v=v0, grads=False):
        model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                         gravity=(0.0, 0.0, -9.81))
        # friction_iterations=0: the finite differences step the function the adjoint differentiates
        # (friction lagged once from the step start; recorded steps always lag once)
        sim = wf.Simulator(model, dt=0.01, integrator=integrator, friction_iterations=0,
                           **{**SOLVER, "tol": 1e-12, "max_iters": 100})
        sim.set_velocities(v)
        sim.add_collider(type="plane", point=tuple(np.array([0.0, 0.0, -0.012]) + shift), normal=(0.0, 0.0, 1.0),
                         stiffness=1e4, dhat=0.01, friction=mu)
        _, loss, g = recorded_run(sim, grads)
        return (loss, g) if grads else loss

    _, g = go(grads=True)
    d3, D = np.array([0.3, -0.2, 1.0]), RNG.standard_normal((N, 3))
    assert g["collider_friction"]["plane"] != 0.0  # friction acts
    cases = {"collider_translations": (sum(float(np.dot(t["plane"], d3)) for t in g["collider_translations"].values()),
                                       lambda h: go(shift=h * d3), 3e-7),
             "collider_friction": (g["collider_friction"]["plane"], lambda h: go(mu=0.4 + h), 1e-5),
             "initial_velocities": (float(np.sum(g["initial_velocities"] * D)), lambda h: go(v=v0 + h * D), 1e-6)}
    assert_central_differences(cases, integrator)


def test_a_new_integrator_is_differentiated_by_its_own_reverse():
    """The adjoint has no table of schemes: an integrator class of its own (here BDF2 under another
    name) is recorded and differentiated through its reverse methods, to the same numbers bit for bit;
    one without a reverse is refused naming the differentiable ones."""
    from warpfem.integrators import BDF2, Integrator

    class MyBDF2(BDF2):
        name = "my_bdf2"

    _, g_ref = run("bdf2", BASE, grads=True)
    _, g = run(MyBDF2(), BASE, grads=True)
    for k in ("youngs_modulus", "density", "initial_positions", "initial_velocities", "forces"):
        assert np.array_equal(g[k], g_ref[k]), k

    class Forward(BDF2):  # a scheme without its reverse
        name = "forward_only"
        reversible = False

    model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0))
    with pytest.raises(NotImplementedError, match="with backward_euler, bdf2 or newmark, not for Simulator "
                                                  r"\(integrator 'forward_only'\)"):
        Recording(wf.Simulator(model, dt=0.01, integrator=Forward(), linear_solver="pcg"))
    assert not Integrator.reversible
