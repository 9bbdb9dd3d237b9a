"""Linear solvers of the Newton systems (warpfem.solvers.linear): accuracy against scipy, symbolic
analysis reuse, the host-sync bound of device PCG, AMG vs block-Jacobi on a nearly incompressible
beam, simulator agreement across solvers, scene key, clear errors."""

import math
import sys

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp

import warpfem as wf
from warpfem.kernels import linalg as LK
from warpfem.solvers.linear import LINEAR_SOLVERS, MissingExtra, make_linear_solver
from warpfem.solvers.linear.direct import available_backends

DIRECT_BACKENDS = available_backends()  # always ends with "superlu"
HAVE_AMG = True
try:
    import pyamg  # noqa: F401
except ImportError:  # pragma: no cover - the test extra installs it
    HAVE_AMG = False


def _system(cells=(6, 2, 2), nu=0.3, precision="float64", h2=1e-3, mass_scale=1.0, seed=0):
    """A masked SPD block system M + h^2 K of a clamped beam, its block values and a masked rhs."""
    mesh = wf.box_tet_mesh(size=(3.0, 0.5, 0.5), cells=cells)
    mat = wf.make_material("linear", youngs_modulus=1e5, poisson_ratio=nu, density=100.0)
    model = wf.Model(mesh, mat)
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    model.fix(np.nonzero(mesh.vertices[:, 0] > 3.0 - 1e-9)[0], "y")  # a partly fixed vertex set too
    sim = wf.Simulator(model, precision=precision, linear_solver="pcg")
    vals = sim._pattern.new_values()
    sim._assemble_stiffness(sim.x, h2, vals)
    wp.launch(LK.add_scaled_kernel, dim=sim._pattern.nnz, inputs=[sim._mass_values, sim._s(mass_scale), vals])
    m = (~model.fixed).astype(np.float64)
    b = np.random.default_rng(seed).standard_normal(m.shape) * m
    A = sim._pattern.to_scipy(vals)
    P = sp.diags(m.ravel())
    Am = (P @ A @ P + sp.diags(1.0 - m.ravel())).tocsc()
    return sim, model, vals, b, Am


def _make(name, sim, model, **opts):
    return make_linear_solver(name, sim._pattern, vec_type=sim._vec, scalar=sim._s,
                              positions=model.rest_positions, **opts)


CASES = [("pcg", {}, "float64"), ("pcg", {"check_every": 4}, "float32")]
CASES += [("direct", {"backend": b}, "float64") for b in DIRECT_BACKENDS]
CASES += [("direct", {"backend": DIRECT_BACKENDS[0]}, "float32")]
if HAVE_AMG:
    CASES += [("amg", {}, "float64")]


@pytest.mark.parametrize("name,opts,precision", CASES, ids=lambda c: str(c))
def test_solver_matches_spsolve_on_masked_spd_system(name, opts, precision):
    sim, model, vals, b, Am = _system(precision=precision)
    solver = _make(name, sim, model, **opts)
    x_ref = spla.spsolve(Am, b.ravel())
    bd, xd = sim._vec_array(b), sim._vec_array()
    tol = 1e-8 if precision == "float64" else 1e-5
    res = solver.solve(vals, sim._mask, bd, xd, tol=tol, maxiter=2000)  # the one-call (Newton) form
    assert res.converged, res
    x = xd.numpy().astype(np.float64).ravel()
    true_rel = np.linalg.norm(Am @ x - b.ravel()) / np.linalg.norm(b)
    eps = 1e-12 if precision == "float64" else 2e-6
    assert true_rel <= 4 * tol + eps
    # x error bounded by cond * residual; the system is well conditioned (mass dominated)
    assert np.linalg.norm(x - x_ref) / np.linalg.norm(x_ref) < 100 * (tol + eps)
    assert np.all(x.reshape(-1, 3)[model.fixed] == 0.0)  # fixed components stay zero
    # the split form gives the same answer
    solver.prepare(vals, sim._mask)
    xd2 = sim._vec_array()
    res2 = solver.solve(bd, xd2, tol=tol, maxiter=2000)
    assert res2.iterations == res.iterations
    np.testing.assert_allclose(xd2.numpy(), xd.numpy(), rtol=0, atol=1e-12 if precision == "float64" else 1e-6)


