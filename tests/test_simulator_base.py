"""One simulator base (solvers.state.StepperBase / SimulatorBase) for the full-space, stiffness-warping
and reduced simulators: stiffness warping as one Newton iteration of its quadratic potential against
a warped step assembled independently in numpy; the reduced simulator's State, failure handling and
energies against the full simulator's."""

import numpy as np
import pytest
import scipy.sparse

import warpfem as wf
from warpfem.reduced import ReducedSimulator, Subspace
from warpfem.reduced.cubature import Cubature
from warpfem.solvers.state import State
from warpfem.solvers.stiffness_warping import StiffnessWarpingSimulator, tet_linear_stiffness_blocks

MESH = wf.box_tet_mesh(size=(3.0, 1.0, 1.0), cells=(3, 1, 1))
LEFT = wf.select_vertices_in_box(MESH, (-1, -1, -1), (1e-6, 2, 2))
RIGHT = wf.select_vertices_in_box(MESH, (3 - 1e-6, -1, -1), (4, 2, 2))


def _model(E=2e4, gravity=(0.0, 0.0, -9.81), fixed=(LEFT, RIGHT)):
    m = wf.Model(MESH, wf.make_material("corotated", youngs_modulus=E, poisson_ratio=0.3, density=100.0),
                 gravity=gravity)
    for idx in fixed:
        m.fix(idx)
    return m


def _polar(F):
    U, _, Vt = np.linalg.svd(F)
    R = U @ Vt
    assert np.linalg.det(R) > 0  # no inverted element in these states
    return R


def _warped_reference(model, x, v, h, alpha, beta, targets, integrator, load_scale):
    """One warped step (backward Euler or Newmark) from (x, v), assembled and solved densely in numpy:
    R_e from the polar decomposition of F = Ds Dm^-1, K' = sum R K_e R^T, f0' = -sum R K_e X, then
    the linear system of the step on the free components, the fixed ones at their prescribed velocity."""
    X, T, n = MESH.vertices, MESH.tets, MESH.num_vertices
    qd = model.quadrature
    Ke = tet_linear_stiffness_blocks(qd.qp_dNdX, qd.qp_weight, model.material.mu_lame, model.material.lam_lame)
    K = np.zeros((3 * n, 3 * n))
    f0 = np.zeros(3 * n)
    for e, tet in enumerate(T):
        Dm = (X[tet[1:]] - X[tet[0]]).T
        Ds = (x[tet[1:]] - x[tet[0]]).T
        R = _polar(Ds @ np.linalg.inv(Dm))
        for a in range(4):
            ia = slice(3 * tet[a], 3 * tet[a] + 3)
            for b in range(4):
                ib = slice(3 * tet[b], 3 * tet[b] + 3)
                K[ia, ib] += R @ Ke[e, a, b] @ R.T
                f0[ia] -= R @ Ke[e, a, b] @ X[tet[b]]
    M = scipy.sparse.kron(model.mass, scipy.sparse.identity(3)).toarray()
    C = alpha * M + beta * K
    fext = load_scale * model.external_forces().reshape(-1)
    free = ~model.fixed.reshape(-1)
    xf, vf = x.reshape(-1), v.reshape(-1)
    if integrator == "backward_euler":
        xb, vh, s = xf, vf, h
    else:  # Newmark: a_0 from the equations of motion on the free components
        rhs = -(K @ xf + f0) + fext - C @ vf
        a0 = np.zeros(3 * n)
        a0[free] = np.linalg.solve(M[np.ix_(free, free)], rhs[free])
        xb, vh, s = xf + 0.5 * h * vf, vf + 0.5 * h * a0, 0.5 * h
    # grad E(y) = M (y - vh) + s C y + s (K' (xb + s y) + f0') - s f_ext = A y - b
    A = M + s * C + s * s * K
    b = M @ vh - s * (K @ xb + f0) + s * fext
    p = x.copy()
    for i, t in targets.items():
        p[i] = t
    y = (p.reshape(-1) - xb) / s  # the prescribed part (fixed components only)
    y[free] = np.linalg.solve(A[np.ix_(free, free)], b[free] - A[np.ix_(free, ~free)] @ y[~free])
    return (xb + s * y).reshape(-1, 3), y.reshape(-1, 3)


