"""Simulator(initial_guess="extrapolated"): the Newton solve of a step starts from v_n extrapolated
at constant acceleration (Newmark: v_n + h a_n) instead of v_n. Same converged steps, a start
nearer the solution, fewer Newton iterations under an absolute stopping criterion; fixed
components and kinematic targets exactly as with the old start."""

import numpy as np
import pytest

import warpfem as wf

# an absolute criterion: with the default relative one (||g|| <= tol ||g_0||) a better start
# only tightens the target (docs/integrators.md, "Initial guess")
ABS = dict(tol=1e-12, atol=1e-7, cg_tol=1e-8)
STEPS = 15


def _beam():
    mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=(6, 2, 2))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=2e4, poisson_ratio=0.3, density=100.0)
    model = wf.Model(mesh, mat, gravity=(0, 0, -9.81))
    fixed = wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 1, 1))
    model.fix(fixed)
    return mesh, model, fixed


def _run(model, integrator, guess, steps=STEPS, targets=None):
    # projected Newton (linear convergence) is where a nearer start saves iterations; on demand both
    # starts converge quadratically in 2 iterations per step here (docs/integrators.md)
    sim = wf.Simulator(model, dt=1 / 60, integrator=integrator, initial_guess=guess, hessian_projection="always", **ABS)
    its, g0 = [], []
    for k in range(steps):
        if targets is not None:
            sim.set_targets(*targets(k))
        st = sim.step()
        assert st.converged, st.reason
        its.append(st.newton_iterations)
        g0.append(st.gradient_norm / st.residual)
    return sim, np.array(its), np.array(g0)


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_extrapolated_guess_same_steps_from_a_nearer_start(integrator):
    mesh, model, fixed = _beam()
    sim_p, its_p, g0_p = _run(model, integrator, "previous")
    sim_e, its_e, g0_e = _run(model, integrator, "extrapolated")
    # the same trajectory to the solve's tolerance (the beam's tip falls ~0.35 m)
    assert np.abs(sim_e.positions() - sim_p.positions()).max() < 1e-7
    assert np.abs(sim_e.velocities() - sim_p.velocities()).max() < 1e-5
    # the start's gradient is several times smaller once the history exists (first step: v_n in both)
    assert g0_e[0] == pytest.approx(g0_p[0], rel=1e-12)
    assert np.median(g0_e[2:] / g0_p[2:]) < 0.3
    assert its_e.sum() <= its_p.sum()
    if integrator == "backward_euler":  # measured 43 against 49
        assert its_e.sum() <= 0.9 * its_p.sum()
    # fixed vertices exactly at rest
    assert np.array_equal(sim_e.positions()[fixed], mesh.vertices[fixed])


def test_extrapolated_guess_keeps_kinematic_targets_exact():
    mesh, model, fixed = _beam()

    def targets(k):  # the clamped end moves up, accelerating
        return fixed, mesh.vertices[fixed] + np.array([0.0, 0.0, 0.002 * (k + 1) ** 2])

    sim_p, _, _ = _run(model, "backward_euler", "previous", steps=6, targets=targets)
    sim_e, _, g0_e = _run(model, "backward_euler", "extrapolated", steps=6, targets=targets)
    # the fixed components come from the targets in both runs, bit for bit
    assert np.array_equal(sim_e.positions()[fixed], sim_p.positions()[fixed])
    assert np.allclose(sim_e.positions()[fixed], targets(5)[1], rtol=0, atol=1e-12)
    assert np.abs(sim_e.positions() - sim_p.positions()).max() < 1e-7


def test_state_change_restarts_the_extrapolation_and_bad_choice_is_rejected():
    _, model, _ = _beam()
    sims = [wf.Simulator(model, dt=1 / 60, initial_guess=g, **ABS) for g in ("previous", "extrapolated")]
    for sim in sims:
        sim.step()
        sim.step()
    assert "guess_v_prev" in sims[1].state.history and "guess_v_prev" not in sims[0].state.history
    for sim in sims:
        sim.set_velocities(np.zeros((sim.num_vertices, 3)))
    assert "guess_v_prev" not in sims[1].state.history
    # the step after the change starts from v_n (= 0) in both: the same starting gradient
    st_p, st_e = (sim.step() for sim in sims)
    assert st_e.gradient_norm / st_e.residual == pytest.approx(st_p.gradient_norm / st_p.residual, rel=1e-6)
    with pytest.raises(ValueError, match="initial_guess must be one of 'previous', 'extrapolated'"):
        wf.Simulator(model, initial_guess="linear")