def test_a_direct_backend_with_symbolic_reuse_is_installed():
    # the test extra installs qdldl everywhere (and pypardiso on x86-64): the reuse test below runs
    assert [b for b in DIRECT_BACKENDS if b != "superlu"], "pip install -e '.[test]' installs qdldl"


@pytest.mark.parametrize("backend", [b for b in DIRECT_BACKENDS if b != "superlu"])
def test_direct_symbolic_analysis_done_once(backend):
    sim, model, vals, b, Am = _system()
    solver = _make("direct", sim, model, backend=backend)
    bd, xd = sim._vec_array(b), sim._vec_array()
    for scale in (1.0, 2.0, 5.0):  # three different matrices of the same pattern
        v = wp.clone(vals)
        wp.launch(LK.scale_copy_kernel, dim=len(v), inputs=[vals, sim._s(scale), v])
        solver.prepare(v, sim._mask)
        res = solver.solve(bd, xd, tol=1e-10, maxiter=1)
        x_ref = spla.spsolve(_scaled(Am, scale, model), b.ravel())
        np.testing.assert_allclose(xd.numpy().ravel(), x_ref, rtol=1e-9, atol=1e-12)
        assert res.converged
    assert solver.analyse_count == 1
    assert solver.prepare_count == 3
    assert solver.symbolic_count == 1


def _scaled(Am, scale, model):
    m = (~model.fixed).astype(np.float64).ravel()
    P = sp.diags(m)
    return (scale * (P @ Am @ P) + sp.diags(1.0 - m)).tocsc()


def test_direct_reports_indefinite_matrix_and_returns_a_descent_direction():
    sim, model, vals, b, Am = _system()
    solver = _make("direct", sim, model)
    v = wp.clone(vals)
    wp.launch(LK.scale_copy_kernel, dim=len(v), inputs=[vals, sim._s(-1.0), v])  # negative definite
    bd, xd = sim._vec_array(b), sim._vec_array()
    res = solver.solve(v, sim._mask, bd, xd, tol=1e-8, maxiter=1)
    assert not res.converged
    assert "positive definite" in res.failed or "pivot" in res.failed
    # x is the block-Jacobi direction inv(D) b of the (negated) matrix
    expect = np.einsum("nij,nj->ni", solver.inv_diag.numpy(), b)
    np.testing.assert_allclose(xd.numpy(), expect, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("k", [1, 5, 16])
def test_pcg_host_sync_bound(k):
    sim, model, vals, b, Am = _system(cells=(8, 2, 2), h2=1e-2)
    solver = _make("pcg", sim, model, check_every=k)
    bd, xd = sim._vec_array(b), sim._vec_array()
    res = solver.solve(vals, sim._mask, bd, xd, tol=1e-10, maxiter=5000)
    assert res.converged and res.iterations > 20
    assert res.host_syncs == math.ceil(res.iterations / k) or res.host_syncs == math.ceil(res.iterations / k) + 1
    assert res.host_syncs <= math.ceil(res.iterations / k) + 1
    # the iterations are those of the classic PCG (k only changes when the host looks)
    if k == 1:
        from warpfem.solvers.pcg import BlockJacobiPCG

        ref = BlockJacobiPCG(sim._pattern, vec_type=sim._vec, scalar=sim._s)
        r2 = ref.solve(vals, sim._mask, bd, sim._vec_array(), tol=1e-10, maxiter=5000)
        assert abs(r2.iterations - res.iterations) <= 1
    # maxiter is honoured on the device, mid-chunk
    res_cap = solver.solve(vals, sim._mask, bd, xd, tol=1e-14, maxiter=7)
    assert res_cap.iterations == 7 and not res_cap.converged


def test_simulator_step_reports_host_syncs_within_bound():
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(8, 2, 2))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    k = 8
    sim = wf.Simulator(model, dt=0.02, linear_solver="pcg", linear_solver_options={"check_every": k},
                       tol=1e-8, cg_tol=1e-6)
    for _ in range(2):
        st = sim.step()
        assert st.converged and st.newton_iterations >= 2
        assert st.linear_iterations == st.cg_iterations > 0
        per_solve = [h[3] for h in st.history]
        # one solve per Newton iteration (the last solve's iterations are in the history too)
        assert st.host_syncs <= sum(math.ceil(i / k) + 1 for i in per_solve)
        assert st.host_syncs <= math.ceil(st.linear_iterations / k) + 2 * st.newton_iterations
        assert st.host_syncs < st.linear_iterations  # far fewer than one per iteration