@pytest.mark.parametrize("integrator", ["backward_euler", "newmark"])
def test_warped_step_through_the_newton_loop_equals_the_direct_warped_solve(integrator):
    """Stiffness warping runs as one Newton iteration of the quadratic WarpedElasticForm through
    newton_solve: the step equals the linear system of Mueller et al.'s warped step, assembled and
    solved in numpy (rotated, deformed, moving start; Rayleigh damping; a moving handle; a load scale)."""
    model = _model()
    h, alpha, beta = 0.02, 0.4, 2e-3
    sw = StiffnessWarpingSimulator(model, dt=h, damping_mass=alpha, damping_stiffness=beta, cg_tol=1e-12,
                                   integrator=integrator)
    rng = np.random.default_rng(7)
    Rz = np.array([[np.cos(0.6), -np.sin(0.6), 0.0], [np.sin(0.6), np.cos(0.6), 0.0], [0.0, 0.0, 1.0]])
    x0 = MESH.vertices @ Rz.T + 0.03 * rng.standard_normal(MESH.vertices.shape)
    v0 = 0.5 * rng.standard_normal(MESH.vertices.shape)
    v0[model.fixed.any(axis=1)] = 0.0
    sw.set_positions(x0)
    sw.set_velocities(v0)
    sw.load_scale = 0.7
    targets = {int(i): x0[i] + [0.0, 0.02, 0.05] for i in RIGHT}
    sw.set_targets(list(targets), np.array(list(targets.values())))
    x_ref, v_ref = _warped_reference(model, x0, v0, h, alpha, beta, targets, integrator, 0.7)
    st = sw.step()
    assert st.converged and st.newton_iterations == 1 and st.residual <= 1e-12
    assert st.newton_syncs == 1  # the whole Newton iteration reads back once (the fused step)
    du = np.abs(x_ref - x0).max()
    assert du > 1e-3  # a real step
    np.testing.assert_allclose(sw.positions(), x_ref, rtol=0, atol=1e-10 * du)
    np.testing.assert_allclose(sw.velocities(), v_ref, rtol=0, atol=1e-10 * np.abs(v_ref).max())
    np.testing.assert_allclose(sw.positions()[RIGHT], x0[RIGHT] + [0.0, 0.02, 0.05], rtol=0, atol=1e-12)


def test_warping_total_energy_scales_the_load_and_a_failed_step_leaves_the_state():
    """total_energy is the base's (kinetic + elastic - load_scale x^T f_ext); a NaN load raises
    SolveFailed before the state, its time or the step count change."""
    model = _model(fixed=(LEFT,))
    sw = StiffnessWarpingSimulator(model, dt=0.02, cg_tol=1e-10)
    for _ in range(3):
        sw.step()
    sw.load_scale = 0.4
    x, v = sw.positions(), sw.velocities()
    M = scipy.sparse.kron(model.mass, scipy.sparse.identity(3))
    ke = 0.5 * v.reshape(-1) @ (M @ v.reshape(-1))
    ref = ke + sw.elastic_energy() - 0.4 * x.reshape(-1) @ model.external_forces().reshape(-1)
    assert sw.kinetic_energy() == pytest.approx(ke, rel=1e-12) and ke > 0
    assert sw.total_energy() == pytest.approx(ref, rel=1e-12)
    t, count = sw.time, sw.step_count
    model.forces[5] = np.nan
    sw.sync_model()
    with pytest.raises(wf.SolveFailed, match="diverged"):
        sw.step()
    assert np.array_equal(sw.positions(), x) and np.array_equal(sw.velocities(), v)
    assert sw.time == t and sw.step_count == count


