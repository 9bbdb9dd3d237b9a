"""Semi-definite and singular Newton systems (issue: PARDISO's non-positive pivot on one CPU).

A projected Hessian is only positive *semi*-definite: the SPD projection clamps the negative
eigenvalues of each element's dP/dF to exactly zero, and in a static solve (no mass term) a
deformation mode that every element clamps is a global zero eigenvalue. Whether a Cholesky
factorisation then meets a pivot of +1e-10 or -1e-10 is round-off, i.e. the CPU's MKL code path.
These tests pin the outcome to every backend and to a forced pivot failure, so no CPU decides it:
the direct solver shifts, deflates the near-null space and still solves what can be solved.
"""

import numpy as np
import pytest
import scipy.sparse as sp

import warpfem as wf
from kernels_bench import stability_cases as S
from warpfem.model import rigid_body_modes
from warpfem.solvers.linear import make_linear_solver
from warpfem.solvers.linear import direct as D

BACKENDS = D.available_backends()


def _free_body_stiffness(cells=(3, 1, 1)):
    """Stiffness K of a free linear-elastic bar (no fixed DOF, no mass): exactly six zero
    eigenvalues (the rigid motions). Returns (sim, K block values, dense K, rigid-mode basis)."""
    mesh = wf.box_tet_mesh(size=(3.0, 1.0, 1.0), cells=cells)
    model = wf.Model(mesh, wf.make_material("linear", youngs_modulus=1e5, poisson_ratio=0.3, density=100.0))
    sim = wf.Simulator(model, precision="float64", linear_solver="pcg")
    vals = sim._pattern.new_values()
    sim._assemble_stiffness(sim.x, 1.0, vals)
    K = sim._pattern.to_scipy(vals).toarray()
    R = np.linalg.qr(rigid_body_modes(mesh.vertices))[0]
    return sim, vals, K, R


def _direct(sim, backend):
    return make_linear_solver("direct", sim._pattern, vec_type=sim._vec, scalar=sim._s, backend=backend)


def test_free_body_stiffness_really_has_six_zero_eigenvalues():
    _, _, K, R = _free_body_stiffness()
    w = np.linalg.eigvalsh(K)
    assert np.all(np.abs(w[:6]) < 1e-9 * w[-1]) and w[6] > 1e-4 * w[-1]
    assert np.abs(K @ R).max() < 1e-9 * np.abs(K).max()


@pytest.mark.parametrize("backend", BACKENDS)
def test_consistent_singular_system_is_solved_to_tolerance(backend):
    sim, vals, K, R = _free_body_stiffness()
    rng = np.random.default_rng(1)
    b = rng.standard_normal(K.shape[0])
    b -= R @ (R.T @ b)  # in the range of K: a solution exists (not unique)
    solver = _direct(sim, backend)
    bd, xd = sim._vec_array(b.reshape(-1, 3)), sim._vec_array()
    res = solver.solve(vals, sim._mask, bd, xd, tol=1e-10, maxiter=1)
    x = xd.numpy().ravel()
    assert not res.failed
    assert res.shift > 0.0 or res.deflated > 0  # the singularity was seen, whatever the pivot's sign
    assert res.deflated == 6  # all six rigid motions found by the inverse iteration
    assert res.converged and res.residual <= 1e-10
    assert np.linalg.norm(K @ x - b) <= 1e-9 * np.linalg.norm(b)
    assert np.abs(R.T @ x).max() <= 1e-9 * np.linalg.norm(x)  # the minimum-norm solution


@pytest.mark.parametrize("backend", BACKENDS)
def test_inconsistent_singular_system_gives_a_descent_step(backend):
    sim, vals, K, R = _free_body_stiffness()
    rng = np.random.default_rng(2)
    b_range = rng.standard_normal(K.shape[0])
    b_range -= R @ (R.T @ b_range)
    c = np.array([1.0, -2.0, 0.5, 0.0, 3.0, 1.0])
    b = b_range + R @ c  # a net force and torque on a free body: no solution
    solver = _direct(sim, backend)
    bd, xd = sim._vec_array(b.reshape(-1, 3)), sim._vec_array()
    res = solver.solve(vals, sim._mask, bd, xd, tol=1e-10, maxiter=1)
    x = xd.numpy().ravel()
    assert res.deflated == 6 and not res.failed
    assert np.all(np.isfinite(x)) and b @ x > 0.0  # -g . d < 0: a descent direction of the potential
    # the range part is solved exactly; along the rigid motions a step of the size the smallest
    # positive curvature gives (not 1/delta: no blow-up). The curvature used is a Ritz value, an
    # upper bound of the smallest positive eigenvalue, so the step is at most c / lam_7.
    x_range = x - R @ (R.T @ x)
    assert np.linalg.norm(K @ x_range - b_range) <= 1e-9 * np.linalg.norm(b_range)
    lam_plus = np.linalg.eigvalsh(K)[6]
    ratio = (R.T @ x)[c != 0] / (c[c != 0] / lam_plus)
    assert np.all((ratio > 0.5) & (ratio <= 1.0 + 1e-9)), ratio
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)  # one curvature for the whole null space