@pytest.mark.skipif(not HAVE_AMG, reason="pyamg not installed (pip install warpfem[amg])")
def test_amg_needs_far_fewer_iterations_than_block_jacobi_when_nearly_incompressible():
    # quasi-static stiffness (tiny mass) of a nu = 0.49 beam: block-Jacobi CG struggles
    sim, model, vals, b, Am = _system(cells=(16, 4, 4), nu=0.49, h2=1.0, mass_scale=1e-6)
    bd, xd = sim._vec_array(b), sim._vec_array()
    r_bj = _make("pcg", sim, model).solve(vals, sim._mask, bd, xd, tol=1e-6, maxiter=20000)
    r_amg = _make("amg", sim, model).solve(vals, sim._mask, bd, xd, tol=1e-6, maxiter=20000)
    assert r_bj.converged and r_amg.converged
    assert r_bj.iterations >= 8 * r_amg.iterations, (r_bj.iterations, r_amg.iterations)
    x_ref = spla.spsolve(Am, b.ravel())
    assert np.linalg.norm(xd.numpy().ravel() - x_ref) / np.linalg.norm(x_ref) < 1e-3


def _beam_model():
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(6, 2, 2))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    return model


SOLVERS = ["pcg", "direct"] + (["amg"] if HAVE_AMG else [])


def test_simulator_step_same_positions_with_every_linear_solver():
    out = {}
    for name in SOLVERS + ["auto"]:
        sim = wf.Simulator(_beam_model(), dt=0.02, linear_solver=name, tol=1e-10, cg_tol=1e-10)
        for _ in range(3):
            st = sim.step()
            assert st.converged
        out[name] = sim.positions()
    disp = np.abs(out["pcg"] - _beam_model().rest_positions).max()
    assert disp > 1e-3  # it moved
    for name in out:
        np.testing.assert_allclose(out[name], out["pcg"], rtol=0, atol=1e-8 * max(disp, 1.0))


def test_stiffness_warping_with_direct_matches_pcg():
    out = {}
    for name in ("pcg", "direct"):
        sim = wf.StiffnessWarpingSimulator(_beam_model(), dt=0.02, cg_tol=1e-10, linear_solver=name)
        for _ in range(2):
            st = sim.step()
            assert st.converged
        out[name] = sim.positions()
    np.testing.assert_allclose(out["direct"], out["pcg"], rtol=0, atol=1e-9)


def test_scene_key_selects_the_linear_solver(tmp_path):
    from warpfem.scenes import SceneError, load_scene

    from test_scenes import BASE

    p = tmp_path / "s.toml"
    p.write_text(BASE.replace('dt = 0.05', 'dt = 0.05\nlinear_solver = "direct"'))
    run = load_scene(p).build()
    assert run.sim._pcg.name == "direct"
    p.write_text(BASE.replace('dt = 0.05', 'dt = 0.05\nlinear_solver = "gmres"'))
    with pytest.raises(SceneError, match="linear_solver"):
        load_scene(p)


def test_unknown_solver_name_lists_the_available_ones():
    sim, model, vals, b, Am = _system(cells=(2, 1, 1))
    with pytest.raises(ValueError) as e:
        _make("cholesky", sim, model)
    for name in LINEAR_SOLVERS:
        assert name in str(e.value)
    with pytest.raises(ValueError, match="unknown linear solver 'cholesky'"):
        wf.Simulator(model, linear_solver="cholesky")
    with pytest.raises(TypeError, match="check_every"):
        _make("direct", sim, model, check_every=4)
    with pytest.raises(ValueError, match="unknown direct backend 'mumps'"):
        _make("direct", sim, model, backend="mumps")


