"""What the deterministic (atomic-free) assembly of surface contact and stiffness warping costs.

Surface contact: two soft boxes of about
``--tets`` tetrahedra, the upper one dropped onto the lower one with friction, stepped into contact;
then, at that state, the contact's energy, gradient and Hessian (barrier pairs + lagged friction)
with the gather (per-pair slots, then per vertex / per block in a fixed order) against the atomic
scatter it replaced (``surface.GATHER = False``), interleaved, best of ``--reps``, process CPU
time and wall time; on one thread (the serial cost) and, for the gather, on two. Then the one-off
work per broad-phase query (the canonical sort of the pairs, the gather maps) and whole steps of
two simulators taking the same steps, one per assembly, alternated.

Stiffness warping: the warped assembly (rotations, forces, stiffness blocks) of a clamped box of
about ``--warp-tets`` tets, vertices perturbed, gather against atomics (``stiffness_warping.GATHER``),
one thread, and the gather on two.

    .venv/bin/python kernels_bench/bench_gather.py [--tets 20000] [--warp-tets 24000] [--reps 9] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import warp as wp  # noqa: E402

import warpfem.contact.surface as S  # noqa: E402
import warpfem.solvers.stiffness_warping as SW  # noqa: E402
import warpfem.threads as TH  # noqa: E402
from warpfem.contact import surface_kernels as SK  # noqa: E402
from warpfem.materials import make_material  # noqa: E402
from warpfem.mesh import box_tet_mesh  # noqa: E402
from warpfem.model import Model  # noqa: E402
from warpfem.simulator import Simulator  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_surface_contact import two_boxes  # noqa: E402


def make(tets, precision, friction):
    mesh, na = two_boxes(tets, apart=False)
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
              gravity=(0.0, -9.81, 0.0))
    X = np.asarray(mesh.vertices)
    m.fix(np.flatnonzero((np.arange(len(X)) < na) & (X[:, 1] < 1e-9)))
    sim = Simulator(m, precision=precision, dt=1.0 / 120.0, integrator="newmark", max_iters=60)
    sim.set_contact(friction=friction)
    v = np.zeros((m.num_vertices, 3))
    v[na:] = (0.3, -0.5, 0.0)
    sim.set_velocities(v)
    return sim


def timed(fn, reps):
    """(best wall, best process CPU) seconds of fn() over reps runs."""
    wall, cpu = [], []
    for _ in range(reps):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return min(wall), min(cpu)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--precision", default="float64")
    ap.add_argument("--tets", type=int, default=20000)
    ap.add_argument("--reps", type=int, default=9)
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds of every variant")
    ap.add_argument("--steps", type=int, default=4, help="steps of the step comparison")
    ap.add_argument("--friction", type=float, default=0.3)
    ap.add_argument("--warp-tets", type=int, default=24000)
    ap.add_argument("--skip-contact", action="store_true")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    out = {"device": "cpu", "machine": platform.machine(), "processor": platform.processor(),
           "python": platform.python_version(), "warp": wp.config.version, "precision": a.precision,
           "load_average": os.getloadavg()}
    out["warping"] = warping(a)
    if not a.skip_contact:
        contact(a, out)
    out["load_average_end"] = os.getloadavg()
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


def warping(a):
    n = max(2, int(round((a.warp_tets / 6) ** (1.0 / 3.0))))
    mesh = box_tet_mesh(size=(1.0, 1.0, 1.0), cells=(n, n, n))
    m = Model(mesh, make_material("corotated", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0))
    X = np.asarray(mesh.vertices)
    m.fix(np.flatnonzero(X[:, 0] < 1e-9))
    TH.set_threads(1)
    sim = SW.StiffnessWarpingSimulator(m, precision=a.precision, rotation="polar")
    x = sim.ops.new_vector()
    x.assign(X + 0.02 * np.random.default_rng(0).standard_normal(X.shape) / n)
    jobs = {"force": lambda: sim._assemble(x, matrix=False), "force+stiffness": lambda: sim._assemble(x, matrix=True)}
    variants = (("atomic", False, 1), ("gather", True, 1), ("gather-2-threads", True, 2))
    best = {}
    for _ in range(a.rounds):
        for v, gather, threads in variants:
            SW.GATHER = gather
            TH.set_threads(threads)
            for j, fn in jobs.items():
                fn()
                w, c = timed(fn, a.reps)
                b = best.get((v, j), (np.inf, np.inf))
                best[(v, j)] = (min(b[0], w), min(b[1], c))
    SW.GATHER = True
    TH.set_threads(1)
    rows = []
    for j in jobs:
        at, ga, g2 = best[("atomic", j)], best[("gather", j)], best[("gather-2-threads", j)]
        row = dict(job=j, tets=int(mesh.num_elements), atomic_ms=1e3 * at[1], gather_ms=1e3 * ga[1],
                   gather_over_atomic_cpu=ga[1] / at[1], gather_over_atomic_wall=ga[0] / at[0],
                   gather_2_threads_wall_ms=1e3 * g2[0], speedup_2_threads_wall=ga[0] / g2[0])
        rows.append(row)
        print(f"warping {j:16s} ({row['tets']} tets) atomic {row['atomic_ms']:.2f} ms  gather {row['gather_ms']:.2f} ms "
              f"(CPU, 1 thread: {row['gather_over_atomic_cpu']:.3f}x; wall {row['gather_over_atomic_wall']:.3f}x)  "
              f"2 threads {row['gather_2_threads_wall_ms']:.2f} ms wall ({row['speedup_2_threads_wall']:.2f}x)", flush=True)
    return rows


def contact(a, out):
    TH.set_threads(1)
    sim = make(a.tets, a.precision, a.friction)
    sc = sim.surface_contact
    out["tets"] = int(sim.model.mesh.num_elements)
    for _ in range(40):  # into contact, with friction lagged
        sim.step()
        if sc.num_friction > 0 and sc._has_blocks.sum() > 0:
            break
    ops = sim.ops
    x = sim.x
    y = ops.new_vector()
    y.assign(sim.state.x.numpy() - sc.step_start.numpy())
    dbase = ops.new_vector()
    sc.update_pairs(x)
    out.update(pairs=int(sc.num_pairs), pairs_with_blocks=int(sc._has_blocks.sum()), friction_pairs=int(sc.num_friction))
    acc = wp.zeros(8, dtype=wp.float64)
    g = ops.new_vector()
    vals = wp.zeros_like(sim.system.hessian_values)
    jobs = {
        "energy": lambda: (sc.run(SK.MODE_ENERGY, x, acc=acc), sc.run_friction(0, dbase, y, 1.0, acc=acc)),
        "gradient": lambda: (sc.run(SK.MODE_GRADIENT, x, g=g, acc=acc), sc.run_friction(1, dbase, y, 1.0, g=g, acc=acc)),
        "hessian": lambda: (sc.run(SK.MODE_HESSIAN, x, values=vals), sc.run_friction(2, dbase, y, 1.0, values=vals)),
    }
    variants = (("atomic", False, 1), ("gather", True, 1), ("gather-2-threads", True, 2))
    best = {(v, j): (np.inf, np.inf) for v, _, _ in variants for j in jobs}
    for _ in range(a.rounds):
        for v, gather, threads in variants:
            S.GATHER = gather
            TH.set_threads(threads)
            for j, fn in jobs.items():
                fn()  # warm (maps built, launches recorded)
                w, c = timed(fn, a.reps)
                b = best[(v, j)]
                best[(v, j)] = (min(b[0], w), min(b[1], c))
    S.GATHER = True
    TH.set_threads(1)
    rows = []
    for j in jobs:
        at, ga, g2 = best[("atomic", j)], best[("gather", j)], best[("gather-2-threads", j)]
        row = dict(job=j, atomic_ms=1e3 * at[1], gather_ms=1e3 * ga[1], gather_over_atomic_cpu=ga[1] / at[1],
                   atomic_wall_ms=1e3 * at[0], gather_wall_ms=1e3 * ga[0], gather_over_atomic_wall=ga[0] / at[0],
                   gather_2_threads_wall_ms=1e3 * g2[0], speedup_2_threads_wall=ga[0] / g2[0])
        rows.append(row)
        print(f"{j:9s} atomic {row['atomic_ms']:.3f} ms  gather {row['gather_ms']:.3f} ms  (CPU, 1 thread: "
              f"{row['gather_over_atomic_cpu']:.3f}x; wall {row['gather_over_atomic_wall']:.3f}x)  "
              f"2 threads {row['gather_2_threads_wall_ms']:.3f} ms wall ({row['speedup_2_threads_wall']:.2f}x)",
              flush=True)
    out["evaluations"] = rows

    # one-off work per broad-phase query: canonical sort, gather maps
    def query():
        sc._valid = False
        sc.update_pairs(x)
    pairs_np, kinds = sc.pairs_np.copy(), sc._kinds.numpy()[:sc.num_pairs].copy()
    tq = min(timed(query, a.reps)[1] for _ in range(a.rounds))
    ts = min(timed(lambda: S.canonical_order(pairs_np, kinds), a.reps)[1] for _ in range(a.rounds))
    tm = min(timed(sc._update_maps, a.reps)[1] for _ in range(a.rounds))
    tf = min(timed(sc._build_friction_maps, a.reps)[1] for _ in range(a.rounds))
    out["query"] = dict(query_ms=1e3 * tq, sort_ms=1e3 * ts, maps_ms=1e3 * tm, friction_maps_ms=1e3 * tf)
    print(f"per query: broad phase {1e3 * tq:.2f} ms (with its canonical sort {1e3 * ts:.3f} ms); gather maps "
          f"{1e3 * tm:.3f} ms (built at the first gradient or Hessian after a query), friction maps {1e3 * tf:.3f} ms "
          "(once per step)", flush=True)

    # whole steps: two simulators taking the same steps, one per assembly, alternated step by step
    sims = {True: make(a.tets, a.precision, a.friction), False: make(a.tets, a.precision, a.friction)}
    for s in sims.values():  # the same start as above (into contact)
        for _ in range(2):
            s.step()
    cpu = {True: 0.0, False: 0.0}
    newton = {True: 0, False: 0}
    for _ in range(a.steps):
        for gather in (False, True):
            S.GATHER = gather
            c0 = time.process_time()
            st = sims[gather].step()
            cpu[gather] += time.process_time() - c0
            newton[gather] += st.newton_iterations
    S.GATHER = True
    out["steps"] = dict(steps=a.steps, atomic_cpu_s=cpu[False], gather_cpu_s=cpu[True], ratio=cpu[True] / cpu[False],
                        newton_atomic=newton[False], newton_gather=newton[True])
    print(f"{a.steps} steps: atomic {cpu[False]:.2f} s, gather {cpu[True]:.2f} s CPU ({cpu[True] / cpu[False]:.3f}x); "
          f"Newton iterations {newton[False]} / {newton[True]}", flush=True)


if __name__ == "__main__":
    main()
