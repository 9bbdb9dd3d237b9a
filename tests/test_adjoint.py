"""Adjoint gradients of implicit steps (warpfem.solvers.adjoint, docs/gradients.md) against central
finite differences, float64, every integrator, every parameter kind, over 10 steps.

A 2x1x1-cell tet box (12 vertices, 12 tets), clamped at x = 0 with one clamped vertex driven by a
kinematic target, under gravity, mass damping and applied forces. The loss is a fixed random
linear functional of the positions of every state (so its derivative is the trajectory's own).
Newton solves run to a relative gradient of 1e-13 with the direct solver, so the forward error is
far below the finite-difference step's effect; the central difference's own error (h^2) is below
1e-8 relative at these steps.
"""

from __future__ import annotations

import numpy as np
import pytest

import warpfem as wf
from warpfem.solvers.adjoint import Recording, set_element_stiffness_scale

STEPS = 10
MESH = wf.box_tet_mesh(size=(0.2, 0.1, 0.1), cells=(2, 1, 1))
N = MESH.num_vertices
FIXED = wf.select_vertices_in_box(MESH, (-1, -1, -1), (1e-9, 1, 1))
DRIVEN = int(FIXED[0])
RNG = np.random.default_rng(7)
WEIGHTS = RNG.standard_normal((STEPS + 1, N, 3))
TARGETS = np.array([MESH.vertices[DRIVEN] + [0.0, 0.0, -0.002 * (k + 1)] for k in range(STEPS)])
BASE = dict(E=1e5, nu=0.3, rho=1000.0, scale=np.ones(MESH.num_elements), x0=MESH.vertices.copy(),
            v0=np.zeros((N, 3)), forces=np.zeros((N, 3)), targets=TARGETS)
SOLVER = dict(linear_solver="direct", linear_solver_options={"backend": "superlu"}, tol=1e-13, max_iters=50)


def run(integrator, p, grads=False):
    mat = wf.StableNeoHookean(youngs_modulus=p["E"], poisson_ratio=p["nu"], density=p["rho"])
    model = wf.Model(MESH, mat, gravity=(0.0, 0.0, -9.81))
    model.fix(FIXED)
    model.forces[:] = p["forces"]
    sim = wf.Simulator(model, dt=0.01, integrator=integrator, damping_mass=0.5, **SOLVER)
    set_element_stiffness_scale(sim, p["scale"])
    sim.set_positions(p["x0"])
    sim.set_velocities(p["v0"])
    xs = [sim.positions()]
    rec = Recording(sim)
    with rec if grads else _null():
        for k in range(STEPS):
            sim.set_targets([DRIVEN], p["targets"][k][None])
            assert sim.step().converged
            xs.append(sim.positions())
    loss = float(sum(np.sum(w * x) for w, x in zip(WEIGHTS, xs)))
    if not grads:
        return loss
    return loss, rec.backward({k: WEIGHTS[k] for k in range(STEPS + 1)})


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        pass


# parameter kind -> (key in BASE, gradient name, direction (None: scalar), finite-difference step)
KINDS = {
    "youngs_modulus": ("E", "youngs_modulus", None, 1e1),
    "poisson_ratio": ("nu", "poisson_ratio", None, 1e-4),
    "density": ("rho", "density", None, 1e-1),
    "element_stiffness_scale": ("scale", "element_stiffness_scale", RNG.standard_normal(MESH.num_elements), 1e-4),
    "initial_positions": ("x0", "initial_positions", RNG.standard_normal((N, 3)), 1e-6),
    "initial_velocities": ("v0", "initial_velocities", RNG.standard_normal((N, 3)), 1e-5),
    "forces": ("forces", "forces", RNG.standard_normal((N, 3)), 1e-3),
    "targets": ("targets", "targets", RNG.standard_normal((STEPS, 3)), 1e-6),
}


def directional(g, name, d):
    if d is None:
        return float(g[name])
    if name == "targets":
        return float(sum(np.dot(g["targets"][k][DRIVEN], d[k]) for k in range(STEPS)))
    return float(np.sum(g[name] * d))


@pytest.mark.parametrize("integrator", ["backward_euler", "bdf2", "newmark"])
def test_gradients_match_central_differences(integrator):
    _, g = run(integrator, BASE, grads=True)
    errors = {}
    for kind, (key, name, d, h) in KINDS.items():
        plus, minus = dict(BASE), dict(BASE)
        plus[key] = BASE[key] + h * (1.0 if d is None else d)
        minus[key] = BASE[key] - h * (1.0 if d is None else d)
        fd = (run(integrator, plus) - run(integrator, minus)) / (2 * h)
        an = directional(g, name, d)
        errors[kind] = abs(an - fd) / abs(fd)
    print(integrator, {k: f"{e:.1e}" for k, e in errors.items()})
    assert max(errors.values()) <= 1e-5, errors