@pytest.mark.parametrize("name,module,extra", [("amg", "pyamg", "amg"),
                                               ("direct:pardiso", "pypardiso", "direct"),
                                               ("direct:qdldl", "qdldl", "direct")])
def test_missing_extra_names_it(monkeypatch, name, module, extra):
    sim, model, vals, b, Am = _system(cells=(2, 1, 1))
    monkeypatch.setitem(sys.modules, module, None)  # import now raises ImportError
    solver, _, backend = name.partition(":")
    opts = {"backend": backend} if backend else {}
    with pytest.raises(MissingExtra, match=rf'pip install "warpfem\[{extra}\]"'):
        _make(solver, sim, model, **opts)


def test_tradeoff_grid_has_a_linear_solver_axis(tmp_path):
    from warpfem.tradeoff.study import GridError, TradeoffConfig, scene_document, variant_scene

    from test_scenes import BASE

    p = tmp_path / "s.toml"
    p.write_text(BASE)
    cfg = TradeoffConfig.from_dict({"linear_solver": "pcg", "cg_tol": 1e-6})
    assert "pcg" in cfg.name
    scene = variant_scene(scene_document(p), str(p), cfg)
    assert scene.spec.integrator["linear_solver"] == "pcg"
    assert scene.build().sim._pcg.name == "pcg"
    with pytest.raises(GridError, match="linear_solver"):
        TradeoffConfig.from_dict({"linear_solver": "lu"})


@pytest.mark.skipif(not HAVE_AMG, reason="pyamg not installed (pip install warpfem[amg])")
def test_amg_reuses_its_hierarchy_until_the_iterations_grow():
    sim, model, vals, b, Am = _system(cells=(8, 2, 2), h2=1e-2)
    solver = _make("amg", sim, model)
    bd, xd = sim._vec_array(b), sim._vec_array()
    its = []
    for scale in (1.0, 1.05, 1.1):  # a slowly drifting matrix: one build serves all three
        v = wp.clone(vals)
        wp.launch(LK.scale_copy_kernel, dim=len(v), inputs=[vals, sim._s(scale), v])
        res = solver.solve(v, sim._mask, bd, xd, tol=1e-8, maxiter=500)
        assert res.converged
        its.append(res.iterations)
        np.testing.assert_allclose(xd.numpy().ravel(), spla.spsolve(_scaled(Am, scale, model), b.ravel()),
                                   rtol=0, atol=1e-6 * np.abs(b).max())
    assert solver.setup_count == 1 and solver.prepare_count == 3
    # a stale hierarchy (forced) triggers a rebuild at the next prepare
    solver._stale = True
    solver.prepare(vals, sim._mask)
    assert solver.setup_count == 2
    always = _make("amg", sim, model, rebuild_every=1)
    for _ in range(2):
        always.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=500)
    assert always.setup_count == 2


