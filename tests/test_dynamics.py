"""Backward Euler dynamics: energy behaviour, modal decay, precision agreement, Dirichlet changes,
failed steps (shared/reference section 5)."""

import numpy as np
import pytest
import scipy.linalg

import warpfem as wf


def _beam(cells=(4, 1, 1), size=(2.0, 0.5, 0.5), material="linear", E=1e4, nu=0.3, rho=100.0):
    mesh = wf.box_tet_mesh(size=size, cells=cells)
    return mesh, wf.make_material(material, youngs_modulus=E, poisson_ratio=nu, density=rho)


TIGHT = dict(tol=1e-11, cg_tol=1e-12, max_iters=10)


@pytest.mark.parametrize("mass_matrix", ["lumped", "consistent"])
def test_single_mode_energy_decays_by_backward_euler_factor(mass_matrix):
    mesh, mat = _beam()
    model = wf.Model(mesh, mat, mass_matrix=mass_matrix)
    h = 0.01
    sim = wf.Simulator(model, dt=h, **TIGHT)
    K = sim.stiffness_matrix().toarray()
    M = sim.mass_matrix().toarray()
    w2, U = scipy.linalg.eigh(K, M)
    mode = 8  # first 6 are rigid (free-floating body)
    assert w2[5] < 1e-8 * w2[-1] and w2[mode] > 1e-3 * w2[-1]
    amp = 1e-3
    sim.set_positions(mesh.vertices + amp * U[:, mode].reshape(-1, 3))
    E0 = sim.total_energy()
    assert E0 == pytest.approx(0.5 * w2[mode] * amp**2, rel=1e-9)
    factor = 1.0 / (1.0 + w2[mode] * h * h)
    for _ in range(3):
        sim.step()
        E1 = sim.total_energy()
        assert E1 / E0 == pytest.approx(factor, rel=1e-7)
        E0 = E1


@pytest.mark.parametrize("damping", [0.0, 0.5])
def test_total_energy_never_increases_without_external_force(damping, rng):
    mesh, mat = _beam(cells=(4, 2, 2))
    model = wf.Model(mesh, mat)
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 1, 1)))
    sim = wf.Simulator(model, dt=1 / 60, damping_mass=damping, tol=1e-10, cg_tol=1e-10)
    x0 = mesh.vertices.copy()
    free = ~model.fixed.any(axis=1)
    x0[free] += 0.05 * rng.standard_normal((free.sum(), 3))
    sim.set_positions(x0)
    energies = [sim.total_energy()]
    for _ in range(15):
        assert sim.step().converged
        energies.append(sim.total_energy())
    e = np.array(energies)
    assert np.all(np.diff(e) <= 1e-10 * e[0])
    assert e[-1] < 0.9 * e[0]  # it does dissipate (numerical + optional Rayleigh damping)


def test_rayleigh_damping_dissipates_more():
    final = {}
    for alpha in (0.0, 2.0):
        mesh, mat = _beam(cells=(4, 1, 1))
        model = wf.Model(mesh, mat)
        model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 1, 1)))
        sim = wf.Simulator(model, dt=1 / 60, damping_mass=alpha, damping_stiffness=0.01 * alpha, tol=1e-10, cg_tol=1e-10)
        sim.set_velocities(np.tile([0.0, 0.0, 1.0], (mesh.num_vertices, 1)) * (~model.fixed))
        for _ in range(10):
            sim.step()
        final[alpha] = sim.total_energy()
    assert final[2.0] < 0.75 * final[0.0]


def _hanging_run(precision, steps=10, material="stable_neo_hookean"):
    mesh, mat = _beam(cells=(6, 2, 2), material=material, E=2e4, rho=100.0)
    model = wf.Model(mesh, mat, gravity=(0, 0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 1, 1)))
    sim = wf.Simulator(model, precision=precision, dt=1 / 60, tol=1e-5 if precision == "float32" else 1e-9, cg_tol=1e-6)
    for _ in range(steps):
        st = sim.step()
        assert st.converged, st.reason
    return sim.positions() - mesh.vertices


