"""Newton iterations per step and step time with ``initial_guess = "previous"`` (v_n) against
``"extrapolated"`` (constant acceleration from the history).

Cases: a 2 x 0.5 x 0.5 m box of 12,288 tets (E 1e5, rho 1000, stable neo-Hookean, clamped at x = 0,
gravity, dt 1/60, nu 0.3 and 0.49) and the bunny of examples/scenes/bunny_gravity.toml (its model,
dt 1/60). Both runs of a case use the same simulator settings; prints Newton iterations per step,
seconds per step and the largest position difference between the two runs after the last step.

    python kernels_bench/bench_initial_guess.py --steps 30 [--integrator backward_euler] [--case box03]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

import warpfem as wf  # noqa: E402
from warpfem.scenes import load_scene  # noqa: E402


def box_model(nu):
    mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=(32, 8, 8))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=nu, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 1, 1)))
    return model, {}


def bunny_model():
    scene = load_scene(os.path.join(ROOT, "examples", "scenes", "bunny_gravity.toml"))
    run = scene.build(device="cpu", precision="float64")
    return run.model, {"damping_mass": 1.0}


def run(model, extra, guess, steps, integrator, linear_solver, atol):
    opts = dict(extra) if atol is None else dict(extra, tol=1e-12, atol=atol)
    sim = wf.Simulator(model, dt=1.0 / 60.0, integrator=integrator, initial_guess=guess,
                       linear_solver=linear_solver, **opts)
    its, cg, secs, g0, g = [], [], [], [], []
    for _ in range(steps):
        t0 = time.perf_counter()
        st = sim.step()
        secs.append(time.perf_counter() - t0)
        its.append(st.newton_iterations)
        cg.append(st.linear_iterations)
        g.append(st.gradient_norm)
        g0.append(st.gradient_norm / st.residual if st.residual > 0 else st.gradient_norm)
    return np.array(its), np.array(cg), np.array(secs), sim.positions(), np.array(g0), np.array(g)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--integrator", default="backward_euler")
    ap.add_argument("--linear-solver", default="auto")
    ap.add_argument("--case", action="append", choices=["box03", "box049", "bunny"])
    ap.add_argument("--atol-factor", type=float, default=None,
                    help="stop on an absolute gradient norm: this factor times the median starting "
                         "gradient norm of the 'previous' run (default: the relative tol = 1e-6)")
    a = ap.parse_args()
    cases = a.case or ["box03", "box049", "bunny"]
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}, "
          f"integrator {a.integrator}, linear solver {a.linear_solver}, {a.steps} steps")
    print(f"{'case':8s} {'guess':13s} {'newton/step':>11s} {'total':>6s} {'lin/step':>8s} {'s/step':>7s} "
          f"{'|g0| med':>9s} {'|g| max':>9s} {'max |dx| (m)':>12s}")
    for case in cases:
        model, extra = {"box03": lambda: box_model(0.3), "box049": lambda: box_model(0.49), "bunny": bunny_model}[case]()
        ref, atol = None, None
        for guess in ("previous", "extrapolated"):
            its, cg, secs, x, g0, g = run(model, extra, guess, a.steps, a.integrator, a.linear_solver, atol)
            if ref is None and a.atol_factor is not None:  # rerun 'previous' with the absolute criterion
                atol = a.atol_factor * float(np.median(g0))
                its, cg, secs, x, g0, g = run(model, extra, guess, a.steps, a.integrator, a.linear_solver, atol)
            dx = 0.0 if ref is None else float(np.abs(x - ref).max())
            ref = x if ref is None else ref
            print(f"{case:8s} {guess:13s} {its.mean():11.2f} {its.sum():6d} {cg.mean():8.1f} {secs[1:].mean():7.3f} "
                  f"{np.median(g0):9.2e} {g.max():9.2e} {dx:12.2e}", flush=True)


if __name__ == "__main__":
    main()