def test_auto_rule_measured_chooses_the_cheapest_measured_solver(monkeypatch, cpu_rules):
    from warpfem.solvers.linear import auto

    # quasi-static nu = 0.499 beam: block-Jacobi PCG needs thousands of iterations, the others few
    # (PCG costs ~12x a direct solve there, ~3x at nu 0.49: a margin wall-clock noise cannot close)
    sim, model, vals, b, Am = _system(cells=(16, 4, 4), nu=0.499, h2=1.0, mass_scale=1e-6)
    x_ref = spla.spsolve(Am, b.ravel())
    bd, xd = sim._vec_array(b), sim._vec_array()
    assert 3 * sim._pattern.num_rows <= auto.EXPLORE_MIN_DOFS
    # a system this small keeps its starting solver whatever the timings (reproducible runs) ...
    small = _make("auto", sim, model, rule="measured", explore_seconds=0.0)
    small.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=20000)
    assert small.active == "pcg" and set(small.solvers) == {"pcg"} and small.explorations == 0
    # ... unless asked: explore_min_dofs = 0 measures it like a large one
    hard = _make("auto", sim, model, rule="measured", explore_seconds=0.0, explore_min_dofs=0)  # starts with PCG; measures the others at once
    r1 = hard.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=20000)
    assert hard.explorations == 1 and set(hard.costs) == set(hard.candidates)
    assert hard.active != "pcg" and hard.costs[hard.active] == min(hard.costs.values())
    assert hard.costs[hard.active] <= hard.switch_margin * hard.costs["pcg"]
    assert r1.converged  # the answer of the chosen solver
    np.testing.assert_allclose(xd.numpy().ravel(), x_ref, rtol=0, atol=1e-6 * np.abs(x_ref).max())
    for _ in range(2):  # later systems: the chosen solver, no new measurement
        r = hard.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=20000)
        assert r.converged
        np.testing.assert_allclose(xd.numpy().ravel(), x_ref, rtol=0, atol=1e-6 * np.abs(x_ref).max())
    assert hard.explorations == 1
    # a run whose systems are cheap stays put: nothing else is built or measured
    cheap = _make("auto", sim, model, rule="measured", explore_seconds=1e9)
    cheap.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=20000)
    assert cheap.active == "pcg" and set(cheap.solvers) == {"pcg"} and cheap.explorations == 0
    # a candidate not clearly cheaper (margin) is not taken
    stay = _make("auto", sim, model, rule="measured", switch_margin=1e-9, explore_seconds=0.0, explore_min_dofs=0)
    for _ in range(2):
        stay.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=20000)
    assert stay.active == "pcg" and stay.explorations == 1
    np.testing.assert_allclose(xd.numpy().ravel(), x_ref, rtol=0, atol=1e-6 * np.abs(x_ref).max())
    with pytest.raises(ValueError, match="candidate"):
        _make("auto", sim, model, candidates=("pcg", "gmres"))

    class _Pattern:
        def __init__(self, n, cuda=False):
            self.num_rows = n
            self.device = type("D", (), {"is_cuda": cuda})()

    monkeypatch.setattr(auto, "_pardiso_available", lambda: True)
    assert not auto.direct_allowed(_Pattern(1000, cuda=True))  # CUDA: PCG only
    assert auto.direct_allowed(_Pattern(auto.DIRECT_MAX_DOFS_CPU // 3))
    assert not auto.direct_allowed(_Pattern(auto.DIRECT_MAX_DOFS_CPU // 3 + 1))
    monkeypatch.setattr(auto, "_pardiso_available", lambda: False)
    assert auto.direct_allowed(_Pattern(auto.SUPERLU_MAX_DOFS_CPU // 3))
    assert not auto.direct_allowed(_Pattern(auto.SUPERLU_MAX_DOFS_CPU // 3 + 1))


def test_auto_rule_model_is_a_function_of_the_problem_not_of_the_clock(monkeypatch, cpu_rules):
    """The default rule picks by size and CG iterations: a timer returning noise (a loaded
    machine, exaggerated) changes neither the choice nor a bit of the answer."""
    from warpfem.solvers.linear import auto

    rng = np.random.default_rng(7)
    monkeypatch.setattr(auto.time, "perf_counter", lambda: float(rng.uniform(0.0, 1e3)))
    # quasi-static nu = 0.499 beam: block-Jacobi PCG needs thousands of CG iterations
    sim, model, vals, b, Am = _system(cells=(16, 4, 4), nu=0.499, h2=1.0, mass_scale=1e-6)
    n = 3 * sim._pattern.num_rows
    x_ref = spla.spsolve(Am, b.ravel())
    bd = sim._vec_array(b)

    def run(**opts):
        s = _make("auto", sim, model, **opts)
        chosen, xs = [], []
        for _ in range(3):
            xd = sim._vec_array()
            r = s.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=20000)
            assert r.converged
            chosen.append(s.active)
            xs.append(xd.numpy().copy())
        return s, chosen, xs

    # a size the rule gives to the small-system direct start: no switching, direct throughout
    s3, c3, _ = run(initial="size")
    assert c3 == ["direct"] * 3 and set(s3.solvers) == {"direct"}
    # above it (lowered to this beam), without multigrid: PCG, then direct once a solve passes the
    # iteration count of its size
    monkeypatch.setattr(auto, "SMALL_DIRECT_DOFS_CPU", n - 1)
    assert auto.switch_after_iterations(n) < 1000 and auto.switch_after_iterations(8000) == auto.SWITCH_AFTER_ITERATIONS
    s1, c1, x1 = run(candidates=("pcg", "direct"))
    s2, c2, x2 = run(candidates=("pcg", "direct"))
    assert c1 == c2 == ["direct", "direct", "direct"]  # the first system was solved by PCG, then switched
    assert set(s1.solvers) == {"pcg", "direct"} and s1.costs == {}  # nothing timed
    for a, c in zip(x1, x2):
        np.testing.assert_array_equal(a, c)  # bit for bit
        np.testing.assert_allclose(a.ravel(), x_ref, rtol=0, atol=1e-6 * np.abs(x_ref).max())
    # the first answer is PCG's own, bit for bit
    pcg = _make("pcg", sim, model)
    xd = sim._vec_array()
    pcg.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=20000)
    np.testing.assert_array_equal(xd.numpy(), x1[0])
    if HAVE_AMG:  # above MULTIGRID_MIN_DOFS: multigrid from the first solve, same bits as naming it
        monkeypatch.setattr(auto, "MULTIGRID_MIN_DOFS", n - 1)
        s4, c4, x4 = run(initial="size")
        assert c4 == ["multigrid"] * 3 and set(s4.solvers) == {"multigrid"}
        mg = _make("multigrid", sim, model)
        xd = sim._vec_array()
        mg.solve(vals, sim._mask, bd, xd, tol=1e-8, maxiter=20000)
        np.testing.assert_array_equal(xd.numpy(), x4[0])
        # below it, started with PCG: multigrid (the switch target when installed) after the first solve
        monkeypatch.setattr(auto, "MULTIGRID_MIN_DOFS", n + 1)
        s5, c5, x5 = run()
        assert c5 == ["multigrid"] * 3 and s5.switch_to == "multigrid"
        np.testing.assert_array_equal(x5[0], x1[0])  # PCG's
        np.testing.assert_array_equal(x5[1], x4[0])  # multigrid's
    with pytest.raises(ValueError, match="rule"):
        _make("auto", sim, model, rule="fastest")


def test_auto_in_a_simulator_repeats_bit_for_bit_under_timer_noise(monkeypatch, cpu_rules):
    """Inside the Newton loop (PCG deferred, its report read with the trial step): the switch past
    the iteration count happens on the same system in every run, whatever the clock says."""
    from warpfem.solvers.linear import auto

    monkeypatch.setattr(auto, "SMALL_DIRECT_DOFS_CPU", 100)  # this beam (300 unknowns) above it: PCG first
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(24, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e8, poisson_ratio=0.45, density=1000.0),
                     gravity=(0.0, 0.0, -9.81))
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))

    def run(seed):
        rng = np.random.default_rng(seed)
        monkeypatch.setattr(auto.time, "perf_counter", lambda: float(rng.uniform(0.0, 1e3)))
        sim = wf.Simulator(model, dt=1 / 60, tol=1e-8, cg_tol=1e-6)
        assert sim._pcg.active == "pcg" and sim._pcg.switch_iterations is not None
        xs, chosen = [], []
        for _ in range(3):
            sim.step()
            xs.append(sim.positions())
            chosen.append(sim._pcg.active)
        return np.array(xs), chosen

    x1, c1 = run(1)
    x2, c2 = run(2)
    assert c1 == c2 and c1[-1] == ("multigrid" if HAVE_AMG else "direct")  # switched, at the same point
    np.testing.assert_array_equal(x1, x2)
