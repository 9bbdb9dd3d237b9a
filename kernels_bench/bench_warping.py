"""Cost per step and accuracy of stiffness warping vs Newton backward Euler on a cantilever beam.

Methods, all on the same beam and at the same dt:
  warping-polar, warping-qr      StiffnessWarpingSimulator (one PCG solve per step)
  newton-corotated, newton-snh   warpfem.Simulator (Newton + line search, default tolerances)
Each trajectory is compared with converged references (Newton, float64, tol 1e-8, cg_tol 1e-8,
dt/8) of the corotated and the stable neo-Hookean material: error = max over the coarse steps of
max_vertex |x - x_ref| / max_vertex |x_ref - X| (relative to the largest displacement).
Also the difference to Newton corotated at the same dt (the model error of warping alone,
without the time-discretisation error both share). Reported: ms per step (mean over the run, after a warm-up step), ratio to warping-polar, PCG
iterations and Newton iterations per step, errors. ``--json`` writes the table as JSON.

    .venv/bin/python kernels_bench/bench_warping.py [--cells 20 2 2] [--steps 30] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
import warnings

import numpy as np

import warpfem as wf
from warpfem.solvers.stiffness_warping import StiffnessWarpingSimulator


def build(args, material, *, precision="float64"):
    mesh = wf.box_tet_mesh(size=(10.0, 1.0, 1.0), cells=tuple(args.cells))
    mat = wf.make_material(material, youngs_modulus=args.youngs_modulus, poisson_ratio=args.poisson_ratio, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 2, 2)))
    return mesh, model


def run(sim, steps, record_every=1):
    """Step ``steps`` times; returns (positions after every ``record_every`` steps, seconds per step, stats)."""
    frames, secs, cg, newton = [], 0.0, 0, 0
    for k in range(steps):
        t0 = time.perf_counter()
        st = sim.step()
        secs += time.perf_counter() - t0
        cg += st.cg_iterations
        newton += st.newton_iterations
        if (k + 1) % record_every == 0:
            frames.append(sim.positions())
    return np.array(frames), secs / steps, cg / steps, newton / steps


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cells", type=int, nargs=3, default=[20, 2, 2])
    p.add_argument("--steps", type=int, default=30, help="coarse steps (default 30 = 0.5 s at dt 1/60)")
    p.add_argument("--dt", type=float, default=1.0 / 60.0)
    p.add_argument("--youngs-modulus", type=float, default=1e6)
    p.add_argument("--poisson-ratio", type=float, default=0.3)
    p.add_argument("--refine", type=int, default=8, help="reference dt = dt / refine")
    p.add_argument("--device", default="cpu")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)

    refs = {}
    for material in ("corotated", "stable_neo_hookean"):
        mesh, model = build(args, material)
        sim = wf.Simulator(model, device=args.device, dt=args.dt / args.refine, tol=1e-8, cg_tol=1e-8, max_iters=50)
        refs[material], _, _, _ = run(sim, args.steps * args.refine, record_every=args.refine)
    X = mesh.vertices
    scale = {k: np.abs(r - X[None]).max() for k, r in refs.items()}

    methods = {
        "warping-polar": lambda m: StiffnessWarpingSimulator(m, device=args.device, dt=args.dt, rotation="polar"),
        "warping-qr": lambda m: StiffnessWarpingSimulator(m, device=args.device, dt=args.dt, rotation="qr"),
        "newton-corotated": lambda m: wf.Simulator(m, device=args.device, dt=args.dt),
        "newton-snh": lambda m: wf.Simulator(m, device=args.device, dt=args.dt),
    }
    material_of = {"warping-polar": "corotated", "warping-qr": "corotated", "newton-corotated": "corotated",
                   "newton-snh": "stable_neo_hookean"}
    rows, trajectories = [], {}
    for name, make in methods.items():
        _, model = build(args, material_of[name])
        warm = make(model)
        warm.step()  # compile / warm caches
        sim = make(build(args, material_of[name])[1])
        frames, sec, cg, newton = run(sim, args.steps)
        trajectories[name] = frames
        err = {k: float(np.abs(frames - refs[k]).max() / scale[k]) for k in refs}
        rows.append(dict(method=name, ms_per_step=1e3 * sec, cg_per_step=cg, newton_per_step=newton,
                         err_vs_corotated=err["corotated"], err_vs_snh=err["stable_neo_hookean"]))
    base = rows[0]["ms_per_step"]
    for r in rows:
        r["ratio_to_warping_polar"] = r["ms_per_step"] / base
        # model error alone: difference to Newton corotated at the same dt (same time discretisation)
        r["diff_vs_newton_corotated_same_dt"] = float(
            np.abs(trajectories[r["method"]] - trajectories["newton-corotated"]).max() / scale["corotated"])

    mesh, _ = build(args, "corotated")
    header = (f"beam 10x1x1, cells {tuple(args.cells)} ({mesh.num_vertices} vertices, {mesh.num_tets} tets), "
              f"E {args.youngs_modulus:g} Pa, nu {args.poisson_ratio}, rho 1000, gravity, dt {args.dt:.5g} s, "
              f"{args.steps} steps; reference Newton float64 tol 1e-8 at dt/{args.refine}; "
              f"max reference displacement {scale['corotated']:.3f} m (corotated), {scale['stable_neo_hookean']:.3f} m (SNH); "
              f"device {args.device} ({platform.processor() or platform.machine()})")
    print(header)
    print(f"{'method':<18} {'ms/step':>9} {'ratio':>7} {'CG/step':>8} {'Newton/step':>11} {'err vs corot':>13} {'err vs SNH':>11} {'vs Newton-corot same dt':>24}")
    for r in rows:
        print(f"{r['method']:<18} {r['ms_per_step']:9.2f} {r['ratio_to_warping_polar']:7.2f} {r['cg_per_step']:8.1f} "
              f"{r['newton_per_step']:11.2f} {r['err_vs_corotated']:13.2e} {r['err_vs_snh']:11.2e} {r['diff_vs_newton_corotated_same_dt']:24.2e}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"setup": header, "args": vars(args), "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
