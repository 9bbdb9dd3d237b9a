"""Recorded steps keep the direct solver's factorisation for their reverse pass (``factor_budget``,
docs/gradients.md "Cost"): the reverse pass then prepares the solver on no step, gives the same
gradients as refactorising every step (``factor_budget=0``), falls back to refactorising beyond
the budget, and frees the factorisations on ``release()``. Every backend (PARDISO's factor slots,
SuperLU and QDLDL objects)."""

from __future__ import annotations

import numpy as np
import pytest

import warpfem as wf
from warpfem.solvers.adjoint import Recording
from warpfem.solvers.linear.direct import available_backends

STEPS = 10
MESH = wf.box_tet_mesh(size=(0.2, 0.1, 0.1), cells=(2, 1, 1))
FIXED = wf.select_vertices_in_box(MESH, (-1, -1, -1), (1e-9, 1, 1))
W = np.random.default_rng(3).standard_normal((STEPS + 1, MESH.num_vertices, 3))


def record(backend, budget, integrator="bdf2"):
    model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, 0.0, -9.81))
    model.fix(FIXED)
    sim = wf.Simulator(model, dt=0.01, integrator=integrator, linear_solver="direct",
                       linear_solver_options={"backend": backend}, tol=1e-12, max_iters=50)
    rec = Recording(sim, factor_budget=budget)
    with rec:
        for _ in range(STEPS):
            assert sim.step().converged
    return sim, rec


@pytest.mark.parametrize("backend", [b for b in ("pardiso", "superlu", "qdldl") if b in available_backends()])
def test_kept_factorisations_give_the_same_gradients_without_refactorising(backend):
    xg = {k: W[k] for k in range(STEPS + 1)}
    sim0, rec0 = record(backend, 0)
    ref = rec0.backward(xg)
    assert all(r.factor is None for r in rec0.records)
    # refinement on the last factorisation, refactorising when it contracts slowly
    assert rec0.adjoint.kept_solves == 0 and rec0.adjoint.prepares >= 1

    sim, rec = record(backend, None)  # the default budget (1 GiB) holds them all
    kept = [r.factor is not None for r in rec.records]
    assert all(kept), kept
    assert rec.factor_nbytes > 0 and sim.linear_solver.kept_bytes == rec.factor_nbytes
    g = rec.backward(xg)
    assert rec.adjoint.prepares == 0 and rec.adjoint.kept_solves == STEPS
    for name in ("youngs_modulus", "poisson_ratio", "density", "initial_positions", "initial_velocities"):
        a, b = np.asarray(g[name]), np.asarray(ref[name])
        assert np.allclose(a, b, rtol=1e-9, atol=1e-12 * np.max(np.abs(b))), name
    # a second reverse pass (another loss) reuses them again
    g2 = rec.backward({k: 2.0 * W[k] for k in range(STEPS + 1)})
    assert rec.adjoint.prepares == 0
    assert np.isclose(g2["youngs_modulus"], 2.0 * g["youngs_modulus"], rtol=1e-9)
    rec.release()
    assert sim.linear_solver.kept_bytes == 0 and rec.factor_nbytes == 0
    # after release the reverse pass refactorises, with the same result
    g3 = rec.backward(xg)
    assert rec.adjoint.prepares > 0
    assert np.isclose(g3["youngs_modulus"], ref["youngs_modulus"], rtol=1e-9)
    # the forward steps after the hand-overs still solve (the solver factorises into new storage)
    assert sim.step().converged


def test_budget_keeps_as_many_as_fit_and_the_rest_refactorise():
    sim, full = record("superlu", None, integrator="backward_euler")
    one = full.records[0].factor.nbytes
    full.release()
    xg = {k: W[k] for k in range(STEPS + 1)}
    ref = full.backward(xg)
    sim, rec = record("superlu", int(3.5 * one), integrator="backward_euler")
    kept = sum(r.factor is not None for r in rec.records)
    assert kept == 3 and rec.factor_nbytes <= 3.5 * one
    g = rec.backward(xg)
    assert rec.adjoint.kept_solves == 3 and rec.adjoint.solves == STEPS  # 7 on the fallback (the solver's factorisation)
    assert np.isclose(g["youngs_modulus"], ref["youngs_modulus"], rtol=1e-9)
    assert np.allclose(g["initial_positions"], ref["initial_positions"], rtol=1e-9, atol=1e-12)
