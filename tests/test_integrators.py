"""Time integrators (backward Euler, BDF2, Newmark average acceleration): measured order of
convergence against the exact modal solution and on a nonlinear cantilever, Newmark's exact energy
conservation on a linear system, BDF2's per-step amplification against its characteristic roots,
the stiff envelope (never NaN in the state), failed steps that keep the history, scenes."""

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

import warpfem as wf
from warpfem.integrators import backward_euler_amplification, bdf2_amplification, newmark_amplification

TIGHT = dict(tol=1e-12, cg_tol=1e-13, max_iters=10)
ORDER = {"backward_euler": 1.0, "bdf2": 2.0, "newmark": 2.0}


def _linear_cube(mass_matrix="lumped"):
    """1 x 1 x 1 m cube of 6 tets, face x = 0 clamped: 4 free vertices, 12 DOFs, linear elastic."""
    mesh = wf.box_tet_mesh(size=(1.0, 1.0, 1.0), cells=(1, 1, 1))
    model = wf.Model(mesh, wf.make_material("linear", youngs_modulus=1e4, poisson_ratio=0.3, density=100.0),
                     mass_matrix=mass_matrix)
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 2, 2)))
    return mesh, model


def _modes(sim, model):
    K = sim.stiffness_matrix().toarray()
    M = sim.mass_matrix().toarray()
    free = ~model.fixed.reshape(-1)
    w2, U = scipy.linalg.eigh(K[np.ix_(free, free)], M[np.ix_(free, free)])
    phi = np.zeros((3 * model.num_vertices, len(w2)))
    phi[free] = U
    return np.sqrt(w2), phi


def _slope(hs, errors):
    return float(np.polyfit(np.log(hs), np.log(errors), 1)[0])


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_order_of_convergence_against_exact_modal_solution(integrator):
    """u(t) = sum_i c_i cos(w_i t) phi_i for u(0) = sum_i c_i phi_i, v(0) = 0 (K phi = w^2 M phi)."""
    mesh, model = _linear_cube()
    sim = wf.Simulator(model, dt=1.0, integrator=integrator, **TIGHT)
    w, phi = _modes(sim, model)
    c = np.array([1e-3, 5e-4])
    u0 = phi[:, :2] @ c
    T = np.pi / w[0]  # half a period of the lowest mode
    hs, errors = [], []
    for N in (24, 48, 96):
        sim = wf.Simulator(model, dt=T / N, integrator=integrator, **TIGHT)
        sim.set_positions(mesh.vertices + u0.reshape(-1, 3))
        for _ in range(N):
            assert sim.step().converged
        exact = phi[:, :2] @ (c * np.cos(w[:2] * T))
        errors.append(np.abs((sim.positions() - mesh.vertices).reshape(-1) - exact).max() / np.abs(u0).max())
        hs.append(T / N)
    assert abs(_slope(hs, errors) - ORDER[integrator]) < 0.15, (hs, errors)


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_order_of_convergence_on_a_nonlinear_cantilever(integrator):
    """Stable neo-Hookean beam falling under gravity; no reference needed: the differences of
    successive halvings, |x_h - x_{h/2}| ~ C h^p, are fitted over 3 pairs (4 step sizes)."""
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(4, 1, 1))
    model = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3,
                                            density=1000.0), gravity=(0.0, -9.81, 0.0))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 2, 2)))
    T = 0.1
    finals = []
    for N in (4, 8, 16, 32):
        sim = wf.Simulator(model, dt=T / N, integrator=integrator, tol=1e-11, cg_tol=1e-12)
        for _ in range(N):
            assert sim.step().converged
        finals.append(sim.positions())
    diffs = [np.abs(a - b).max() for a, b in zip(finals[:-1], finals[1:])]
    assert diffs[-1] > 1e-9  # far above the solver tolerance
    assert abs(_slope([T / 4, T / 8, T / 16], diffs) - ORDER[integrator]) < 0.15, diffs


