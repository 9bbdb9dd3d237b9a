"""The solver core: the incremental potential's terms against finite differences, the Newton
loop's read-back budget, and the cached launch helper."""

import numpy as np
import pytest
import warp as wp

import warpfem as wf
from warpfem.kernels import linalg as LK
from warpfem.kernels.generic import launch
from warpfem.solvers.forms import DampingForm, ElasticForm, FullSpacePotential, InertiaForm, LoadForm


def _sim(integrator="backward_euler", **kw):
    mesh = wf.box_tet_mesh(size=(1.0, 0.3, 0.3), cells=(3, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2)))
    return wf.Simulator(model, dt=0.02, integrator=integrator, damping_mass=0.4, damping_stiffness=0.01,
                        project_hessian=False, **kw)


def _potential(sim, rng):
    """The potential of the simulator's next step, from a moving state (history built by 2 steps)."""
    sim.set_velocities(0.1 * rng.standard_normal((sim.num_vertices, 3)) * ~sim.model.fixed)
    sim.step()
    sim.step()
    return sim.potential()


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_potential_gradient_and_hessian_match_finite_differences(integrator, rng):
    sim = _sim(integrator)
    pot = _potential(sim, rng)
    free = (~sim.model.fixed).astype(np.float64)
    y = sim.velocities() + 0.05 * rng.standard_normal(free.shape) * free
    dirn = rng.standard_normal(free.shape) * free
    ya = sim._vec_array(y)
    g = sim._vec_array()
    pot.gradient(ya, g)
    gy = g.numpy()
    eps = 1e-6
    Ep = pot.energy(sim._vec_array(y + eps * dirn))[0]
    Em = pot.energy(sim._vec_array(y - eps * dirn))[0]
    fd = (Ep - Em) / (2 * eps)
    assert fd == pytest.approx(float((gy * dirn).sum()), rel=1e-6)
    # Hessian-vector product against the difference of gradients
    H = sim._pattern.to_scipy(pot.assemble_hessian(ya, sim._hess_values))
    gp, gm = sim._vec_array(), sim._vec_array()
    pot.gradient(sim._vec_array(y + eps * dirn), gp)
    pot.gradient(sim._vec_array(y - eps * dirn), gm)
    hv_fd = ((gp.numpy() - gm.numpy()) / (2 * eps)).reshape(-1)
    hv = (H @ dirn.reshape(-1)) * free.reshape(-1)
    assert np.abs(hv - hv_fd).max() <= 1e-5 * np.abs(hv).max()


def test_newton_iteration_reads_back_a_bounded_number_of_values(rng):
    """Outside the linear solve a Newton iteration reads back from the device at most once per
    energy (each line-search trial), once per gradient and once for the direction check."""
    sim = _sim("bdf2", tol=1e-10, cg_tol=1e-10)
    sim.step()
    counts = {"numpy": 0}
    to_numpy, solve = wp.array.numpy, sim._linear_solve
    inside = [0]

    def counted(self):
        counts["numpy"] += inside[0] == 0
        return to_numpy(self)

    def counted_solve(*a, **kw):  # the Newton systems' linear solver: its read-backs are its own
        inside[0] += 1
        try:
            return solve(*a, **kw)
        finally:
            inside[0] -= 1

    solver = sim._pcg
    finish = getattr(solver, "complete_deferred", None)
    if finish is not None:  # a deferred solve's further chunks (chunked PCG: CUDA, strict device mode) are its own too
        def counted_finish(*a, **kw):
            inside[0] += 1
            try:
                return finish(*a, **kw)
            finally:
                inside[0] -= 1
        solver.complete_deferred = counted_finish
    wp.array.numpy, sim._linear_solve = counted, counted_solve
    try:
        st = sim.step()
    finally:
        wp.array.numpy = to_numpy
        del sim._linear_solve
        if finish is not None:
            del solver.complete_deferred
    assert st.newton_iterations >= 2
    # start: energy + gradient; per iteration: direction check + (1 + line-search halvings) energies + gradient
    assert 0 < counts["numpy"] <= 2 + 3 * st.newton_iterations + st.line_search_steps, (counts, st)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_launch_helper_matches_wp_launch_and_survives_a_module_rebuild(precision):
    s, vec, _, npdt = wf.solvers.state.PRECISIONS[precision]
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((7, 3)), rng.standard_normal((7, 3))
    x, y = wp.array(a.astype(npdt), dtype=vec), wp.array(b.astype(npdt), dtype=vec)
    for _ in range(2):
        out = wp.zeros(7, dtype=vec)
        launch(LK.lincomb_kernel, 7, [s(2.0), x, s(-3.0), y, out], "cpu")
        np.testing.assert_allclose(out.numpy(), 2 * a - 3 * b, rtol=1e-6)
        LK.lincomb_kernel.module.mark_modified()  # the recorded launch must be re-recorded, not reused stale