def test_float32_and_float64_agree_on_a_short_run():
    u64 = _hanging_run("float64")
    u32 = _hanging_run("float32")
    scale = np.abs(u64).max()
    assert scale > 1e-2  # the beam really sags
    assert np.abs(u32 - u64).max() < 1e-3 * scale


def test_fix_and_release_between_steps_match_a_run_built_with_the_final_set():
    mesh, mat = _beam(cells=(4, 1, 1), material="corotated", E=1e4)
    left = wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 1, 1))
    right = wf.select_vertices_in_box(mesh, (2, -1, -1), (3, 1, 1))

    def run(release_mid_run):
        model = wf.Model(mesh, mat, gravity=(0, 0, -9.81))
        model.fix(left)
        if release_mid_run:
            model.fix(right)
        sim = wf.Simulator(model, dt=1 / 60, tol=1e-10, cg_tol=1e-10)
        pattern_id = id(sim._pattern)
        if release_mid_run:
            sim.step()
            assert np.abs(sim.positions()[right] - mesh.vertices[right]).max() == 0.0  # held
            sim.release(right)
            sim.set_positions(mesh.vertices)
            sim.set_velocities(np.zeros_like(mesh.vertices))
        for _ in range(5):
            sim.step()
        assert id(sim._pattern) == pattern_id
        return sim.positions()

    np.testing.assert_allclose(run(True), run(False), atol=1e-9)


def test_fixed_components_only():
    """A sliding support: fixing only z keeps z and lets x, y move."""
    mesh, mat = _beam(cells=(4, 1, 1))
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, -9.81))
    ids = wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 1, 1))
    model.fix(ids, "z")
    model.fix(wf.select_vertices_in_box(mesh, (2, -1, -1), (3, 1, 1)), "xyz")
    sim = wf.Simulator(model, dt=1 / 60)
    for _ in range(3):
        sim.step()
    u = sim.positions() - mesh.vertices
    assert np.abs(u[ids, 2]).max() == 0.0
    assert np.abs(u[ids, 1]).max() > 1e-4


def test_failed_step_leaves_state_untouched():
    mesh, mat = _beam(cells=(4, 1, 1), material="stable_neo_hookean")
    model = wf.Model(mesh, mat, gravity=(0, 0, -9.81))
    sim = wf.Simulator(model, dt=1 / 60, max_iters=1, tol=1e-12, require_convergence=True)
    sim.set_velocities(np.random.default_rng(0).standard_normal((mesh.num_vertices, 3)))
    x0, v0 = sim.positions(), sim.velocities()
    with pytest.raises(wf.SolveFailed, match="did not converge") as info:
        sim.step()
    assert info.value.stats.newton_iterations == 1 and not info.value.stats.converged
    np.testing.assert_array_equal(sim.positions(), x0)
    np.testing.assert_array_equal(sim.velocities(), v0)
    assert sim.time == 0.0 and sim.step_count == 0
    # without require_convergence the same step is accepted, flagged and warned about
    sim.require_convergence = False
    with pytest.warns(RuntimeWarning, match="did not converge"):
        st = sim.step()
    assert not st.converged and "max_iters" in st.reason


def test_static_solve_needs_fixed_vertices_and_bad_options_are_rejected():
    mesh, mat = _beam()
    model = wf.Model(mesh, mat)
    with pytest.raises(ValueError, match="fixed components"):
        wf.Simulator(model).solve_static()
    with pytest.raises(ValueError, match="dt"):
        wf.Simulator(model, dt=0.0)
    with pytest.raises(ValueError, match="precision"):
        wf.Simulator(model, precision="float16")
    with pytest.raises(TypeError, match="unknown solver option"):
        wf.Simulator(model, newton_tolerance=1e-3)
    with pytest.raises(ValueError, match="cg_tol"):
        wf.Simulator(model, cg_tol=2.0)
    with pytest.raises(IndexError, match="out of range"):
        model.fix([mesh.num_vertices + 3])
    with pytest.raises(ValueError, match="components"):
        model.fix([0], "w")
    with pytest.raises(ValueError, match="positions"):
        wf.Simulator(model).set_positions(np.full((mesh.num_vertices, 3), np.nan))
