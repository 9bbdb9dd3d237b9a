"""Where the direct solver overtakes block-Jacobi PCG per time step on the CPU: ms per step of the
same cantilever (1 m x 0.2 m x 0.2 m, clamped at x = 0, stable neo-Hookean, gravity, Newmark,
dt 1/60) meshed ever finer, with ``linear_solver = "pcg"`` and ``"direct"``, at a loose and a
tight tolerance (tol 1e-2 / cg_tol 1e-1 and tol 1e-5 / cg_tol 1e-3), soft (E = 1e6) and stiff
(E = 1e8). The measurements behind ``auto``'s small-system rule (docs/linear_solvers.md).

    .venv/bin/python kernels_bench/bench_auto_crossover.py [--steps 8] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout's warpfem

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402

CELLS = [(20, 2, 2), (20, 4, 4), (30, 5, 5), (40, 6, 6), (50, 8, 8)]


def ms_per_step(cells, E, ls, tol, cg, steps):
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=cells)
    mat = wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81), mass_matrix="lumped")
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    sim = wf.Simulator(model, dt=1 / 60, integrator="newmark", tol=tol, cg_tol=cg, linear_solver=ls, max_cg_iters=5000,
                       )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(2):
            sim.step()
        t0 = time.perf_counter()
        lin = 0
        for _ in range(steps):
            lin += sim.step().linear_iterations
    return 1e3 * (time.perf_counter() - t0) / steps, lin / steps, 3 * mesh.num_vertices


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    rows = []
    print(f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})")
    print(f"{'DOFs':>6s} {'E':>6s} {'tol/cg_tol':>12s} {'pcg ms':>8s} {'(CG/step)':>9s} {'direct ms':>9s} {'pcg/direct':>10s}")
    for cells in CELLS:
        for E in (1e6, 1e8):
            for tol, cg in ((1e-2, 1e-1), (1e-5, 1e-3)):
                tp, itp, n = ms_per_step(cells, E, "pcg", tol, cg, args.steps)
                td, _, _ = ms_per_step(cells, E, "direct", tol, cg, args.steps)
                rows.append(dict(cells=cells, dofs=n, E=E, tol=tol, cg_tol=cg, pcg_ms=tp, cg_per_step=itp, direct_ms=td))
                print(f"{n:6d} {E:6.0e} {tol:5.0e}/{cg:5.0e} {tp:8.2f} {itp:9.0f} {td:9.2f} {tp / td:10.2f}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(device="cpu", load=os.getloadavg()[0], rows=rows), f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
