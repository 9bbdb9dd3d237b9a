"""Reduced (cubature) vs full backward Euler on the cantilever beam (seed 000, Cubica).

For r in {10, 20, 40} and cubature tolerance in {0.1, 0.05, 0.01}: cubature points, training time
(basis + cubature), time per reduced step, time per full step (baseline, same run), speed-up and
the tip-trajectory error (max over the run of |tip_reduced - tip_full|, relative to the peak tip
displacement of the full run). Prints a markdown table.

    .venv/bin/python kernels_bench/bench_reduced.py [--steps 30] [--device cpu]
"""

import argparse
import time
import warnings

import numpy as np
import warp as wp

import warpfem as wf
from warpfem.reduced import ReducedSimulator, train_subspace

wp.config.quiet = True


def beam():
    mesh = wf.box_tet_mesh(size=(10.0, 1.0, 1.0), cells=(20, 2, 2))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e7, poisson_ratio=0.3, density=100.0), gravity=(0, 0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2)))
    tip = np.flatnonzero(mesh.vertices[:, 0] > 10 - 1e-6)
    return "beam 20x2x2 (480 tets)", mesh, model, tip


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--dt", type=float, default=1 / 30)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--modes", default="10,20,40")
    ap.add_argument("--tols", default="0.1,0.05,0.01")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    name, mesh, model, tip = beam()
    fs = wf.Simulator(model, dt=args.dt, device=args.device)
    full_tip, t_full = [], 0.0
    for _ in range(args.steps):
        t = time.perf_counter(); fs.step(); t_full += time.perf_counter() - t
        full_tip.append(fs.positions()[tip].mean(0))
    full_tip = np.array(full_tip)
    amp = np.linalg.norm(full_tip - mesh.vertices[tip].mean(0), axis=1).max()
    t_full /= args.steps
    print(f"{name}, {args.steps} steps of dt={args.dt:.4g} s, peak tip displacement {amp:.3f} m, device {args.device}")
    print("| r | tol | cubature pts | train err | valid err | training s | reduced step ms | full step ms | speed-up | tip err / peak |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in [int(x) for x in args.modes.split(",")]:
        for tol in [float(x) for x in args.tols.split(",")]:
            t = time.perf_counter()
            sub = train_subspace(model, modes=r, modal_derivatives=True, cubature_tolerance=tol,
                                 max_cubature_points=300, seed=0)
            t_train = time.perf_counter() - t
            rs = ReducedSimulator(model, sub, dt=args.dt, device=args.device)
            rs.step()  # warm (kernel load)
            rs = ReducedSimulator(model, sub, dt=args.dt, device=args.device)
            t_red, err = 0.0, 0.0
            for k in range(args.steps):
                t = time.perf_counter(); rs.step(); t_red += time.perf_counter() - t
                err = max(err, np.linalg.norm(rs.positions()[tip].mean(0) - full_tip[k]))
            t_red /= args.steps
            rep = sub.report
            print(f"| {r} | {tol} | {rep['cubature_points']} | {rep['training_error']:.3f} | {rep['validation_error']:.3f} | "
                  f"{t_train:.1f} | {1e3 * t_red:.1f} | {1e3 * t_full:.0f} | {t_full / t_red:.0f}x | {err / amp:.3f} |", flush=True)


if __name__ == "__main__":
    main()
