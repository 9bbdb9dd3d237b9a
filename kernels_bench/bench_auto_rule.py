"""``auto``'s deterministic rule (``rule="model"``, the default) against the timed rule it replaced
(``rule="measured"``) on the cases that measured the rules: the cantilevers of
bench_auto_crossover.py above EXPLORE_MIN_DOFS unknowns (below it both rules keep their starting
solver: the same code path, not measured again) and the 98k-tet box of bench_scale.py at nu 0.49.
Per case: the two rules and the three candidates named (pcg, direct, multigrid; direct not on the
box) alternate for ``--rounds`` rounds, each run a new simulator, ``--warmup`` steps (the measured
rule's timings and set-ups happen there), then ``--steps`` timed steps; the fastest run of each
configuration is kept. Recorded: ms per step, what each run chose, whether the runs of a
configuration ended at bit-identical positions, and each rule's time over the best named solver's.

    .venv/bin/python kernels_bench/bench_auto_rule.py [--steps 4] [--warmup 2] [--no-box] [--json PATH]
    .venv/bin/python kernels_bench/bench_auto_rule.py --repeat-box 4 --steps 3 [--json PATH]
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

RULES = ("model", "measured")
NAMED = ("pcg", "direct", "multigrid")  # the candidates, named: what the best choice would have cost
CANTILEVER_CELLS = [(30, 5, 5), (40, 6, 6), (50, 8, 8)]  # bench_auto_crossover's sizes above EXPLORE_MIN_DOFS


def _solver(rule):
    """'model' / 'measured': auto with that rule; any other name: that solver, named."""
    if rule in ("model", "measured"):
        return dict(linear_solver="auto", linear_solver_options={"rule": rule})
    return dict(linear_solver=rule)


def cantilever(cells, E, tol, cg, rule):
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=cells)
    mat = wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81), mass_matrix="lumped")
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    return wf.Simulator(model, dt=1 / 60, integrator="newmark", tol=tol, cg_tol=cg, max_cg_iters=5000, **_solver(rule))


def box98k(rule):
    c = 16
    mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=(4 * c, c, c))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.49, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    return wf.Simulator(model, dt=1.0 / 60.0, **_solver(rule))


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
    return ms, getattr(sim._pcg, "active", sim._pcg.name), hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()[:16]


def repeat_box(args):
    """The issue this rule fixes: N runs of the box with the defaults, the same final positions?"""
    def default_box():
        c = 16
        mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=(4 * c, c, c))
        mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.49, density=1000.0)
        model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
        model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
        return wf.Simulator(model, dt=1.0 / 60.0)  # every option at its default: linear_solver "auto"

    load0 = os.getloadavg()[0]
    runs = []
    for i in range(args.repeat_box):
        ms, chose, digest = run(default_box, 0, args.steps)
        runs.append(dict(ms_per_step=ms, chose=chose, positions_sha256_16=digest))
        print(f"run {i + 1}: {ms:8.1f} ms/step, {chose}, final positions {digest}", flush=True)
    same = len({r["positions_sha256_16"] for r in runs}) == 1
    print(f"{args.repeat_box} runs, {args.steps} steps each: final positions {'identical' if same else 'DIFFERENT'}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(device="cpu", machine=platform.machine(), cores=os.cpu_count(), load_start=load0,
                           load_end=os.getloadavg()[0], steps=args.steps, case="box 98k tets nu 0.49, defaults",
                           runs=runs, identical=same), f, indent=1)
    return 0 if same else 1


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2, help="runs of each configuration (the fastest kept)")
    ap.add_argument("--no-box", action="store_true", help="leave out the 98k-tet box")
    ap.add_argument("--repeat-box", type=int, default=0, metavar="N",
                    help="instead: N runs of the 98k-tet box at nu 0.49 with the default solver, --steps steps each; "
                         "are the final positions the same bits?")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    if args.repeat_box:
        return repeat_box(args)
    cases = []
    for cells in CANTILEVER_CELLS:
        for E in (1e6, 1e8):
            for tol, cg in ((1e-2, 1e-1), (1e-5, 1e-3)):
                cases.append((f"cantilever {cells} E {E:.0e} tol {tol:g}/{cg:g}",
                              lambda rule, cells=cells, E=E, tol=tol, cg=cg: cantilever(cells, E, tol, cg, rule)))
    if not args.no_box:
        cases.append(("box 98k tets nu 0.49", box98k))  # (direct: 5-7 s per step there, not run)
    load0 = os.getloadavg()[0]
    print(f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {load0:.1f}); "
          f"cantilevers above {EXPLORE_MIN_DOFS} unknowns")
    rows = []
    for name, make in cases:
        configs = RULES + tuple(n for n in NAMED if not (n == "direct" and name.startswith("box")))
        res = {c: [] for c in configs}
        for _ in range(args.rounds):  # interleaved: each configuration once per round
            for c in configs:
                res[c].append(run(lambda: make(c), args.warmup, args.steps))
        row = dict(case=name)
        for c, rs in res.items():
            row[f"{c}_ms"] = min(r[0] for r in rs)
            row[f"{c}_chose"] = [r[1] for r in rs]
            row[f"{c}_same_bits"] = all(r[2] == rs[0][2] for r in rs)
        best = min(row[f"{n}_ms"] for n in configs if n not in RULES)
        row["model_over_measured"] = row["model_ms"] / row["measured_ms"]
        row["model_over_best_named"] = row["model_ms"] / best
        row["measured_over_best_named"] = row["measured_ms"] / best
        rows.append(row)
        named = "  ".join(f"{n} {row[f'{n}_ms']:.0f}" for n in configs if n not in RULES)
        print(f"{name:45s} model {row['model_ms']:7.1f} ms ({'/'.join(row['model_chose'])}) "
              f"measured {row['measured_ms']:7.1f} ms ({'/'.join(row['measured_chose'])})  named: {named}  "
              f"model/measured {row['model_over_measured']:.2f}  bits repeat: {row['model_same_bits']} / "
              f"{row['measured_same_bits']}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(device="cpu", machine=platform.machine(), cores=os.cpu_count(), load_start=load0,
                           load_end=os.getloadavg()[0], steps=args.steps, warmup=args.warmup, rows=rows), f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
