"""``auto``'s deterministic rule (``rule="model"``, the default) against the timed rule it replaced
(``rule="measured"``) on the cases that measured the rules: the cantilevers of
bench_auto_crossover.py above EXPLORE_MIN_DOFS unknowns (below it both rules keep their starting
solver: the same code path, not measured again) and the 98k-tet box of bench_scale.py at nu 0.49.
Per case: the two rules alternate (model, measured, model, measured), each run a new simulator,
``--warmup`` steps (the measured rule's timings and set-ups happen there), then ``--steps`` timed
steps; the faster of the two runs of each rule is kept. Recorded: ms per step, what each run chose,
and whether the two runs of a rule ended at bit-identical positions.

    .venv/bin/python kernels_bench/bench_auto_rule.py [--steps 4] [--warmup 2] [--no-box] [--json PATH]
"""

from __future__ import annotations

import argparse
import hashlib
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
from warpfem.solvers.linear.auto import EXPLORE_MIN_DOFS  # noqa: E402

CANTILEVER_CELLS = [(30, 5, 5), (40, 6, 6), (50, 8, 8)]  # bench_auto_crossover's sizes above EXPLORE_MIN_DOFS


def cantilever(cells, E, tol, cg, rule):
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=cells)
    mat = wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81), mass_matrix="lumped")
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    return wf.Simulator(model, dt=1 / 60, integrator="newmark", tol=tol, cg_tol=cg, linear_solver="auto",
                        linear_solver_options={"rule": rule}, max_cg_iters=5000)


def box98k(rule):
    c = 16
    mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=(4 * c, c, c))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.49, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    return wf.Simulator(model, dt=1.0 / 60.0, linear_solver="auto", linear_solver_options={"rule": rule})


def run(make, warmup, steps):
    sim = make()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(warmup):
            sim.step()
        t0 = time.perf_counter()
        for _ in range(steps):
            sim.step()
        ms = 1e3 * (time.perf_counter() - t0) / steps
    x = sim.positions()
    return ms, sim._pcg.active, hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()[:16]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--no-box", action="store_true", help="leave out the 98k-tet box")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    cases = []
    for cells in CANTILEVER_CELLS:
        for E in (1e6, 1e8):
            for tol, cg in ((1e-2, 1e-1), (1e-5, 1e-3)):
                cases.append((f"cantilever {cells} E {E:.0e} tol {tol:g}/{cg:g}",
                              lambda rule, cells=cells, E=E, tol=tol, cg=cg: cantilever(cells, E, tol, cg, rule)))
    if not args.no_box:
        cases.append(("box 98k tets nu 0.49", box98k))
    load0 = os.getloadavg()[0]
    print(f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {load0:.1f}); "
          f"cantilevers above {EXPLORE_MIN_DOFS} unknowns")
    rows = []
    for name, make in cases:
        res = {"model": [], "measured": []}
        for rule in ("model", "measured", "model", "measured"):
            res[rule].append(run(lambda: make(rule), args.warmup, args.steps))
        row = dict(case=name)
        for rule, rs in res.items():
            row[f"{rule}_ms"] = min(r[0] for r in rs)
            row[f"{rule}_chose"] = [r[1] for r in rs]
            row[f"{rule}_same_bits"] = rs[0][2] == rs[1][2]
        row["model_over_measured"] = row["model_ms"] / row["measured_ms"]
        rows.append(row)
        print(f"{name:45s} model {row['model_ms']:8.1f} ms {'/'.join(row['model_chose']):17s} "
              f"measured {row['measured_ms']:8.1f} ms {'/'.join(row['measured_chose']):17s} "
              f"ratio {row['model_over_measured']:.2f}  same bits: {row['model_same_bits']} / {row['measured_same_bits']}",
              flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(device="cpu", machine=platform.machine(), cores=os.cpu_count(), load_start=load0,
                           load_end=os.getloadavg()[0], steps=args.steps, warmup=args.warmup, rows=rows), f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