@pytest.mark.parametrize("mass_matrix,steps", [("lumped", 1000), ("consistent", 200)])
def test_newmark_conserves_energy_of_undamped_linear_system(mass_matrix, steps):
    mesh, model = _linear_cube(mass_matrix)
    sim = wf.Simulator(model, dt=0.01, integrator="newmark", **TIGHT)
    rng = np.random.default_rng(1)
    free = ~model.fixed
    sim.set_positions(mesh.vertices + 1e-3 * rng.standard_normal(mesh.vertices.shape) * free)
    sim.set_velocities(1e-2 * rng.standard_normal(mesh.vertices.shape) * free)
    E0 = sim.total_energy()
    energies = []
    for _ in range(steps):
        sim.step()
        energies.append(sim.total_energy())
    drift = np.abs(np.array(energies) - E0).max() / E0
    assert drift < 1e-8, drift
    # backward Euler on the same system loses energy every step
    be = wf.Simulator(model, dt=0.01, **TIGHT)
    be.set_positions(mesh.vertices + 1e-3 * rng.standard_normal(mesh.vertices.shape) * free)
    E0 = be.total_energy()
    for _ in range(10):
        be.step()
    assert be.total_energy() < 0.99 * E0


@pytest.mark.parametrize("integrator,amplification", [("backward_euler", backward_euler_amplification),
                                                      ("bdf2", bdf2_amplification),
                                                      ("newmark", newmark_amplification)])
def test_single_mode_energy_factor_matches_characteristic_root(integrator, amplification):
    """On a single linear mode the energy after step n is |z|^(2n) E_0 (up to BDF2's parasitic
    root, which dies out); z the principal root of the scheme's characteristic equation."""
    mesh, model = _linear_cube()
    sim = wf.Simulator(model, dt=1.0, **TIGHT)
    w, phi = _modes(sim, model)
    h = 0.6 / w[0]
    sim = wf.Simulator(model, dt=h, integrator=integrator, **TIGHT)
    sim.set_positions(mesh.vertices + 1e-3 * phi[:, 0].reshape(-1, 3))
    energies = [sim.total_energy()]
    for _ in range(30):
        sim.step()
        energies.append(sim.total_energy())
    factor = abs(amplification(w[0] * h)) ** 2
    measured = np.array(energies[21:]) / np.array(energies[20:-1])
    np.testing.assert_allclose(measured, factor, rtol=1e-7)
    if integrator == "bdf2":
        assert 0.9 < factor < 0.99  # second order: far less decay than backward Euler's 1 / (1 + 0.36)


def test_closed_form_roots_are_what_the_schemes_claim():
    for wh in (0.1, 0.5, 2.0):
        z = bdf2_amplification(wh)
        assert abs((1.5 - 1j * wh) * z * z - 2 * z + 0.5) < 1e-12
        assert abs(newmark_amplification(wh)) == pytest.approx(1.0, abs=1e-15)
    # local accuracy: z = e^{i wh} + O(h^{p+1})
    for amp, p in ((backward_euler_amplification, 1), (bdf2_amplification, 2), (newmark_amplification, 2)):
        e1, e2 = (abs(amp(wh) - np.exp(1j * wh)) for wh in (0.01, 0.005))
        assert np.log2(e1 / e2) == pytest.approx(p + 1, abs=0.05)


@pytest.mark.parametrize("integrator", ["bdf2", "newmark"])
def test_failed_step_keeps_state_and_history(integrator):
    """A step that raises SolveFailed changes nothing: the run continues exactly as without it."""
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(3, 1, 1))
    model = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 2, 2)))
    a = wf.Simulator(model, dt=0.02, integrator=integrator, tol=1e-10, cg_tol=1e-12)
    b = wf.Simulator(model, dt=0.02, integrator=integrator, tol=1e-10, cg_tol=1e-12, require_convergence=True)
    for _ in range(3):
        a.step()
        b.step()
    b.options.max_iters = 1
    with pytest.raises(wf.SolveFailed):
        b.step()
    b.options.max_iters = 30
    for _ in range(3):
        a.step()
        b.step()
    np.testing.assert_array_equal(a.positions(), b.positions())
    np.testing.assert_array_equal(a.velocities(), b.velocities())
    assert a.step_count == b.step_count == 6


