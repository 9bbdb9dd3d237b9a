"""The reduced step's evaluation and Newton loop: the per-point cubature path (F = I + G z on the
host, one material kernel, host reductions) against the per-element path and finite differences,
and the kept / BFGS-updated Newton matrix against plain Newton (same solution, fewer Hessians)."""

import numpy as np
import pytest

import warpfem as wf
from warpfem.reduced import CubatureForces, ReducedSimulator, Subspace, build_basis
from warpfem.reduced.cubature import Cubature
from warpfem.reduced.subspace import material_parameters, mesh_hash


def _beam(E=2e5, cells=(8, 1, 1)):
    mesh = wf.box_tet_mesh(size=(4.0, 0.5, 0.5), cells=cells)
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=0.3, density=100.0), gravity=(0, 0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2)))
    return mesh, model


@pytest.fixture(scope="module")
def beam_subspace():
    mesh, model = _beam()
    basis = build_basis(model, modes=10, modal_derivatives_=True)
    m = mesh.num_tets
    rng = np.random.default_rng(5)
    elements = np.sort(rng.choice(m, size=m // 2, replace=False))
    cub = Cubature(elements, np.full(len(elements), m / len(elements)), 0.0, 0.0, 0.0, np.zeros((0, 0)), 0.0,
                   len(elements), 0, True)
    return mesh, model, Subspace(basis, cub, mesh_hash(model), material_parameters(model))


def test_point_path_matches_per_element_path_and_finite_differences(beam_subspace):
    mesh, model, sub = beam_subspace
    U = sub.U
    rng = np.random.default_rng(0)
    cub = sub.cubature
    w = rng.uniform(0.5, 2.0, cub.num_points)
    cf = CubatureForces(model, U, cub.elements, w)
    # a large pose: the beam bent and twisted well beyond the linear range
    q = 0.6 * rng.standard_normal(U.shape[1]) / np.abs(U).max()
    for project in (False, True):
        E, f, K = cf.evaluate(q, hessian=True, project=project)
        E0, f0, K0 = cf.evaluate_per_element(q, hessian=True, project=project)
        assert abs(E - E0) <= 1e-10 * abs(E0)
        assert np.abs(f - f0).max() <= 1e-10 * np.abs(f0).max()
        assert np.abs(K - K0).max() <= 1e-10 * np.abs(K0).max()
        assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()
    # f = -dE/dq and K = -df/dq (exact Hessian) by central differences
    E, f, K = cf.evaluate(q, hessian=True, project=False)
    h = 1e-6 * max(1.0, np.abs(q).max())
    r = len(q)
    f_fd, K_fd = np.zeros(r), np.zeros((r, r))
    for j in range(r):
        e = np.zeros(r)
        e[j] = h
        Ep, fp, _ = cf.evaluate(q + e)
        Em, fm, _ = cf.evaluate(q - e)
        f_fd[j] = -(Ep - Em) / (2 * h)
        K_fd[:, j] = -(fp - fm) / (2 * h)
    assert np.abs(f - f_fd).max() <= 1e-6 * np.abs(f).max()
    assert np.abs(K - K_fd).max() <= 1e-6 * np.abs(K).max()
    # float32 evaluates the same quantities to its precision
    cf32 = CubatureForces(model, U, cub.elements, w, precision="float32")
    E32, f32, K32 = cf32.evaluate(q, hessian=True, project=False)
    assert abs(E32 - E) <= 1e-5 * abs(E)
    assert np.abs(f32 - f).max() <= 1e-4 * np.abs(f).max()
    assert np.abs(K32 - K).max() <= 1e-4 * np.abs(K).max()


def test_copy_path_of_a_gpu_equals_the_zero_copy_path(beam_subspace, monkeypatch):
    """On a GPU the point arrays are copied to and from the device; the same code on the CPU."""
    import warpfem.reduced.simulator as S

    _, model, sub = beam_subspace
    q = 0.3 * np.random.default_rng(1).standard_normal(sub.U.shape[1]) / np.abs(sub.U).max()
    direct = CubatureForces(model, sub.U, sub.cubature.elements, sub.cubature.weights)
    monkeypatch.setattr(S, "_COPY_ARRAYS", True)
    copied = CubatureForces(model, sub.U, sub.cubature.elements, sub.cubature.weights)
    assert not copied._zero_copy
    for hessian in (False, True):
        a, b = direct.evaluate(q, hessian=hessian), copied.evaluate(q, hessian=hessian)
        assert a[0] == b[0] and np.array_equal(a[1], b[1])
        assert (a[2] is None and b[2] is None) or np.array_equal(a[2], b[2])
    rs = ReducedSimulator(model, sub, dt=1 / 30)
    for _ in range(3):
        assert rs.step().converged
    assert np.abs(rs.q).max() > 0


def _run(model, sub, steps, **kw):
    rs = ReducedSimulator(model, sub, dt=1 / 30, damping_mass=0.5, tol=1e-10, **{k: v for k, v in kw.items() if k != "reuse"})
    rs.reuse_newton_matrix = kw.get("reuse", True)
    qs, stats = [], []
    for _ in range(steps):
        stats.append(rs.step())
        qs.append(rs.q.copy())
    return np.array(qs), stats, rs


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_kept_newton_matrix_converges_to_the_newton_solution_with_fewer_hessians(beam_subspace, integrator):
    _, model, sub = beam_subspace
    q_newton, st_newton, _ = _run(model, sub, 12, reuse=False, integrator=integrator)
    q_kept, st_kept, rs = _run(model, sub, 12, reuse=True, integrator=integrator)
    assert all(s.converged for s in st_newton + st_kept)
    assert np.abs(rs.positions() - model.rest_positions).max() > 0.1  # the beam really swings (m)
    # the same solution of every step, to the solver tolerance (1e-10 relative gradient)
    assert np.abs(q_kept - q_newton).max() <= 1e-8 * np.abs(q_newton).max()
    it_newton = np.mean([s.newton_iterations for s in st_newton])
    h_newton = np.mean([s.hessian_evaluations for s in st_newton])
    h_kept = np.mean([s.hessian_evaluations for s in st_kept])
    it_kept = np.mean([s.newton_iterations for s in st_kept])
    # plain Newton on the exact Hessian: quadratic, 3 iterations per step to 1e-10 (measured 3.00 for
    # each integrator), one Hessian per iteration
    assert it_newton <= 3.0 and h_newton == pytest.approx(it_newton, abs=1.0)
    # the kept matrix: far fewer Hessians (measured 0.08-0.67 per step against 3), at most 2.5x the
    # (cheap) iterations (measured 5.7-6.6)
    assert h_kept <= 0.3 * h_newton
    assert it_kept <= 2.5 * it_newton


def test_failed_step_leaves_state_and_drops_the_kept_matrix(beam_subspace):
    _, model, sub = beam_subspace
    rs = ReducedSimulator(model, sub, dt=1 / 30, tol=1e-12, max_iters=1, require_convergence=True)
    with pytest.raises(wf.SolveFailed):
        for _ in range(5):
            q0, v0, t0 = rs.q.copy(), rs.qdot.copy(), rs.time
            rs.step()
    assert np.array_equal(rs.q, q0) and np.array_equal(rs.qdot, v0) and rs.time == t0
    assert rs._newton_matrix is None
    rs.options.max_iters = 30
    st = rs.step()
    assert st.converged and np.all(np.isfinite(rs.q))


def test_step_potential_energy_and_gradient_match_the_cubature_forces(beam_subspace):
    """The fused evaluation of a step's potential E(v) = 1/2 |v - v_hat|_M^2 + s/2 v^T C v + V(z_b + s v)
    - s v^T f_ext and its gradient against the same terms from CubatureForces.evaluate, and the
    gradient against central differences of the energy."""
    _, model, sub = beam_subspace
    rs = ReducedSimulator(model, sub, dt=1 / 30, damping_mass=0.5, integrator="newmark")
    for _ in range(3):
        rs.step()
    zb, zhat, s = rs.predict()
    pot = rs._pot.begin(zb=zb, v_hat=zhat, adot_hat=zhat[:0], adot=zhat[:0], s=s)
    rng = np.random.default_rng(3)
    v = rs.qdot + 0.3 * np.abs(rs.qdot).max() * rng.standard_normal(rs.r)
    E, _ = pot.energy(v)
    g = np.zeros(rs.r)
    pot.gradient(v, g)
    V, f, _ = rs.forces.evaluate(zb + s * v)
    M, C = rs.mass_r, rs.damping_mass * rs.mass_r
    dv = v - zhat
    E_ref = 0.5 * dv @ M @ dv + 0.5 * s * v @ C @ v + V - s * v @ rs.fext_r
    g_ref = M @ dv + s * C @ v - s * f - s * rs.fext_r
    assert E == pytest.approx(E_ref, rel=1e-12)
    assert np.abs(g - g_ref).max() <= 1e-11 * np.abs(g_ref).max()
    h = 1e-6 * np.abs(v).max()
    for j in range(0, rs.r, 3):
        e = np.zeros(rs.r)
        e[j] = h
        fd = (pot.energy(v + e)[0] - pot.energy(v - e)[0]) / (2 * h)
        assert fd == pytest.approx(g_ref[j], abs=1e-6 * np.abs(g_ref).max())


def test_float32_reduced_steps_track_float64(beam_subspace):
    """float32 cubature (float64 host products and Newton solve): the same trajectory to float32's precision."""
    _, model, sub = beam_subspace
    qs = []
    for precision in ("float64", "float32"):
        rs = ReducedSimulator(model, sub, dt=1 / 30, damping_mass=0.5, precision=precision, tol=1e-5)
        for _ in range(6):
            assert rs.step().converged
        qs.append(rs.q.copy())
    assert np.abs(qs[0]).max() > 1e-3
    assert np.abs(qs[1] - qs[0]).max() <= 2e-5 * np.abs(qs[0]).max()  # measured 9e-7


def test_direct_cpu_launch_equals_warps_own_launch(beam_subspace, monkeypatch):
    """RecordedLaunch calls the CPU entry point directly on the Warp versions it was checked
    against; the results equal Warp's own (public) launch bit for bit."""
    import warp as wp

    import warpfem.kernels.generic as G

    _, model, sub = beam_subspace
    q = 0.3 * np.random.default_rng(2).standard_normal(sub.U.shape[1]) / np.abs(sub.U).max()
    fast = CubatureForces(model, sub.U, sub.cubature.elements, sub.cubature.weights)
    a = [fast.evaluate(q, hessian=h) for h in (False, True)]
    checked = tuple(int(v) for v in wp.config.version.split(".")[:2]) in G._DIRECT_CPU_CALL_WARP
    # (a launch split across CPU threads runs its chunks as recorded launches of their own)
    used = [p for rl in fast._launch.values() for p in (rl._parts or [rl]) if p._cmd]
    assert used and all((rl._direct is not None) == checked for rl in used)
    monkeypatch.setattr(G, "_DIRECT_CPU_CALL_WARP", set())
    public = CubatureForces(model, sub.U, sub.cubature.elements, sub.cubature.weights)
    b = [public.evaluate(q, hessian=h) for h in (False, True)]
    assert all(p._direct is None for rl in public._launch.values() for p in (rl._parts or [rl]))
    for (Ea, fa, Ka), (Eb, fb, Kb) in zip(a, b):
        assert Ea == Eb and np.array_equal(fa, fb)
        assert (Ka is None and Kb is None) or np.array_equal(Ka, Kb)


def test_point_kernel_split_across_threads_gives_the_same_bits(beam_subspace, monkeypatch):
    """The per-point kernel with the Hessian runs in chunks on 2 threads (every point writes its own
    outputs; the reductions are dense host products): the same energy, force and stiffness bits."""
    import warpfem.kernels.generic as G
    import warpfem.threads as TH

    monkeypatch.setattr(G, "MIN_CHUNK", 1)
    monkeypatch.setattr(TH, "available_cores", lambda: 4)
    _, model, sub = beam_subspace
    q = 0.3 * np.random.default_rng(4).standard_normal(sub.U.shape[1]) / np.abs(sub.U).max()
    cf = CubatureForces(model, sub.U, sub.cubature.elements, sub.cubature.weights)
    out = []
    try:
        for T in (1, 2, 2):  # (the second run on 2 threads replays the recorded chunks)
            TH.set_threads(T)
            E, f, K = cf.evaluate(q, hessian=True, project=False)
            out.append((E, f.tobytes(), K.tobytes()))
        assert len(cf._launch[(1, 0)]._parts) == 2
    finally:
        TH.set_threads(None)
    assert out[0] == out[1] == out[2]


def test_load_scale_is_a_control_of_the_reduced_step(beam_subspace):
    """load_scale scales the external forces of the reduced step as it does in full space."""
    _, model, sub = beam_subspace
    qdots = []
    for scale in (0.0, 0.5, 1.0):
        rs = ReducedSimulator(model, sub, dt=1 / 60, tol=1e-12)
        rs.load_scale = scale
        rs.step()
        qdots.append(rs.qdot.copy())
    assert np.array_equal(qdots[0], np.zeros_like(qdots[0]))  # no load: the rest state stays
    assert np.abs(qdots[2]).max() > 0.0
    np.testing.assert_allclose(qdots[1], 0.5 * qdots[2], rtol=0, atol=1e-3 * np.abs(qdots[2]).max())


def test_reduced_step_of_states_reads_its_input_only(beam_subspace):
    """The reduced simulator shares step(state_in, state_out, control, dt) (solvers.state.StepperBase):
    the input state is not written and the convenience step from the same state gives the same result."""
    _, model, sub = beam_subspace
    rs = ReducedSimulator(model, sub, dt=1 / 60, integrator="bdf2", tol=1e-10)
    rs.reuse_newton_matrix = False  # the plain Newton path: the same iterates whatever came before
    for _ in range(2):
        rs.step()
    s_in, s_out = rs.new_state(), rs.new_state()
    before = (s_in.x.copy(), s_in.v.copy(), s_in.history["x_prev"].copy(), s_in.time)
    st = rs.step(s_in, s_out)
    assert st.converged
    assert np.array_equal(s_in.x, before[0]) and np.array_equal(s_in.v, before[1])
    assert np.array_equal(s_in.history["x_prev"], before[2]) and s_in.time == before[3]
    assert s_out.time == pytest.approx(before[3] + 1 / 60, abs=1e-15)
    rs.step()
    np.testing.assert_allclose(rs.q, s_out.x[:rs.r], rtol=0, atol=1e-12 * np.abs(rs.q).max())
    np.testing.assert_allclose(rs.qdot, s_out.v[:rs.r], rtol=0, atol=1e-10 * np.abs(rs.qdot).max())
