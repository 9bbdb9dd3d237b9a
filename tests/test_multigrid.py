"""The multigrid-preconditioned device PCG (warpfem.solvers.linear.multigrid): accuracy against a
direct solve in both precisions, fixed DOFs exactly zero, iteration counts flat under refinement and
far below block-Jacobi's, Galerkin coarse operators re-formed on the device, a mask that changes
between solves, and a simulation step equal to PCG's."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp

import warpfem as wf
from warpfem.kernels import linalg as LK

pytest.importorskip("pyamg")

from test_linear_solvers import _beam_model, _make, _system  # noqa: E402


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_multigrid_matches_spsolve_and_keeps_fixed_dofs_zero(precision):
    sim, model, vals, b, Am = _system(cells=(12, 3, 3), precision=precision, h2=1e-2)
    solver = _make("multigrid", sim, model, max_coarse=30)
    bd, xd = sim._vec_array(b), sim._vec_array()
    tol = 1e-8 if precision == "float64" else 1e-5
    res = solver.solve(vals, sim._mask, bd, xd, tol=tol, maxiter=200)
    assert res.converged and len(solver.levels) >= 2, (res, [lv.size for lv in solver.levels])
    x = xd.numpy().astype(np.float64).ravel()
    x_ref = spla.spsolve(Am, b.ravel())
    eps = 1e-12 if precision == "float64" else 2e-6
    assert np.linalg.norm(Am @ x - b.ravel()) / np.linalg.norm(b) <= 4 * tol + eps
    assert np.linalg.norm(x - x_ref) / np.linalg.norm(x_ref) < 100 * (tol + eps)
    assert np.all(x.reshape(-1, 3)[model.fixed] == 0.0)  # exactly, not to round-off
    # split form: same iterations, same answer
    solver.prepare(vals, sim._mask)
    xd2 = sim._vec_array()
    res2 = solver.solve(bd, xd2, tol=tol, maxiter=200)
    assert res2.iterations == res.iterations
    np.testing.assert_allclose(xd2.numpy(), xd.numpy(), rtol=0, atol=0)


def test_coarse_operators_are_the_galerkin_products_of_the_masked_matrix():
    sim, model, vals, b, Am = _system(cells=(12, 3, 3), h2=1e-2)
    # the V-cycle in float64 here, to compare the products to 1e-9 (float32 ones: test_float32_vcycle_*)
    solver = _make("multigrid", sim, model, max_coarse=30, coarse_update="every", preconditioner_precision="same")
    v = wp.clone(vals)
    for scale in (1.0, 3.0):  # re-formed on the device at every prepare, with the same prolongators
        wp.launch(LK.scale_copy_kernel, dim=len(v), inputs=[vals, sim._s(scale), v])
        solver.prepare(v, sim._mask)
        m = (~model.fixed).astype(np.float64).ravel()
        A = (sp.diags(m) @ sim._pattern.to_scipy(v) @ sp.diags(m)).toarray()  # free-space matrix
        np.testing.assert_allclose(solver._dense(solver.levels[0].A), A + np.diag(1.0 - m), rtol=0, atol=1e-9)
        for cur, nxt in zip(solver.levels[:-1], solver.levels[1:]):
            P = solver._dense(cur.P)
            A = P.T @ A @ P
            np.testing.assert_allclose(solver._dense(nxt.A), A, rtol=0, atol=1e-9 * np.abs(A).max())
    assert solver.setup_count == 1 and solver.prepare_count == 2 and solver.galerkin_count == 2


def test_lagged_coarse_operators_refresh_when_the_iterations_grow():
    sim, model, vals, b, Am = _system(cells=(12, 3, 3), h2=1e-2)
    solver = _make("multigrid", sim, model, max_coarse=30)  # coarse_update="lagged", the default
    bd, xd = sim._vec_array(b), sim._vec_array()
    v = wp.clone(vals)
    its = []
    for scale in (1.0, 1.1, 100.0, 100.0):  # a drifting matrix, then one the coarse operators no longer fit
        wp.launch(LK.scale_copy_kernel, dim=len(v), inputs=[vals, sim._s(scale), v])
        wp.launch(LK.add_scaled_kernel, dim=len(v), inputs=[sim._mass_values, sim._s(1.0 - scale), v])
        res = solver.solve(v, sim._mask, bd, xd, tol=1e-8, maxiter=300)
        assert res.converged  # valid (SPD) preconditioner with older coarse operators too
        m = (~model.fixed).astype(np.float64).ravel()
        A = sim._pattern.to_scipy(v)
        A = (sp.diags(m) @ A @ sp.diags(m) + sp.diags(1.0 - m)).tocsc()
        x = xd.numpy().ravel()
        assert np.linalg.norm(A @ x - b.ravel()) <= 1e-7 * np.linalg.norm(b)
        its.append(res.iterations)
    # one re-formation while the iterations stay (1.0, 1.1), one after they grew (100)
    assert solver.galerkin_count == 2, its
    assert its[2] > 1.5 * its[0] + 2 and its[3] < its[2], its


@pytest.mark.parametrize("nu", [0.3, 0.49])
def test_iterations_flat_under_refinement_and_far_below_block_jacobi(nu):
    # quasi-static stiffness of a clamped beam (tiny mass): the hard case for block-Jacobi
    its, bj = [], []
    # 16k to 66k unknowns, three levels each (the hierarchy's depth changes the count; the box
    # benchmark, kernels_bench/bench_scale.py, follows it to 98k tets)
    for c in (6, 8, 10):
        sim, model, vals, b, Am = _system(cells=(6 * c, c, c), nu=nu, h2=1.0, mass_scale=1e-6)
        bd, xd = sim._vec_array(b), sim._vec_array()
        r = _make("multigrid", sim, model).solve(vals, sim._mask, bd, xd, tol=1e-6, maxiter=500)
        assert r.converged
        x = xd.numpy().ravel()
        assert np.linalg.norm(Am @ x - b.ravel()) <= 1.01e-6 * np.linalg.norm(b)  # the true residual
        its.append(r.iterations)
        if c == 6:  # block-Jacobi on the smallest size (the larger would take thousands of iterations)
            rb = _make("pcg", sim, model).solve(vals, sim._mask, bd, sim._vec_array(), tol=1e-6, maxiter=20000)
            assert rb.converged
            x_ref = spla.spsolve(Am, b.ravel())
            assert np.linalg.norm(x - x_ref) / np.linalg.norm(x_ref) < 1e-4
            bj.append(rb.iterations)
    assert max(its) <= 1.5 * min(its), its
    assert bj[0] >= 8 * its[0], (bj, its)


def test_coarse_intervals_are_the_estimated_spectrum_and_save_iterations():
    # quasi-static nu 0.49 beam, three levels: the coarse levels' Chebyshev bound u is 1.1 times
    # rho(D^-1 A) of the operator they use (D the block l1 diagonal), the finest keeps the l1 bound
    # 1; with the block-weighted prolongation smoothing the CG needs fewer iterations than with
    # the bound 1 everywhere and the scalar-diagonal weighting (the defaults before)
    sim, model, vals, b, Am = _system(cells=(24, 4, 4), nu=0.49, h2=1.0, mass_scale=1e-6)
    bd = sim._vec_array(b)
    its = {}
    for name, opts in (("new", {}), ("old", dict(upper=1.0, smooth=("jacobi", {"omega": 4.0 / 3.0}))),
                       ("coarse6", dict(degree=(3, 6)))):
        solver = _make("multigrid", sim, model, max_coarse=30, **opts)
        solver.dense_estimate_below = 0  # the Lanczos estimate that the large levels get
        xd = sim._vec_array()
        r = solver.solve(vals, sim._mask, bd, xd, tol=1e-6, maxiter=500)
        assert r.converged and len(solver.levels) >= 3, (r, [lv.size for lv in solver.levels])
        assert np.linalg.norm(Am @ xd.numpy().ravel() - b.ravel()) <= 1.01e-6 * np.linalg.norm(b)
        its[name] = r.iterations
        if name == "old":
            assert solver.intervals == [1.0] * (len(solver.levels) - 1)
        if name != "new":
            continue
        assert solver.intervals[0] == 1.0
        for lv, u in zip(solver.levels[1:-1], solver.intervals[1:]):
            A = solver._dense(lv.A)
            nb = A.shape[0] // 6
            Dinv = lv.dinv.numpy().astype(np.float64).reshape(nb, 6, 6)
            DA = np.concatenate([Dinv[i] @ A[6 * i: 6 * i + 6] for i in range(nb)])
            lam = np.linalg.eigvals(DA).real.max()
            assert 0.3 < lam < 0.95 and abs(u - 1.1 * lam) <= 0.02 * u, (u, lam)
    assert its["new"] <= 0.9 * its["old"], its
    assert its["coarse6"] < its["new"], its  # degree 6 below the finest level: a stronger cycle


def test_changed_mask_between_solves():
    # a handle released between two solves: the hierarchy stays, the Galerkin products use the new mask
    sim, model, vals, b, Am = _system(cells=(12, 3, 3), h2=1e-2)
    solver = _make("multigrid", sim, model, max_coarse=30)
    bd, xd = sim._vec_array(b), sim._vec_array()
    assert solver.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=200).converged
    fixed = model.fixed.copy()
    fixed[np.nonzero(fixed.any(axis=1))[0][-3:]] = False  # three vertices released
    m = (~fixed).astype(np.float64)
    mask = sim._vec_array(m)
    rng = np.random.default_rng(1)
    b2 = rng.standard_normal(m.shape) * m
    A = sim._pattern.to_scipy(vals)
    A2 = (sp.diags(m.ravel()) @ A @ sp.diags(m.ravel()) + sp.diags(1.0 - m.ravel())).tocsc()
    res = solver.solve(vals, mask, sim._vec_array(b2), xd, tol=1e-8, maxiter=200)
    assert res.converged and solver.setup_count == 1
    x = xd.numpy().ravel()
    np.testing.assert_allclose(x, spla.spsolve(A2, b2.ravel()), rtol=0, atol=1e-6 * np.abs(x).max())
    assert np.all(x.reshape(-1, 3)[fixed] == 0.0)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_simulator_step_with_multigrid_equals_pcg(precision):
    out, stats = {}, {}
    tol = 1e-10 if precision == "float64" else 1e-5
    for name in ("pcg", "multigrid"):
        sim = wf.Simulator(_beam_model(), dt=0.02, linear_solver=name, tol=1e-6 if precision == "float32" else 1e-10,
                           cg_tol=tol, precision=precision)
        for _ in range(3):
            st = sim.step()
            assert st.converged
        out[name], stats[name] = sim.positions(), st
    disp = np.abs(out["pcg"] - _beam_model().rest_positions).max()
    assert disp > 1e-3
    atol = 1e-8 * max(disp, 1.0) if precision == "float64" else 1e-4 * disp
    np.testing.assert_allclose(out["multigrid"], out["pcg"], rtol=0, atol=atol)
    assert stats["multigrid"].linear_iterations < stats["pcg"].linear_iterations


def test_scene_key_and_bad_options(tmp_path):
    from warpfem.scenes import load_scene

    from test_scenes import BASE

    p = tmp_path / "s.toml"
    p.write_text(BASE.replace('dt = 0.05', 'dt = 0.05\nlinear_solver = "multigrid"'))
    run = load_scene(p).build()
    assert run.sim._pcg.name == "multigrid"
    sim, model, vals, b, Am = _system(cells=(2, 1, 1))
    with pytest.raises(ValueError, match="degree"):
        _make("multigrid", sim, model, degree=0)
    with pytest.raises(ValueError, match="lower"):
        _make("multigrid", sim, model, lower=1.5)
    with pytest.raises(ValueError, match="degree"):
        _make("multigrid", sim, model, degree=(3, 0))
    with pytest.raises(ValueError, match="lower"):
        _make("multigrid", sim, model, lower=(0.03, 1.0))
    with pytest.raises(ValueError, match="upper"):
        _make("multigrid", sim, model, upper=1.5)
    with pytest.raises(ValueError, match="safety"):
        _make("multigrid", sim, model, safety=0.5)
    with pytest.raises(ValueError, match="preconditioner_precision"):
        _make("multigrid", sim, model, preconditioner_precision="float16")
    with pytest.raises(TypeError, match="unknown option"):
        _make("multigrid", sim, model, rebuild_every=2)


def test_float32_vcycle_in_a_float64_solve_keeps_the_answer_and_the_iterations():
    # quasi-static nu 0.49 beam, three levels: the V-cycle in float32 (matrices, l1 inverses,
    # transfers, coarsest inverse), CG in float64; same solution to the CG tolerance, +-1 iteration
    sim, model, vals, b, Am = _system(cells=(24, 4, 4), nu=0.49, h2=1.0, mass_scale=1e-6)
    bd, tol = sim._vec_array(b), 1e-8
    x_ref = spla.spsolve(Am, b.ravel())
    out, A0 = {}, {}
    for pp in ("same", "float32"):
        solver = _make("multigrid", sim, model, max_coarse=30, preconditioner_precision=pp)
        xd = sim._vec_array()
        np.random.seed(0)  # pyamg's spectral radius estimate (prolongation smoothing) starts at random
        r = solver.solve(vals, sim._mask, bd, xd, tol=tol, maxiter=500)
        assert r.converged and len(solver.levels) >= 3, (r, [lv.size for lv in solver.levels])
        x = xd.numpy().ravel()
        assert x.dtype == np.float64
        assert np.linalg.norm(Am @ x - b.ravel()) <= 4 * tol * np.linalg.norm(b)
        assert np.linalg.norm(x - x_ref) <= 100 * tol * np.linalg.norm(x_ref)
        assert np.all(x.reshape(-1, 3)[model.fixed] == 0.0)
        want = wp.float32 if pp == "float32" else wp.float64
        assert all(lv.A.scalar_type == want and lv.x.dtype == want for lv in solver.levels)
        out[pp] = r.iterations
        A0[pp] = [solver._dense(lv.A) for lv in solver.levels]
    assert out["float32"] <= out["same"] + 1, out
    for a, b in zip(A0["float32"], A0["same"]):  # the float32 Galerkin products: float64's to rounding
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * np.abs(b).max())



def test_eisenstat_walker_forcing_saves_cg_iterations_and_keeps_the_result():
    from warpfem.solvers.linear.forcing import ForcingTerms

    ft = ForcingTerms("eisenstat_walker", cg_tol=1e-4, tol=1e-6)
    etas = [ft.next(g) for g in (1.0, 0.5, 0.05, 1e-4, 1e-7)]
    assert etas[0] == 0.1 and all(1e-4 <= e <= 0.1 for e in etas)
    assert etas[2] < etas[1]  # tighter as the gradient falls fast
    assert etas[-1] == min(0.1, 0.5 * 1e-6 * 1.0 / 1e-7)  # never tighter than the Newton tolerance needs
    assert ForcingTerms("fixed", cg_tol=1e-4, tol=1e-6).next(1.0) == 1e-4
    out, cg = {}, {}
    for forcing in ("fixed", "eisenstat_walker"):
        mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(12, 3, 3))
        mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.45, density=1000.0)
        model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
        model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
        sim = wf.Simulator(model, dt=0.02, linear_solver="pcg", tol=1e-8, cg_tol=1e-6, forcing=forcing)
        cg[forcing] = 0
        for _ in range(3):
            st = sim.step()
            assert st.converged
            cg[forcing] += st.linear_iterations
        out[forcing] = sim.positions()
    disp = np.abs(out["fixed"] - model.rest_positions).max()
    assert disp > 1e-3
    np.testing.assert_allclose(out["eisenstat_walker"], out["fixed"], rtol=0, atol=1e-6 * disp)
    assert cg["eisenstat_walker"] < 0.8 * cg["fixed"], cg
    with pytest.raises(ValueError, match="forcing"):
        wf.Simulator(model, forcing="newton")