@pytest.mark.parametrize("backend", BACKENDS)
def test_forced_pivot_failure_on_an_spd_matrix_still_solves_it(monkeypatch, backend):
    """Whatever a CPU's code path does with the first factorisation, the answer is the same."""
    mesh = wf.box_tet_mesh(size=(3.0, 0.5, 0.5), cells=(4, 1, 1))
    model = wf.Model(mesh, wf.make_material("linear", youngs_modulus=1e5, poisson_ratio=0.3, density=100.0))
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    sim = wf.Simulator(model, precision="float64", linear_solver="pcg")
    vals = sim._pattern.new_values()
    sim._assemble_stiffness(sim.x, 1.0, vals)
    m = (~model.fixed).astype(np.float64).ravel()
    A = sim._pattern.to_scipy(vals)
    Am = (sp.diags(m) @ A @ sp.diags(m) + sp.diags(1.0 - m)).toarray()
    b = np.random.default_rng(3).standard_normal(len(m)) * m
    solver = _direct(sim, backend)
    real_factor, calls = solver.backend.factor, []

    def flaky(Amat):  # the unshifted matrix "fails", as on the CPU of the issue
        calls.append(1)
        if len(calls) == 1:
            raise D._NotPositiveDefinite("forced non-positive pivot")
        return real_factor(Amat)

    monkeypatch.setattr(solver.backend, "factor", flaky)
    bd, xd = sim._vec_array(b.reshape(-1, 3)), sim._vec_array()
    res = solver.solve(vals, sim._mask, bd, xd, tol=1e-12, maxiter=1)
    x = xd.numpy().ravel()
    assert res.shift == pytest.approx(D.SHIFTS[0] * np.abs(np.diag(Am)[m > 0]).max())
    assert res.deflated == 0  # SPD: nothing below the null tolerance
    assert res.converged and solver.shifted_factorisations == 1
    np.testing.assert_allclose(x, np.linalg.solve(Am, b), rtol=1e-9, atol=1e-14)
    assert np.all(x.reshape(-1, 3)[model.fixed] == 0.0)


def test_uniaxial_cell_static_matrix_is_singular_at_each_load_step_start():
    """The root cause, measured: the first Newton matrix of a load step of the one-cell uniaxial
    case (stable neo-Hookean, nu 0.49, x stretched to 1.5) has one zero eigenvalue: a homogeneous
    state, the pure-shear mode diag(0, e, -e) clamped by every element's projection, no mass."""
    mats = []
    real = D.DirectSolver._prepare

    def record(self, values, mask):
        mats.append((self.host_matrix(values, mask).toarray(), self._mask_host.copy()))
        return real(self, values, mask)

    D.DirectSolver._prepare = record
    try:
        r = S.incompressible("stable_neo_hookean", "float64", 0.49, a=1.5, cells=(1, 1, 1), linear_solver="direct",
                             hessian_projection="always")  # projected Newton's matrices are the subject
    finally:
        D.DirectSolver._prepare = real
    assert r["not_converged"] == 0 and r["failed"] == 0 and r["J_rel_error"] < 1e-7
    A, m = mats[0]
    if not np.allclose(A, A.T):
        U = np.triu(A) if np.allclose(np.tril(A, -1), 0) else np.tril(A)
        A = U + U.T - np.diag(np.diag(U))
    free = m > 0
    w, V = np.linalg.eigh(A[np.ix_(free, free)])
    assert abs(w[0]) < 1e-12 * w[-1] and w[1] > 1e-3 * w[-1]
    v = np.zeros(len(m))
    v[free] = V[:, 0]
    X = wf.box_tet_mesh(size=(1.0, 1.0, 1.0), cells=(1, 1, 1)).vertices
    mode = np.c_[0 * X[:, 0], X[:, 1], -X[:, 2]].ravel()  # u = (0, Y, -Z)
    assert abs(abs(v @ mode) / np.linalg.norm(mode) - 1.0) < 1e-6


@pytest.mark.parametrize("backend", BACKENDS)
def test_nearly_incompressible_static_converges_with_every_backend_and_reports_singular_solves(backend):
    import warpfem.simulator as SM

    seen = []
    real = SM.newton_solve

    def spy(pot, y, opts):
        st = real(pot, y, opts)
        seen.append(st.singular_solves)
        return st

    SM.newton_solve = spy
    try:
        r = S.incompressible("stable_neo_hookean", "float64", 0.499, a=1.5, cells=(1, 1, 1), linear_solver="direct",
                             linear_solver_options={"backend": backend}, hessian_projection="always")
    finally:
        SM.newton_solve = real
    assert r["not_converged"] == 0 and r["failed"] == 0, r
    assert r["J_rel_error"] < 1e-7
    assert sum(seen) >= 1  # the singular systems are counted in the step's stats


def test_static_solve_of_a_body_free_to_rotate_names_the_motion():
    mesh = wf.box_tet_mesh(size=(2.0, 1.0, 1.0), cells=(2, 1, 1))
    model = wf.Model(mesh, wf.make_material("linear", youngs_modulus=1e5, poisson_ratio=0.3, density=100.0),
                     gravity=(0.0, 0.0, -9.81))
    X = mesh.vertices
    model.fix(np.flatnonzero((X[:, 1] == 0) & (X[:, 2] == 0)))  # one edge along x: x, y, z all fixed somewhere
    assert model.free_rigid_motions() == ["rotation about the x axis through (1, 0, 0)"]
    sim = wf.Simulator(model, precision="float64")
    x0 = sim.positions()
    with pytest.raises(ValueError, match=r"still free: rotation about the x axis through \(1, 0, 0\)"):
        sim.solve_static()
    np.testing.assert_array_equal(sim.positions(), x0)
    model.fix(np.flatnonzero((X[:, 1] == 1) & (X[:, 2] == 0)), "z")
    assert model.free_rigid_motions() == []
    free = wf.Model(mesh, model.material)
    assert len(free.free_rigid_motions()) == 6
    free.fix([0])
    assert [t.split(" through")[0] for t in free.free_rigid_motions()] == [
        "rotation about the x axis", "rotation about the y axis", "rotation about the z axis"]
