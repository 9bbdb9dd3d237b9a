"""Saving and loading a simulator's full step state (``state_dict`` / ``load_state_dict``,
``warpfem.save_state`` / ``warpfem.load_state``): N steps in one go against k steps, a checkpoint,
a NEW simulator of the same scene loaded from it and N - k more steps, compared bit for bit; and
the errors of states that do not fit."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest

import warpfem as wf
from tiny_scenes import beam_on_block_model, reduced_beam_model
from warpfem.io.checkpoint import CheckpointError, read_state


def _steps(sim, n):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(n):
            sim.step()


def _arrays(sim):
    return sim.positions(), sim.velocities(), sim.time


def _resumed(build, n, k, tmp_path, name="state.npz", fingerprint=None):
    """(uninterrupted end, resumed end, the second simulator): ``build()`` makes the simulator."""
    a = build()
    _steps(a, n)
    end = _arrays(a)
    b = build()
    _steps(b, k)
    path = os.path.join(tmp_path, name)
    wf.save_state(b, path, fingerprint=fingerprint)
    del b
    c = build()
    wf.load_state(c, path)
    _steps(c, n - k)
    return end, _arrays(c), c


def _assert_same(end, resumed):
    (xa, va, ta), (xb, vb, tb) = end, resumed
    assert ta == tb
    assert np.array_equal(xa, xb), np.abs(xa - xb).max()
    assert np.array_equal(va, vb), np.abs(va - vb).max()


def _beam(integrator, precision="float64", linear_solver="direct", **kw):
    def build():
        model = reduced_beam_model()
        return wf.Simulator(model, dt=1 / 30, damping_mass=1.0, integrator=integrator, precision=precision,
                            linear_solver=linear_solver, tol=1e-8, **kw)
    return build


@pytest.mark.parametrize("integrator, guess, solver", [("bdf2", "extrapolated", "direct"), ("newmark", "previous", "pcg")])
def test_free_beam_continues_bit_identically(tmp_path, integrator, guess, solver):
    end, resumed, c = _resumed(_beam(integrator, initial_guess=guess, linear_solver=solver), 6, 3, tmp_path)
    _assert_same(end, resumed)
    assert c.step_count == 6
    keys = set(c.state_dict())
    assert {"integrator/x_prev", "integrator/v_prev"} <= keys if integrator == "bdf2" else "integrator/a" in keys
    if guess == "extrapolated":
        assert "integrator/guess_v_prev" in keys


def test_float32_and_auto_solver_continue_bit_identically(tmp_path):
    end, resumed, c = _resumed(_beam("bdf2", precision="float32", linear_solver="auto"), 5, 2, tmp_path)
    _assert_same(end, resumed)
    d = c.state_dict()
    assert d["x"].dtype == np.float32 and d["linear_solver/active"] == c.linear_solver.active


def test_auto_solver_reuses_the_recorded_choice(tmp_path):
    """A recorded choice of ``auto`` (here: PCG after a measurement) is restored, not measured again."""
    build = _beam("backward_euler", linear_solver="auto")
    a = build()
    _steps(a, 1)
    a.linear_solver.active, a.linear_solver.explorations, a.linear_solver._chosen_cost = "pcg", 1, 0.5
    a.linear_solver._make("pcg")
    path = os.path.join(tmp_path, "auto.npz")
    wf.save_state(a, path)
    b = build()
    assert b.linear_solver.active == "direct"  # the small-system rule of a fresh run
    wf.load_state(b, path)
    s = b.linear_solver
    assert (s.active, s.explorations, s._chosen_cost) == ("pcg", 1, 0.5)
    _steps(a, 2)
    _steps(b, 2)
    _assert_same(_arrays(a), _arrays(b))


def _multigrid_beam(solver="multigrid", precision="float64", **options):
    def build():
        mesh = wf.box_tet_mesh(size=(8.0, 1.0, 1.0), cells=(16, 2, 2))
        model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e6, poisson_ratio=0.3, density=100.0),
                         gravity=(0.0, 0.0, -9.81))
        model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2)))
        return wf.Simulator(model, dt=1 / 30, integrator="newmark", linear_solver=solver, tol=1e-8 if precision == "float64"
                            else 1e-5, precision=precision,
                            linear_solver_options=dict(options, max_coarse=60) if solver == "amg" else options)
    return build


@pytest.mark.parametrize("solver, precision, options", [("multigrid", "float64", {}), ("amg", "float64", {}),
                                                        ("multigrid", "float32", {}),
                                                        ("multigrid", "float64", {"coarse_update": "every"})])
def test_multigrid_hierarchy_continues_bit_identically(tmp_path, solver, precision, options):
    """The multigrid (and the host AMG) keeps its hierarchy (and its coarse operators) over many Newton systems: a
    resumed run rebuilds the same one from the saved matrices, so it preconditions, and steps,
    exactly as the uninterrupted run (a hierarchy built afresh from the resume's first system
    changes the CG iterates, and the positions, in the last bits)."""
    pytest.importorskip("pyamg")
    end, resumed, c = _resumed(_multigrid_beam(solver, precision, **options), 6, 3, tmp_path)
    _assert_same(end, resumed)
    # loaded again into the simulator that has stepped past it (and rebuilt its hierarchy since):
    # the same steps again, not steps preconditioned by the later hierarchy
    wf.load_state(c, os.path.join(tmp_path, "state.npz"))
    _steps(c, 3)
    _assert_same(end, _arrays(c))
    mg = c.linear_solver
    assert (len(mg.levels) if solver == "multigrid" else len(mg.ml.levels)) >= 2 and c.state_dict()["linear_solver/built"]


def _incline(precision="float64"):
    def build():
        box = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1), origin=(-0.05, 0.001, -0.05))
        model = wf.Model(box, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                         gravity=(0.0, -9.81, 0.0))
        sim = wf.Simulator(model, dt=0.01, precision=precision, linear_solver="direct",
                           colliders=[wf.Plane(point=(0, -0.015, 0), normal=(0.2, 1.0, 0.0), friction=0.5, stiffness="auto",
                                               name="floor")])
        sim.set_velocities(np.tile([0.3, -0.2, 0.0], (model.num_vertices, 1)))
        return sim
    return build


def test_contact_with_friction_and_adaptive_stiffness_continues_bit_identically(tmp_path):
    end, resumed, c = _resumed(_incline(), 8, 4, tmp_path)
    _assert_same(end, resumed)
    d = c.state_dict()
    assert np.max(d["form/contact/lag_normal_force"]) > 0.0  # friction lagged from a real contact
    assert np.isfinite(d["form/contact/stiffness/0/kappa"])


def test_extra_evaluations_leave_the_steps_bit_identical(monkeypatch):
    """Energy and gradient evaluations added inside the Newton loop (at the iterate, and at the full
    step along each Newton direction, into vectors of their own), as a measurement would make
    them, change nothing: frictional contact with adaptive stiffness steps to the same bits with
    the same Newton iterations."""
    import warpfem.simulator as S

    def run(extra):
        sim = _incline()()
        orig = S.newton_solve

        def solve(pot, y, opts, *a, **kw):
            if extra:
                hook, system = pot.after_iteration, pot.solve_newton_system

                def after(yy, alpha=1.0, residual=0.0):
                    pot.energy(yy)
                    pot.gradient(yy, pot.new_vector())
                    return hook(yy, alpha, residual=residual)

                def solve_system(yy, g, d, o):
                    lin = system(yy, g, d, o)
                    v = pot.new_vector()
                    pot.trial(yy, 1.0, d, v)
                    pot.evaluate(v, pot.new_vector())
                    return lin

                pot.after_iteration, pot.solve_newton_system = after, solve_system  # (instance attributes)
            try:
                return orig(pot, y, opts, *a, **kw)
            finally:
                pot.__dict__.pop("after_iteration", None)
                pot.__dict__.pop("solve_newton_system", None)

        monkeypatch.setattr(S, "newton_solve", solve)
        counts = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for _ in range(8):
                counts.append(sim.step().newton_iterations)
        monkeypatch.setattr(S, "newton_solve", orig)
        return counts, _arrays(sim)

    (c0, a0), (c1, a1) = run(False), run(True)
    assert sum(c0) > 8 and c0 == c1  # contact steps that iterate
    _assert_same(a0, a1)


def _blocks(friction=0.3):
    def build():
        model = beam_on_block_model()
        sim = wf.Simulator(model, dt=0.01, linear_solver="direct", tol=1e-10, max_iters=100)
        sim.set_contact(bodies=True, dhat=0.01, stiffness="auto", friction=friction)
        v = np.zeros((model.num_vertices, 3))
        v[:wf.box_tet_mesh(size=(0.2, 0.05, 0.05), cells=(2, 1, 1)).num_vertices] = (0.3, 0.0, -0.5)
        sim.set_velocities(v)
        return sim
    return build


def test_surface_contact_of_two_bodies_continues_bit_identically(tmp_path):
    end, resumed, c = _resumed(_blocks(), 6, 3, tmp_path)
    _assert_same(end, resumed)
    d = c.state_dict()
    assert len(d["form/surface_contact/pairs"]) > 0 and len(d["pattern/extra_pairs"]) > 0


@pytest.fixture(scope="module")
def subspace():
    from warpfem.reduced import Cubature, train_subspace

    model = reduced_beam_model()
    sub = train_subspace(model, modes=6, modal_derivatives=True, load_response=True, cubature_tolerance=0.5,
                         num_training_poses=4, num_validation_poses=2)
    sub.cubature = Cubature.full(model.quadrature.num_elements)
    return sub


@pytest.mark.parametrize("integrator", ["backward_euler", "newmark"])
def test_reduced_continues_bit_identically(tmp_path, subspace, integrator):
    from warpfem.reduced import ReducedSimulator

    def build():
        return ReducedSimulator(reduced_beam_model(), subspace, dt=1 / 30, damping_mass=1.0, tol=1e-11,
                                integrator=integrator)

    end, resumed, c = _resumed(build, 8, 4, tmp_path)
    _assert_same(end, resumed)
    assert c.state_dict()["reduced/has_newton_matrix"]


# -- bad input ---------------------------------------------------------------------------------------
def test_state_that_does_not_fit_is_refused_with_the_key_and_leaves_the_simulator_as_it_was(tmp_path):
    build = _beam("bdf2")
    a = build()
    _steps(a, 2)
    d = a.state_dict()
    b = build()
    _steps(b, 1)
    before = b.state_dict()

    def refused(state, match):
        with pytest.raises(CheckpointError, match=match):
            b.load_state_dict(state)
        after = b.state_dict()
        assert after.keys() == before.keys()
        assert all(np.array_equal(after[k], before[k]) for k in before)

    refused({**d, "x": d["x"][:-1]}, r"state key 'x': shape \(35, 3\), this simulator needs \(36, 3\)")
    refused({**d, "integrator/x_prev": d["integrator/x_prev"].astype(np.float32)},
            r"'integrator/x_prev': dtype float32, this simulator needs float64")
    refused({**d, "meta/precision": "float32"}, r"'meta/precision': saved from a simulator of precision 'float32'")
    refused({k: v for k, v in d.items() if k != "v"}, r"state key 'v' is missing")
    refused({**d, "form/contact/colliders": np.array(["floor"])}, r"not part of this simulator")
    bad = dict(d)
    bad["x"] = d["x"].copy()
    bad["x"][0, 0] = np.nan
    refused(bad, r"'x': holds NaN")
    # a float32 simulator refuses a float64 state
    c = _beam("bdf2", precision="float32")()
    with pytest.raises(CheckpointError, match="precision"):
        c.load_state_dict(d)


def test_checkpoint_file_fingerprint_and_missing_file(tmp_path):
    build = _beam("backward_euler")
    a = build()
    _steps(a, 1)
    path = os.path.join(tmp_path, "run.npz")
    fp = {"dt": 1 / 30, "mesh": {"cells": [8, 1, 1]}, "material": "stable_neo_hookean"}
    wf.save_state(a, path, fingerprint=fp)
    assert [f for f in os.listdir(tmp_path)] == ["run.npz"]  # no temporary file left
    state, stored = read_state(path)
    assert stored == fp and state["step_count"] == 1
    b = build()
    assert wf.load_state(b, path, expect_fingerprint=dict(fp)) == fp
    with pytest.raises(CheckpointError, match=r"scene changed since the checkpoint: dt \(saved 0.0333.*, now 0.05\); "
                                              r"mesh \(saved"):
        wf.load_state(b, path, expect_fingerprint={**fp, "dt": 0.05, "mesh": {"cells": [4, 1, 1]}})
    with pytest.raises(FileNotFoundError, match="no checkpoint file"):
        wf.load_state(b, os.path.join(tmp_path, "nothing.npz"))
    with open(os.path.join(tmp_path, "junk.npz"), "wb") as f:
        f.write(b"not a zip")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        wf.load_state(b, os.path.join(tmp_path, "junk.npz"))
