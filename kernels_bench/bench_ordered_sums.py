"""What the fixed-order float64 sums (``kernels.generic.ORDERED_SUMS``, the path of devices other
than the CPU) cost when forced on the CPU, one thread: the chunked PCG (its own kernels' rows and
tree launches; ``cpu_serial`` off, as on CUDA), the multigrid's CG (recorded reductions), a dot
product, and whole steps of a simulator (``pcg`` in strict device mode: the chunked loop, its chunk
replayed as a captured graph). Default ("device": atomics in index order on the CPU) against
"always", interleaved, best of ``--reps``, wall time.

The CPU runs a launch's threads one after the other, so the forced path only adds work there (a
row per index, the tree's launches, zeroing); on a GPU the rows are written in parallel and the
tree's passes are short launches. The figure is the serial overhead, not a GPU estimate.

    .venv/bin/python kernels_bench/bench_ordered_sums.py [--cells 24 6 6] [--reps 5] [--json PATH]
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

import warpfem as wf  # noqa: E402
import warpfem.threads as TH  # noqa: E402
from warpfem.kernels import generic  # noqa: E402
from warpfem.kernels import linalg as LK  # noqa: E402
from warpfem.solvers.linear import make_linear_solver  # noqa: E402
from warpfem.transfer import strict_device_mode  # noqa: E402


def system(cells):
    mesh = wf.box_tet_mesh(size=(3.0, 0.75, 0.75), cells=cells)
    model = wf.Model(mesh, wf.make_material("linear", youngs_modulus=1e5, poisson_ratio=0.3, density=100.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    sim = wf.Simulator(model, precision="float64", linear_solver="pcg")
    vals = sim._pattern.new_values()
    sim._assemble_stiffness(sim.x, 1e-2, vals)
    wp.launch(LK.add_scaled_kernel, dim=sim._pattern.nnz, inputs=[sim._mass_values, sim._s(1.0), vals])
    b = np.random.default_rng(0).standard_normal((model.num_vertices, 3)) * (~model.fixed)
    return sim, model, vals, b


def timed(fn, reps):
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def compare(make_case, reps):
    """(default s, ordered s, ratio): each mode's case built once, warmed up, then timed alternately."""
    cases = {}
    for mode in ("device", "always"):
        generic.ORDERED_SUMS = mode
        cases[mode] = make_case()
        cases[mode]()  # compile, record
        cases[mode]()
    best = {"device": float("inf"), "always": float("inf")}
    for _ in range(reps):
        for mode in ("device", "always"):
            generic.ORDERED_SUMS = mode
            best[mode] = min(best[mode], timed(cases[mode], 1))
    generic.ORDERED_SUMS = "device"
    return {"default_s": best["device"], "ordered_s": best["always"], "ratio": best["always"] / best["device"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, nargs=3, default=(24, 6, 6))
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    TH.set_threads(1)
    wp.config.quiet = True
    sim, model, vals, b = system(tuple(a.cells))
    n = sim._pattern.num_rows
    out = {"device": "cpu", "machine": platform.machine(), "processor": platform.processor(),
           "python": platform.python_version(), "warp": wp.config.version, "threads": 1, "block_rows": n,
           "note": "shared 2-core machine (other jobs running): ratios measured interleaved in one process",
           "cases": {}}
    bd = sim._vec_array(b)

    def solve_case(name, **opts):
        def make():
            solver = make_linear_solver(name, sim._pattern, vec_type=sim._vec, scalar=sim._s,
                                        positions=model.rest_positions, **opts)
            xd = sim._vec_array()
            solver.prepare(vals, sim._mask)
            its = []

            def run():
                its.append(solver.solve(bd, xd, tol=1e-8, maxiter=2000).iterations)
            run.its = its
            return run
        return make

    out["cases"]["pcg_chunked_solve"] = compare(solve_case("pcg", check_every=16), a.reps)
    try:
        import pyamg  # noqa: F401

        out["cases"]["multigrid_solve"] = compare(solve_case("multigrid"), a.reps)
    except ImportError:
        out["cases"]["multigrid_solve"] = "pyamg not installed"

    def dot_case():
        solver = make_linear_solver("pcg", sim._pattern, vec_type=sim._vec, scalar=sim._s)
        return lambda: [solver.dot(bd, bd) for _ in range(20)]
    out["cases"]["dot_x20"] = compare(dot_case, a.reps)

    def steps_case():
        with strict_device_mode():
            m = wf.Model(wf.box_tet_mesh(size=(0.4, 0.2, 0.2), cells=(8, 4, 4)),
                         wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                         gravity=(0.0, 0.0, -9.81))
            m.fix(np.nonzero(m.rest_positions[:, 0] < 1e-9)[0])
            s = wf.Simulator(m, dt=1 / 60, precision="float64", linear_solver="pcg")

        def run():
            with strict_device_mode():
                s.step()
        return run
    out["cases"]["strict_pcg_step"] = compare(steps_case, a.reps)
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
