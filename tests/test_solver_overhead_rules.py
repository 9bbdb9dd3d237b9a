"""The rules behind the per-step speed-ups: ``auto``'s small-system choice and its fallback, the
direct solver's iterative refinement, and the launch cache that re-packs only changed arguments."""

import numpy as np
import pytest
import warp as wp

import warpfem as wf
from warpfem.kernels import linalg as LK
from warpfem.kernels.generic import launch
from warpfem.solvers.linear import auto, make_linear_solver


def _beam(cells=(4, 1, 1), nu=0.3):
    mesh = wf.box_tet_mesh(size=(1.0, 0.25, 0.25), cells=cells)
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=nu, density=100.0),
                     gravity=(0.0, 0.0, -9.81))
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    return model


class _Pattern:
    def __init__(self, n, cuda=False):
        self.num_rows = n
        self.device = type("D", (), {"is_cuda": cuda})()


def test_auto_rule_direct_for_small_cpu_systems_only():
    assert auto.starts_direct(_Pattern(auto.SMALL_DIRECT_DOFS_CPU // 3))
    assert not auto.starts_direct(_Pattern(auto.SMALL_DIRECT_DOFS_CPU // 3 + 1))
    assert not auto.starts_direct(_Pattern(10, cuda=True))
    sim = wf.Simulator(_beam(), linear_solver="auto")
    assert sim._pcg.active == "direct"  # a simulator applies the size rule
    bare = make_linear_solver("auto", sim._pattern, vec_type=sim._vec, scalar=sim._s)
    assert bare.active == "pcg"  # the bare solver starts with PCG unless asked
    pinned = wf.Simulator(_beam(), linear_solver="auto", linear_solver_options={"initial": "pcg"})
    assert pinned._pcg.active == "pcg"


def test_auto_that_stays_direct_allocates_no_pcg_workspace():
    """A small CPU system starts direct; the PCG workspace (vectors, block-Jacobi diagonal) is only
    made when PCG is first used, and the steps agree with the direct solver's."""
    sims = {name: wf.Simulator(_beam(), linear_solver=name, dt=0.01) for name in ("auto", "direct")}
    solver = sims["auto"]._pcg
    assert solver.active == "direct" and solver.pcg is None and solver._inv_diag is None
    for _ in range(3):
        for sim in sims.values():
            assert sim.step().converged
    assert solver.active == "direct" and solver.pcg is None and solver._inv_diag is None
    assert solver.direct.prepare_count >= 3
    x_auto, x_direct = sims["auto"].positions(), sims["direct"].positions()
    assert np.abs(x_auto - sims["auto"].model.rest_positions).max() > 1e-4  # it moved
    np.testing.assert_array_equal(x_auto, x_direct)


def test_auto_hands_an_indefinite_system_to_pcg_for_good():
    sim = wf.Simulator(_beam(), linear_solver="auto", dt=0.01)
    solver = sim._pcg
    assert solver.active == "direct" and solver.pcg is None  # small CPU system: no PCG workspace yet
    vals = sim._pattern.new_values()
    sim._assemble_stiffness(sim.x, 1e-4, vals)
    wp.launch(LK.add_scaled_kernel, dim=sim._pattern.nnz, inputs=[sim._mass_values, sim._s(1.0), vals])
    neg = wp.clone(vals)
    wp.launch(LK.scale_copy_kernel, dim=len(neg), inputs=[vals, sim._s(-1.0), neg])  # negative definite
    b = sim._vec_array(np.random.default_rng(1).standard_normal((sim.num_vertices, 3)) * (~sim.model.fixed))
    x = sim._vec_array()
    res = solver.solve(neg, sim._mask, b, x, tol=1e-8, maxiter=200)
    assert solver.active == "pcg" and not solver._may_switch and solver.pcg is not None  # made on first use
    assert res.failed == ""  # PCG ran (it reports negative curvature, not a failed factorisation)
    res = solver.solve(vals, sim._mask, b, x, tol=1e-10, maxiter=2000)  # an SPD system later: still PCG
    assert solver.active == "pcg" and res.converged and res.iterations > 1


def test_direct_refinement_never_worsens_and_reports_the_true_residual():
    sim = wf.Simulator(_beam(cells=(8, 2, 2), nu=0.4999), linear_solver="direct")
    vals = sim._pattern.new_values()
    sim._assemble_stiffness(sim.x, 1.0, vals)  # stiffness only, clamped: SPD but ill-conditioned
    wp.launch(LK.add_scaled_kernel, dim=sim._pattern.nnz, inputs=[sim._mass_values, sim._s(1e-9), vals])
    b = sim._vec_array(np.random.default_rng(2).standard_normal((sim.num_vertices, 3)) * (~sim.model.fixed))
    x = sim._vec_array()
    A = sim._pattern.to_scipy(vals)
    m = (~sim.model.fixed).astype(np.float64).ravel()

    def true_residual():
        r = m * (A @ (m * x.numpy().ravel())) - b.numpy().ravel()
        return np.linalg.norm(r) / np.linalg.norm(b.numpy())

    plain = sim._pcg.solve(vals, sim._mask, b, x, tol=0.5, maxiter=1)  # loose: no refinement
    r_plain = true_residual()
    refined = sim._pcg.solve(vals, sim._mask, b, x, tol=1e-16, maxiter=1)
    r_refined = true_residual()
    # a refinement step is kept only if it lowers the residual: never worse than the plain solve
    # (that it rescues a 1e-12 tolerance at nu = 0.4999 is asserted by test_stability's warping case)
    assert r_refined <= r_plain * (1.0 + 1e-9), (r_plain, r_refined)
    for res, r in ((plain, r_plain), (refined, r_refined)):  # the reported residual is the true one
        assert abs(res.residual - r) <= 0.2 * r, (res.residual, r)


def test_cached_launch_repacks_changed_arguments():
    n = 7
    rng = np.random.default_rng(3)
    xs = [wp.array(rng.standard_normal((n, 3)), dtype=wp.vec3d) for _ in range(3)]
    out = wp.zeros(n, dtype=wp.vec3d)
    expect = []
    for a, xi, b, yi in ((1.0, 0, 2.0, 1), (1.0, 0, 2.0, 1), (3.0, 0, 2.0, 2), (-1.0, 2, 0.5, 2)):
        launch(LK.lincomb_kernel, n, [wp.float64(a), xs[xi], wp.float64(b), xs[yi], out], "cpu")
        expect.append(a * xs[xi].numpy() + b * xs[yi].numpy())
        np.testing.assert_allclose(out.numpy(), expect[-1], rtol=1e-14, atol=1e-14)


def test_cached_launch_with_kernel_structs(monkeypatch):
    """The quadrature-point kernels take ``QuadraturePoints`` / ``MaterialParams`` structs. The launch
    cache does not re-pack a struct passed again (its packed parameter is the instance's own C buffer),
    yet a field assigned in place and a new instance are both what the next launch computes with."""
    from warpfem.kernels import fem as FK
    from warpfem.kernels.structs import MaterialParams64, material_params

    sim = wf.Simulator(_beam(), precision="float64")
    x = sim.new_vector(sim.positions() * np.array([1.1, 0.95, 1.0]))
    P = wp.zeros(sim.num_points, dtype=wp.mat33d)
    mat = material_params(wp.float64, sim.model.material.kind, sim.model.material.kernel_mu,
                          sim.model.material.kernel_lam)
    assert isinstance(mat, MaterialParams64.instance_type)

    def stress(material):
        launch(FK.qp_stress_kernel, sim.num_points, [x, sim._points, material, P], "cpu")
        return P.numpy().copy()

    reference = sim.stresses(sim.positions() * np.array([1.1, 0.95, 1.0]))  # the simulator's own structs
    base = stress(mat)
    np.testing.assert_allclose(base, reference, rtol=1e-13, atol=0.0)
    repacked = []
    original = wp.Launch.set_param_at_index
    monkeypatch.setattr(wp.Launch, "set_param_at_index",
                        lambda self, i, v, *a, **k: (repacked.append(i), original(self, i, v, *a, **k))[1])
    np.testing.assert_array_equal(stress(mat), base)
    assert repacked == []  # nothing changed: nothing re-packed
    mat.mu = 2.0 * sim.model.material.kernel_mu  # in place: seen without a re-pack
    doubled = stress(mat)
    assert repacked == [] and np.abs(doubled - base).max() > 0.1 * np.abs(base).max()
    other = material_params(wp.float64, sim.model.material.kind, 2.0 * sim.model.material.kernel_mu,
                            sim.model.material.kernel_lam)
    np.testing.assert_allclose(stress(other), doubled, rtol=1e-14, atol=0.0)  # a new instance: re-packed
    assert repacked == [2]


def test_public_simulator_hooks_give_the_kernel_inputs():
    """What the benchmarks read from a simulator goes through public properties (no privates):
    the quadrature points integrate the volume, the mass blocks the mass, the types the precision."""
    model = _beam()
    for precision, s, dt, v in (("float64", wp.float64, np.float64, wp.vec3d), ("float32", wp.float32, np.float32, wp.vec3)):
        sim = wf.Simulator(model, precision=precision)
        assert sim.scalar_type is s and sim.numpy_dtype == dt and sim.vector_type is v
        assert sim.quadrature_points.weight.numpy().sum() == pytest.approx(0.0625, rel=1e-6)
        assert int(sim.material_params.kind) == model.material.kind
        m = sim.mass_values.numpy()
        assert np.trace(m, axis1=1, axis2=2).sum() == pytest.approx(3 * 100.0 * 0.0625, rel=1e-6)
        old = sim.linear_solver
        sim.linear_solver = old  # assignable (benchmarks put a baseline solver in its place)
        assert sim.linear_solver is old