def _identity_subspace(model):
    free = np.flatnonzero(~model.fixed.reshape(-1))
    U = np.zeros((3 * model.num_vertices, len(free)))
    U[free, np.arange(len(free))] = 1.0
    basis = wf.reduced.Basis(U=U, linear_frequencies=np.zeros(0), frequencies=np.zeros(0))
    return Subspace(basis, Cubature.full(MESH.num_tets), wf.reduced.mesh_hash(model),
                    wf.reduced.subspace.material_parameters(model))


def test_reduced_state_is_a_state_and_its_energies_are_the_full_ones():
    """The reduced simulator's state is a State of coordinate arrays (q, qdot views of it, two
    buffers in turn); with the identity basis and every tet in the cubature its kinetic, elastic and
    total energies (load scale included) equal the full simulator's at the same state."""
    model = _model(fixed=(LEFT,))
    rs = ReducedSimulator(model, _identity_subspace(model), dt=0.05, tol=1e-11)
    buffers = {id(rs.state.x)}
    for _ in range(3):
        rs.step()
        buffers.add(id(rs.state.x))
    assert isinstance(rs.state, State) and len(buffers) == 2  # two states used in turn, no allocation
    assert np.shares_memory(rs.q, rs.state.x) and np.shares_memory(rs.qdot, rs.state.v)
    rs.load_scale = 0.6
    fs = wf.Simulator(model)
    fs.set_positions(rs.positions())
    fs.set_velocities(rs.velocities())
    fs.load_scale = 0.6
    assert rs.kinetic_energy() > 0
    assert rs.kinetic_energy() == pytest.approx(fs.kinetic_energy(), rel=1e-12)
    assert rs.elastic_energy() == pytest.approx(fs.elastic_energy(), rel=1e-10)
    assert rs.total_energy() == pytest.approx(fs.total_energy(), rel=1e-10)


def test_reduced_step_takes_dt_as_its_argument_and_a_failed_step_leaves_the_state():
    """step(dt=...) steps by the argument without changing the simulator's dt (how the coarse training
    steps of reduced scenes run) and equals step(state_in, state_out, dt=...) from the same state,
    which does not write state_in; a NaN load raises SolveFailed and leaves state, history and time."""
    model = _model(fixed=(LEFT,))
    rs = ReducedSimulator(model, _identity_subspace(model), dt=0.05, tol=1e-11, integrator="bdf2")
    rs.reuse_newton_matrix = False  # the same Newton iterates whatever came before
    for _ in range(2):
        rs.step()
    s_in, s_out = rs.new_state(), rs.new_state()
    before = (s_in.x.copy(), s_in.v.copy(), s_in.history["x_prev"].copy(), s_in.time)
    rs.step(s_in, s_out, dt=0.1)
    assert np.array_equal(s_in.x, before[0]) and np.array_equal(s_in.v, before[1])
    assert np.array_equal(s_in.history["x_prev"], before[2]) and s_in.time == before[3]
    rs.step(dt=0.1)
    assert rs.dt == 0.05 and rs.time == pytest.approx(before[3] + 0.1, abs=1e-15)
    assert np.abs(rs.q - before[0][:rs.r]).max() > 1e-4  # it moved
    np.testing.assert_allclose(rs.q, s_out.x[:rs.r], rtol=0, atol=1e-12 * np.abs(rs.q).max())
    q, qdot, hist, t, count = rs.q.copy(), rs.qdot.copy(), rs.state.history["x_prev"].copy(), rs.time, rs.step_count
    model.forces[7] = np.nan
    rs.sync_model()
    with pytest.raises(wf.SolveFailed, match="diverged"):
        rs.step()
    assert np.array_equal(rs.q, q) and np.array_equal(rs.qdot, qdot) and rs.time == t and rs.step_count == count
    assert np.array_equal(rs.state.history["x_prev"], hist)
