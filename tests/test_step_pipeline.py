"""The time step as a pipeline: step(state_in, state_out, control, dt) reads its input
state only, a failed step writes nothing, a steady step allocates no device array, and a Newton
iteration on the PCG path reads back from the device once (the start's energy and gradient ride
with the first iteration's read-back)."""

import numpy as np
import pytest
import warp as wp

import warpfem as wf
from warpfem.solvers.state import Control


def _model():
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(5, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=5e4, poisson_ratio=0.3, density=800.0),
                     gravity=(0.0, 0.0, -9.81))
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    return model


def _arrays(state):
    return [state.x.numpy().copy(), state.v.numpy().copy()] + [
        v.numpy().copy() for _, v in sorted(state.history.items()) if isinstance(v, wp.array)]


@pytest.mark.parametrize("integrator", ["bdf2", "newmark"])
def test_step_of_states_is_a_pure_function_of_its_input(integrator):
    sim = wf.Simulator(_model(), dt=0.02, integrator=integrator, damping_mass=0.3, linear_solver="pcg", tol=1e-9,
                       cg_tol=1e-10)
    for _ in range(3):  # a moving state with history
        sim.step()
    s_in = sim.new_state()
    before = _arrays(s_in)
    out1, out2 = sim.new_state(), sim.new_state()
    top = np.flatnonzero(sim.model.fixed.any(axis=1))[:2]
    control = Control(targets={int(i): sim.model.rest_positions[i] + [0.0, 0.0, 0.01] for i in top}, load_scale=0.5)
    sim.step(s_in, out1, control)
    sim.step(s_in, out2, control)
    for a, b in zip(before, _arrays(s_in)):  # the input is untouched
        assert np.array_equal(a, b)
    for a, b in zip(_arrays(out1), _arrays(out2)):  # same input, same output, bit for bit
        assert np.array_equal(a, b)
    assert out1.time == pytest.approx(s_in.time + 0.02, abs=1e-15)
    x1 = out1.x.numpy()
    np.testing.assert_allclose(x1[top], sim.model.rest_positions[top] + [0.0, 0.0, 0.01], atol=1e-12)
    # the convenience step from the same state and control does the same
    sim.set_targets(top, sim.model.rest_positions[top] + [0.0, 0.0, 0.01])
    sim.load_scale = 0.5
    x_conv = sim.state  # the simulator's own state equals s_in (nothing stepped it since)
    assert np.array_equal(x_conv.x.numpy(), before[0])
    sim.step()
    assert np.array_equal(sim.positions(), x1.astype(np.float64))
    with pytest.raises(ValueError, match="distinct output state"):
        sim.step(s_in, s_in)


def test_failed_step_of_states_writes_nothing():
    sim = wf.Simulator(_model(), dt=0.05, integrator="newmark", require_convergence=True, max_iters=1, tol=1e-12,
                       linear_solver="pcg")
    sim.step_count = 0
    s_in = sim.new_state()
    s_out = sim.new_state()
    s_out.x.fill_(7.0)
    before_in, before_out = _arrays(s_in), _arrays(s_out)
    with pytest.raises(wf.SolveFailed, match="did not converge"):
        sim.step(s_in, s_out)
    for a, b in zip(before_in + before_out, _arrays(s_in) + _arrays(s_out)):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_steady_steps_allocate_no_device_array_and_read_back_once_per_newton_iteration(integrator):
    sim = wf.Simulator(_model(), dt=0.02, integrator=integrator, damping_mass=0.2, damping_stiffness=0.01,
                       linear_solver="pcg", tol=1e-8, cg_tol=1e-6)
    for _ in range(3):
        sim.step()
    counts = {"arrays": 0, "reads": 0}
    init, to_numpy = wp.array.__init__, wp.array.numpy

    def counted_init(self, *a, **kw):
        counts["arrays"] += 1
        return init(self, *a, **kw)

    def counted_numpy(self):
        counts["reads"] += 1
        return to_numpy(self)

    newton = steps = launches = syncs = cg = 0
    wp.array.__init__, wp.array.numpy = counted_init, counted_numpy
    try:
        for _ in range(4):
            st = sim.step()
            newton += st.newton_iterations
            launches += st.launches
            syncs += st.newton_syncs + st.host_syncs
            cg += st.linear_iterations
            steps += 1
    finally:
        wp.array.__init__, wp.array.numpy = init, to_numpy
    assert counts["arrays"] == 0
    assert newton >= steps
    # one read-back per Newton iteration, linear solves included (the CPU PCG: one launch per solve)
    assert counts["reads"] == newton
    assert syncs == counts["reads"]
    # reported launches: a few tens per iteration, not hundreds; plus, where PCG runs in chunks of k
    # iterations (CUDA, strict device mode) instead of one serial launch, 3 per iteration and chunk slack
    pcg = sim._pcg
    k = 0 if pcg.cpu_serial else pcg.check_every
    assert 0 < launches <= 40 * newton + (3 * (cg + k * newton) + 3 * newton if k else 0)


@pytest.mark.parametrize("linear_solver", ["pcg", "direct"])
def test_captured_newton_iterations_replay_the_same_launches(linear_solver, monkeypatch):
    """The Newton iteration's launches before and after the linear solve are captured once per key
    as a graph (Warp's CPU operation stream here) and replayed: the trajectory is bit for bit the
    one of plain launches, the launch count is the same, and a material changed in place (a struct
    field, packed by value into a graph) is a new key, not a stale replay."""
    import warpfem.kernels.generic as G

    def run(capture):
        monkeypatch.setattr(G, "CAPTURE_SEQUENCES", capture)
        sim = wf.Simulator(_model(), dt=0.02, integrator="bdf2", damping_mass=0.3, linear_solver=linear_solver,
                           tol=1e-6, cg_tol=1e-4)
        launches, xs = 0, []
        for k in range(6):
            if k == 4:  # stiffer from here on, in place
                sim.material_params.mu = 2.0 * float(sim.material_params.mu)
            launches += sim.step().launches
            xs.append(sim.positions())
        return np.array(xs), launches, sim._potential.graphs

    plain, n_plain, g_plain = run(False)
    replayed, n_replayed, g = run(True)
    assert g_plain.replays == 0 and g.captures >= 2 and g.replays >= 6
    assert np.abs(plain[-1] - plain[0]).max() > 1e-3  # it moves
    np.testing.assert_array_equal(replayed, plain)
    assert n_replayed == n_plain


def test_sequences_inside_a_callers_capture_are_recorded_there():
    """Inside a caller's own capture (e.g. a user capturing their loop) a captured sequence is not
    replayed nor captured again (no nested capture): its work goes into the caller's graph."""
    sim = wf.Simulator(_model(), dt=0.02, integrator="backward_euler", linear_solver="pcg", tol=1e-6, cg_tol=1e-4)
    sim.step()
    graphs, tmp = sim._potential.graphs, sim._potential.work.tmp

    def fill():
        tmp.fill_(1.0)

    graphs.run(("probe",), fill)  # first time: as is
    graphs.run(("probe",), fill)  # second: captured and replayed
    captures, replays = graphs.captures, graphs.replays
    assert replays >= 1
    tmp.zero_()
    with wp.ScopedCapture(device="cpu") as cap:
        graphs.run(("probe",), fill)
    assert (graphs.captures, graphs.replays) == (captures, replays)
    assert np.abs(tmp.numpy()).max() == 0.0  # recorded into the caller's graph, not executed
    wp.capture_launch(cap.graph)
    assert np.all(tmp.numpy() == 1.0)