def test_targets_are_reached_by_every_integrator():
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(3, 1, 1))
    model = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0))
    ids = wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 2, 2))
    model.fix(ids)
    for integrator in ("backward_euler", "bdf2", "newmark"):
        sim = wf.Simulator(model, dt=0.02, integrator=integrator, tol=1e-10, cg_tol=1e-12)
        for k in range(1, 4):
            target = mesh.vertices[ids] + [0.0, 0.01 * k, 0.0]
            sim.set_targets(ids, target)
            assert sim.step().converged
            np.testing.assert_allclose(sim.positions()[ids], target, atol=1e-12)


def test_bad_integrator_is_rejected_clearly():
    mesh, model = _linear_cube()
    with pytest.raises(ValueError, match="integrator must be one of 'backward_euler', 'bdf2', 'newmark'"):
        wf.Simulator(model, integrator="rk4")
    assert isinstance(wf.Simulator(model, integrator=wf.Newmark()).integrator, wf.Newmark)


def test_newmark_stiff_large_step_never_writes_nan():
    """Newmark is not L-stable: on E = 1e9, h = 1/10 s (the stiff cell of docs/stability.md) it must
    either stay bounded or report, and never write NaN to the state."""
    from kernels_bench import stability_cases as S

    for integrator in ("newton-newmark", "newton-bdf2"):
        r = S.cantilever_any("stable_neo_hookean", "float64", dt=0.1, youngs_modulus=1e9, integrator=integrator,
                             steps=6)
        assert r["verdict"] != "SILENT", r
        assert np.isfinite(r["tip_z"]), r
        assert r["min_J"] > 0, r


@pytest.mark.parametrize("name,cls", [("bdf2", wf.BDF2), ("newmark", wf.Newmark), ("backward_euler", wf.BackwardEuler)])
def test_scene_integrator_types(tmp_path, name, cls):
    from warpfem.scenes import load_scene

    toml = Path(__file__).resolve().parents[1] / "examples" / "scenes" / "cantilever.toml"
    text = toml.read_text().replace('type = "backward_euler"', f'type = "{name}"')
    p = tmp_path / "s.toml"
    p.write_text(text)
    run = load_scene(p).build()
    assert isinstance(run.sim.integrator, cls)


