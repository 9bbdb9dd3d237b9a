"""Gradients through surface contact with friction (``set_contact(friction=...)``) against central
finite differences, float64, over 10 steps: a Tet4 beam thrown sideways onto a Hex8 block whose
bottom is clamped, the two bodies' surfaces in frictional contact (kappa 1e5 N/m^3, dhat 1 cm,
mu 0.4). Young's modulus, v_0, x_0 (random directions) and mu; each term of the reverse pass
(the friction Hessian in H, the x_n-derivative of the lagged friction) is shown to matter. And the
host lag and friction Hessian of ``warpfem.solvers.adjoint_surface`` against the kernels'.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpfem as wf
from gradient_checks import assert_central_differences
from warpfem.contact import surface_kernels as SK
from warpfem.solvers import adjoint_surface as AS
from tiny_scenes import beam_on_block_model
from warpfem.solvers.adjoint import Recording

STEPS = 10
TOP = wf.box_tet_mesh(size=(0.2, 0.05, 0.05), cells=(2, 1, 1))
BASE = wf.box_hex_mesh(size=(0.3, 0.1, 0.05), cells=(2, 1, 1))
N = TOP.num_vertices + BASE.num_vertices
RNG = np.random.default_rng(5)
# a generic start: in the meshes' rest shape the pairs' closest points lie on region boundaries
# (a vertex right above a triangle's edge), where the lagged closest-point weights are only continuous
JITTER = 3e-4 * RNG.standard_normal((N, 3))
W = RNG.standard_normal((STEPS + 1, N, 3))
MU = 0.4


def _stepped(sim, sc, weights, record):
    """STEPS converged steps of ``sim`` (recorded when ``record``): (the loss sum_k weights_k . x_k,
    the recording, the lagged friction pairs of each step, the positions)."""
    xs, lagged = [sim.positions()], []
    rec = Recording(sim)
    if record:
        rec.__enter__()
    try:
        for _ in range(STEPS):
            assert sim.step().converged
            xs.append(sim.positions())
            lagged.append(sc.num_friction)
    finally:
        if record:
            rec.__exit__(None, None, None)
    return float(sum(np.sum(a * x) for a, x in zip(weights, xs))), rec, lagged, xs


def run(E=1e5, mu=MU, dv=None, dx=None, integrator="backward_euler", record=False):
    model = beam_on_block_model(E)
    n0 = TOP.num_vertices
    # friction_iterations=0: friction lagged once from the step start, as recorded steps do
    sim = wf.Simulator(model, dt=0.01, integrator=integrator, linear_solver="direct", friction_iterations=0,
                       linear_solver_options={"backend": "superlu"}, tol=1e-12, max_iters=300)
    sc = sim.set_contact(bodies=True, dhat=0.01, stiffness=1e5, friction=mu)
    sim.set_positions(sim.positions() + JITTER + (0.0 if dx is None else dx))
    v = np.zeros((N, 3))
    v[:n0] = (0.3, 0.1, -0.3)
    sim.set_velocities(v if dv is None else v + dv)
    return _stepped(sim, sc, W, record)


def _grads(rec):
    return rec.backward({k: W[k] for k in range(STEPS + 1)})


def test_surface_friction_gradients_match_central_differences(monkeypatch):
    _, rec, lagged, xs = run(record=True)
    assert sum(k > 0 for k in lagged) >= 8 and min(lagged) >= 1, lagged  # friction pairs in (nearly) every step
    # friction matters: the beam slides less far than without it
    _, _, _, xs0 = run(mu=0.0)
    slide, slide0 = (np.mean(x[:TOP.num_vertices, 0] - x_[:TOP.num_vertices, 0]) for x, x_ in
                     ((xs[-1], xs[0]), (xs0[-1], xs0[0])))
    assert slide < 0.5 * slide0, (slide, slide0)  # measured 0.23
    g = _grads(rec)
    D = np.random.default_rng(4).standard_normal((N, 3))
    checks = {"youngs_modulus[top]": (lambda g: float(g["youngs_modulus"][0]), lambda h: run(E=1e5 + h), 10.0),
              "initial_velocities": (lambda g: float(np.sum(g["initial_velocities"] * D)), lambda h: run(dv=h * D),
                                     1e-6),
              "initial_positions": (lambda g: float(np.sum(g["initial_positions"] * D)), lambda h: run(dx=h * D), 1e-7),
              "contact_friction": (lambda g: float(g["contact_friction"]), lambda h: run(mu=MU + h), 1e-5)}
    fd = {k: (f(h)[0] - f(-h)[0]) / (2 * h) for k, (_, f, h) in checks.items()}

    def errors(g):
        return {k: abs(get(g) - fd[k]) / abs(fd[k]) for k, (get, _, _) in checks.items()}

    err = errors(g)
    print({k: f"{e:.1e}" for k, e in err.items()})
    assert max(err.values()) <= 1e-5, err
    # the test sees each term: without the friction Hessian in H, without the x_n-derivative of
    # the lagged friction (normal forces, weights, normals, -x^n), and the frictionless gradient
    with monkeypatch.context() as m:
        m.setattr(AS.SurfaceFrictionTerms, "add_hessian", lambda self, K, pattern: None)
        no_h = errors(_grads(rec))
    with monkeypatch.context() as m:
        m.setattr(AS.SurfaceFrictionTerms, "xn_product", lambda self, lam: np.zeros_like(lam))
        no_xn = errors(_grads(rec))
    _, rec0, _, _ = run(mu=0.0, record=True)
    frictionless = errors(_grads(rec0))
    for what, e in (("no Hessian", no_h), ("no x_n term", no_xn), ("frictionless", frictionless)):
        print(what, {k: f"{v:.1e}" for k, v in e.items()})
    assert no_h["initial_velocities"] > 1e-2 and no_h["initial_positions"] > 1e-2, no_h
    assert no_xn["initial_positions"] > 1e-2 and no_xn["initial_velocities"] > 1e-3, no_xn
    assert frictionless["initial_velocities"] > 1e-1, frictionless


def test_host_lag_and_friction_hessian_match_the_kernels():
    """The lag (pairs kept, normal forces) of every step and the last step's friction Hessian blocks
    (friction_kernel's mode 2, the exact Hessian for fixed lagged quantities) against the host
    complex-step ones, at the end of a forward run."""
    bodies = [wf.Body(TOP, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0), name="top"),
              wf.Body(BASE, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0), name="base",
                      offset=(-0.05, -0.025, -0.059))]
    model = wf.Model.from_bodies(bodies, gravity=(0.0, 0.0, -9.81))
    sim = wf.Simulator(model, dt=0.01, linear_solver="direct", friction_iterations=0, tol=1e-12, max_iters=300)
    sc = sim.set_contact(bodies=True, dhat=0.01, stiffness=1e5, friction=MU)
    sim.set_positions(sim.positions() + JITTER)
    v = np.zeros((N, 3))
    v[:TOP.num_vertices] = (0.3, 0.1, -0.3)
    sim.set_velocities(v)
    rest = model.rest_positions
    for _ in range(4):
        xn = sim.positions()
        assert sim.step().converged
        x1 = sim.positions()
        lam_dev = dict(zip(map(tuple, sc._f_pairs_np), sc.normal_forces()))
        pairs, kinds = sc.candidates(wp.array(xn, dtype=wp.vec3d))
        lam, _, _ = AS.lag_host(xn[pairs], kinds, rest[pairs], sc.kappa, sc.dhat)
        keep = lam > 0
        lam_host = dict(zip(map(tuple, pairs[keep]), lam[keep]))
        assert set(lam_host) == set(lam_dev) and len(lam_dev) > 5
        assert max(abs(lam_host[q] - lam_dev[q]) for q in lam_dev) <= 1e-12 * max(lam_dev.values())
        assert (AS.PT, AS.EE) == (SK.PT, SK.EE)
        assert sorted(set(kinds[keep].tolist())) == [SK.PT, SK.EE]  # point-triangle and edge-edge pairs
    # friction Hessian of the last step at x1: the kernel (lagged at xn) and the host
    eps = sc.friction_velocity * sim.dt
    terms = AS.surface_friction_terms(pairs, kinds, x1, xn, rest, kappa=sc.kappa, dhat=sc.dhat, mu=sc.friction, eps=eps)
    pat = sim.pattern
    host = np.zeros((pat.nnz, 3, 3))
    terms.add_hessian(host, pat)
    vals = pat.new_values()
    vals.zero_()
    ops = sim.ops
    dbase = ops.new_vector()
    dbase.assign(x1 - xn)
    sc.run_friction(2, dbase, ops.new_vector(), 0.0, values=vals)
    dev = vals.numpy().reshape(-1, 3, 3)[:pat.nnz]
    assert np.abs(host).max() > 0
    assert np.abs(host - dev).max() <= 1e-9 * np.abs(dev).max()
    # the host gradient (the complex step's function) is the kernel's too
    g = ops.new_vector()
    g.zero_()
    sc.run_friction(1, dbase, ops.new_vector(), 0.0, g=g)
    gh = np.zeros((N, 3))
    np.add.at(gh, terms.pairs, terms.g)
    assert np.abs(gh - g.numpy()).max() <= 1e-10 * np.abs(gh).max()


def _c_shape():
    """A Tet4 'C' of one body: a 20 x 5 cm arm 1.5 cm above another (3 cm thick, its bottom
    clamped), joined at x < 5 cm (4 x 1 x 3 cells, the middle layer's three outer cells removed)."""
    box = wf.box_tet_mesh(size=(0.2, 0.05, 0.09), cells=(4, 1, 3))
    V = np.array(box.vertices, dtype=np.float64)
    V[:, 2] = np.array([0.0, 0.03, 0.045, 0.075])[np.rint(V[:, 2] / 0.03).astype(int)]
    T = np.asarray(box.elements).reshape(-1, 4)
    cell = np.arange(len(T)) // 6
    return wf.VolumeMesh(V, T[~((cell // 4 == 1) & (cell % 4 >= 1))], "tet4")


C_SHAPE = _c_shape()
NC = C_SHAPE.num_vertices
C_JITTER = 2e-4 * np.random.default_rng(3).standard_normal((NC, 3))
C_W = np.random.default_rng(6).standard_normal((STEPS + 1, NC, 3))


def run_self(E=5e4, mu=MU, dv=None, dx=None, record=False):
    """The C's upper arm swung down (up to 0.45 m/s) and sideways (0.15 m/s) onto the lower one:
    self contact with friction (kappa 1e5 N/m^3, dhat 1 cm)."""
    model = wf.Model(C_SHAPE, wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, 0.0, -9.81))
    X = model.rest_positions
    model.fix(np.flatnonzero(X[:, 2] < 1e-9))
    sim = wf.Simulator(model, dt=0.01, linear_solver="direct", friction_iterations=0,
                       linear_solver_options={"backend": "superlu"}, tol=1e-12, max_iters=300)
    sc = sim.set_contact(bodies=False, self=True, dhat=0.01, stiffness=1e5, friction=mu)
    sim.set_positions(sim.positions() + C_JITTER + (0.0 if dx is None else dx))
    v = np.zeros((NC, 3))
    arm = X[:, 2] > 0.04
    reach = np.maximum(X[arm, 0] - 0.05, 0.0)
    v[arm, 2], v[arm, 1] = -3.0 * reach, reach
    sim.set_velocities(v if dv is None else v + dv)
    loss, rec, lagged, _ = _stepped(sim, sc, C_W, record)
    return loss, rec, lagged


def test_self_contact_friction_gradients_match_central_differences():
    _, rec, lagged = run_self(record=True)
    assert sum(k > 0 for k in lagged) >= 8 and max(lagged) >= 100, lagged  # self pairs lagged in most steps
    g = rec.backward({k: C_W[k] for k in range(STEPS + 1)})
    D = np.random.default_rng(8).standard_normal((NC, 3))
    # x_0's step is 3e-8 m: friction sticks below eps_v h = 2.3e-6 m of sliding, so the loss bends
    # sharply in x_0 (measured: a 1e-7 m step is 2.4e-5 off, 8e-8 with a 10x friction_velocity)
    checks = {"youngs_modulus": (float(g["youngs_modulus"]), lambda h: run_self(E=5e4 + h), 5.0),
              "initial_velocities": (float(np.sum(g["initial_velocities"] * D)), lambda h: run_self(dv=h * D), 1e-6),
              "initial_positions": (float(np.sum(g["initial_positions"] * D)), lambda h: run_self(dx=h * D), 3e-8),
              "contact_friction": (float(g["contact_friction"]), lambda h: run_self(mu=MU + h), 1e-5)}
    assert_central_differences(checks, value=lambda r: r[0])
