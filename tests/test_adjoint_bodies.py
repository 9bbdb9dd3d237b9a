"""Gradients of a model of several bodies (``Model.from_bodies``) against central finite
differences, float64, over 10 steps: a Tet4 beam and a Hex8 beam of different materials side by
side (each clamped at x = 0, under gravity); Young's modulus, Poisson ratio and density of each
body (one gradient per body), per-element stiffness (numbered body after body), initial positions.
And frictionless surface contact between two bodies (the pairs' exact Hessian in H).
"""

from __future__ import annotations

import numpy as np
import pytest

import warpfem as wf
from tiny_scenes import beam_on_block_model
from gradient_checks import assert_central_differences
from warpfem.solvers.adjoint import Recording, set_element_stiffness_scale

STEPS = 10
TET = wf.box_tet_mesh(size=(0.2, 0.05, 0.05), cells=(2, 1, 1))
HEX = wf.box_hex_mesh(size=(0.2, 0.05, 0.05), cells=(2, 1, 1))
OFFSET = (0.0, 0.2, 0.0)
N = TET.num_vertices + HEX.num_vertices
M = TET.num_elements + HEX.num_elements
RNG = np.random.default_rng(11)
W = RNG.standard_normal((STEPS + 1, N, 3))
BASE = {"E": np.array([1e5, 3e5]), "nu": np.array([0.3, 0.2]), "rho": np.array([1000.0, 600.0]),
        "scale": np.ones(M), "x0": None}


def run(integrator, p, grads=False):
    bodies = [wf.Body(TET, wf.StableNeoHookean(youngs_modulus=p["E"][0], poisson_ratio=p["nu"][0], density=p["rho"][0]),
                      name="tet"),
              wf.Body(HEX, wf.Corotated(youngs_modulus=p["E"][1], poisson_ratio=p["nu"][1], density=p["rho"][1]),
                      name="hex", offset=OFFSET)]
    model = wf.Model.from_bodies(bodies, gravity=(0.0, 0.0, -9.81))
    model.fix(np.flatnonzero(model.rest_positions[:, 0] < 1e-9))
    sim = wf.Simulator(model, dt=0.01, integrator=integrator, damping_mass=0.5, linear_solver="direct",
                       linear_solver_options={"backend": "superlu"}, tol=1e-13, max_iters=50)
    set_element_stiffness_scale(sim, p["scale"])
    if p["x0"] is not None:
        sim.set_positions(p["x0"])
    xs = [sim.positions()]
    rec = Recording(sim)
    with rec:
        for _ in range(STEPS):
            assert sim.step().converged
            xs.append(sim.positions())
    loss = float(sum(np.sum(w * x) for w, x in zip(W, xs)))
    if not grads:
        return loss, xs[0]
    return loss, rec.backward({k: W[k] for k in range(STEPS + 1)})


@pytest.mark.parametrize("integrator", ["backward_euler", "newmark"])
def test_several_bodies_gradients_match_central_differences(integrator):
    _, g = run(integrator, BASE, grads=True)
    assert np.shape(g["youngs_modulus"]) == (2,) and np.shape(g["density"]) == (2,)
    x_rest = run(integrator, BASE)[1]
    dx = RNG.standard_normal((N, 3))
    dc = RNG.standard_normal(M)
    cases = []  # (what, key, direction, step, analytic)
    for b in range(2):
        for key, name, h in (("E", "youngs_modulus", 10.0 * (b + 1)), ("nu", "poisson_ratio", 1e-4),
                             ("rho", "density", 1e-1)):
            d = np.zeros(2)
            d[b] = 1.0
            cases.append((f"{name}[{b}]", key, d, h, float(g[name][b])))
    cases.append(("element_stiffness_scale", "scale", dc, 1e-4, float(np.sum(g["element_stiffness_scale"] * dc))))
    cases.append(("initial_positions", "x0", dx, 1e-6, float(np.sum(g["initial_positions"] * dx))))
    errors = {}
    for what, key, d, h, an in cases:
        base = x_rest if key == "x0" else BASE[key]
        plus, minus = dict(BASE), dict(BASE)
        plus[key], minus[key] = base + h * d, base - h * d
        fd = (run(integrator, plus)[0] - run(integrator, minus)[0]) / (2 * h)
        errors[what] = abs(an - fd) / abs(fd)
    print(integrator, {k: f"{e:.1e}" for k, e in errors.items()})
    assert max(errors.values()) <= 1e-5, errors


def test_surface_contact_with_a_default_or_adaptive_stiffness_is_refused_with_a_reason():
    bodies = [wf.Body(TET, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0), name="tet"),
              wf.Body(HEX, wf.Corotated(youngs_modulus=3e5, poisson_ratio=0.2, density=600.0), name="hex",
                      offset=OFFSET)]
    sim = wf.Simulator(wf.Model.from_bodies(bodies), dt=0.01, linear_solver="direct")
    sim.set_contact(bodies=True)
    with pytest.raises(NotImplementedError, match="surface contact: give set_contact a stiffness"):
        Recording(sim)
    sim.set_contact(bodies=True, stiffness="auto", friction=0.3)
    with pytest.raises(NotImplementedError, match="adaptive stiffness"):
        Recording(sim)
    sim.set_contact(bodies=True, stiffness=1e5, friction=0.3)
    Recording(sim)  # friction is differentiable (tests/test_adjoint_surface_friction.py)


def _stacked(E=1e5, dv=None, dforce=None, grads=False):
    """A Tet4 beam pushed (0.5 N per vertex, gravity) onto a clamped Hex8 block 9 mm below it,
    frictionless surface contact (kappa 1e5 N/m^3, dhat 1 cm): point-triangle and edge-edge pairs
    within dhat in every step (asserted)."""
    model = beam_on_block_model(E, dforce)
    n0 = int(model.body_offsets[1])
    sim = wf.Simulator(model, dt=0.01, integrator="backward_euler", linear_solver="direct",
                       linear_solver_options={"backend": "superlu"}, tol=1e-12, max_iters=300)
    sc = sim.set_contact(bodies=True, dhat=0.01, stiffness=1e5)
    v = np.zeros((sim.num_vertices, 3))
    v[:n0] = (0.1, 0.0, -0.3)
    sim.set_velocities(v if dv is None else v + dv)
    xs, near = [sim.positions()], []
    rec = Recording(sim)
    with rec if grads else _Null():
        for _ in range(STEPS):
            assert sim.step().converged
            xs.append(sim.positions())
            near.append(int(np.sum(sc.distances() < 0.01)))
    w = np.random.default_rng(2).standard_normal((STEPS + 1, sim.num_vertices, 3))
    loss = float(sum(np.sum(a * x) for a, x in zip(w, xs)))
    if not grads:
        return loss
    assert min(near) >= 10, near  # pairs within dhat in every step
    return loss, rec.backward({k: w[k] for k in range(STEPS + 1)}), sim.num_vertices


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        pass


def test_frictionless_surface_contact_gradients_match_central_differences():
    _, g, n = _stacked(grads=True)
    D = np.random.default_rng(4).standard_normal((n, 3))
    checks = {"youngs_modulus[top]": (float(g["youngs_modulus"][0]), lambda h: _stacked(E=1e5 + h), 10.0),
              "initial_velocities": (float(np.sum(g["initial_velocities"] * D)), lambda h: _stacked(dv=h * D), 1e-6),
              "forces": (float(np.sum(g["forces"] * D)), lambda h: _stacked(dforce=h * D), 1e-4)}
    assert_central_differences(checks)