@pytest.mark.parametrize("integrator", ["bdf2", "newmark"])
def test_reduced_identity_basis_matches_full_simulator(integrator):
    """The reduced simulator runs the same terms and Newton loop: with the identity basis and full
    cubature it reproduces the full-space run of the same integrator (with Rayleigh damping)."""
    from warpfem.reduced import ReducedSimulator, Subspace
    from warpfem.reduced.cubature import Cubature
    from warpfem.reduced.subspace import material_parameters

    mesh = wf.box_tet_mesh(size=(3.0, 1.0, 1.0), cells=(3, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e4, poisson_ratio=0.3, density=10.0),
                     gravity=(0, 0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2)))
    free = np.flatnonzero(~model.fixed.reshape(-1))
    U = np.zeros((3 * mesh.num_vertices, len(free)))
    U[free, np.arange(len(free))] = 1.0
    basis = wf.reduced.Basis(U=U, linear_frequencies=np.zeros(0), frequencies=np.zeros(0))
    sub = Subspace(basis, Cubature.full(mesh.num_tets), wf.reduced.mesh_hash(model), material_parameters(model))
    opts = dict(dt=0.05, damping_mass=0.3, damping_stiffness=0.01, tol=1e-11, integrator=integrator)
    rs = ReducedSimulator(model, sub, **opts)
    fs = wf.Simulator(model, cg_tol=1e-12, **opts)
    for _ in range(4):
        rs.step()
        fs.step()
    moved = np.abs(fs.positions() - model.rest_positions).max()
    assert moved > 0.05
    assert np.abs(rs.positions() - fs.positions()).max() <= 1e-8 * moved
    assert np.abs(rs.velocities() - fs.velocities()).max() <= 1e-7 * np.abs(fs.velocities()).max()


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_stiffness_warping_identity_is_one_newton_iteration_of_the_same_scheme(integrator):
    """With R = I stiffness warping is linear FEM, so its one linear solve per step is the exact
    Newton step of the scheme's potential: it matches the Newton simulator with the linear
    material for every integrator (damping and a moving target included)."""
    mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=(4, 1, 1))
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=1e4, poisson_ratio=0.3, density=100.0),
                     gravity=(0, 0, -9.81))
    ids = wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2))
    model.fix(ids)
    kw = dict(dt=0.02, damping_mass=0.2, damping_stiffness=0.01, integrator=integrator)
    ws = wf.StiffnessWarpingSimulator(model, rotation="identity", cg_tol=1e-13, **kw)
    ns = wf.Simulator(model, tol=1e-12, cg_tol=1e-13, **kw)
    for k in range(6):
        target = mesh.vertices[ids] + [0.0, 0.0, 0.01 * k]
        ws.set_targets(ids, target)
        ns.set_targets(ids, target)
        ws.step()
        ns.step()
    moved = np.abs(ns.positions() - mesh.vertices).max()
    assert moved > 1e-2
    assert np.abs(ws.positions() - ns.positions()).max() <= 1e-9 * moved
    assert np.abs(ws.velocities() - ns.velocities()).max() <= 1e-8 * np.abs(ns.velocities()).max()


@pytest.mark.parametrize("integrator", ["bdf2", "newmark"])
def test_float32_and_float64_agree(integrator):
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(3, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2)))
    runs = {}
    for precision in ("float32", "float64"):
        sim = wf.Simulator(model, precision=precision, dt=1 / 60, integrator=integrator,
                           tol=1e-5 if precision == "float32" else 1e-9, cg_tol=1e-6)
        for _ in range(8):
            sim.step()
        runs[precision] = sim.positions() - mesh.vertices
    u = np.abs(runs["float64"]).max()
    assert u > 1e-2
    assert np.abs(runs["float32"] - runs["float64"]).max() < 1e-4 * u


def test_static_scene_load_ramp_does_not_rescale_the_model(tmp_path):
    """Static frames ramp the loads through the solver's load_scale control, not the model."""
    from warpfem.scenes import load_scene

    toml = Path(__file__).resolve().parents[1] / "examples" / "scenes" / "cantilever.toml"
    text = toml.read_text().replace('type = "backward_euler"', 'type = "static"')
    text = text.replace("dt = 0.020833333333333332       # 1/48 s: one step per frame\n", "")
    p = tmp_path / "s.toml"
    p.write_text(text)
    run = load_scene(p).build()
    g0, f0 = run.model.gravity.copy(), run.model.forces.copy()
    tip = np.flatnonzero(run.model.rest_positions[:, 0] > 1 - 1e-9)
    sags = []
    for _ in range(2):
        run.step_frame(total_frames=4)
        sags.append(run.sim.positions()[tip, 1].mean() - run.model.rest_positions[tip, 1].mean())
        np.testing.assert_array_equal(run.model.gravity, g0)
        np.testing.assert_array_equal(run.model.forces, f0)
    assert run.sim.load_scale == 0.5
    # small deflection: the sag at half load is about twice the sag at a quarter
    assert sags[1] / sags[0] == pytest.approx(2.0, rel=0.05)
