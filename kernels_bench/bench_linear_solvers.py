"""Per-step cost of each linear solver of the Newton systems (pcg, direct, amg) on real scenes.

Cases: the bunny scene (examples/scenes/bunny.toml, ~23k tets), the octopus scene (~1.1k tets),
a clamped box beam (``--box-cells``; 6 tets per cell), each as shipped and with poisson_ratio 0.49
(nearly incompressible). Each (case, solver) builds the scene's simulator with
``linear_solver=<name>``, runs one warm-up step (kernel loads, first factorisation) and then
``--steps`` timed steps, recording per step: wall seconds, Newton iterations, linear iterations
(CG iterations; 1 per direct solve) and the linear solver's host read-backs. The ratio column is
the per-step time relative to pcg in the same run; ``pcg-legacy`` is the previous PCG loop
(8 launches and 3 host read-backs per iteration), the baseline of the device-scalar loop. The device and the machine's load average are
recorded with the results (this machine's CPUs are shared; compare ratios, not absolutes).

    .venv/bin/python kernels_bench/bench_linear_solvers.py [--steps 2] [--box-cells 24 6 6]
        [--solvers pcg direct amg pcg-legacy] [--cases bunny octopus box] [--out kernels_bench/results/linear_solvers]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402
from warpfem.scenes import load_scene  # noqa: E402


def _scene_run(path, *, solver, nu, device):
    scene = load_scene(path)
    scene.spec.integrator["linear_solver"] = solver
    if nu is not None:
        scene.spec.material["poisson_ratio"] = nu
    return scene.build(device=device, precision="float64")


def _box_sim(cells, *, solver, nu, device):
    L = 4.0
    mesh = wf.box_tet_mesh(size=(L, L * cells[1] / cells[0], L * cells[2] / cells[0]), cells=tuple(cells))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e6, poisson_ratio=0.3 if nu is None else nu,
                           density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    return wf.Simulator(model, device=device, dt=1.0 / 60.0, linear_solver=solver, tol=1e-5, cg_tol=1e-3)


class _Legacy:
    """The previous PCG loop (warpfem.solvers.pcg: 8 launches and 3 read-backs per iteration),
    as the baseline of the device-scalar loop."""

    name = "pcg-legacy"

    def __init__(self, sim):
        from warpfem.solvers.pcg import BlockJacobiPCG

        self.impl = BlockJacobiPCG(sim.pattern, vec_type=sim.vector_type, scalar=sim.scalar_type)
        self.device, self.scalar, self.inv_diag = self.impl.device, self.impl.scalar, self.impl.inv_diag

    def dot(self, a, b):
        return self.impl.dot(a, b)

    def solve(self, *args, **kw):
        res = self.impl.solve(*args, **kw)
        res.host_syncs = 3 * res.iterations + 2  # two before the loop, three per iteration
        return res


def step_recorder(obj, sim):
    """(advance, records): ``advance()`` runs one frame of a scene run (or one step of a bare
    simulator) and ``records`` collects the SolveStats of the steps it took (clear it per frame)."""
    records = []
    orig = sim.step

    def step():
        st = orig()
        records.append(st)
        return st

    sim.step = step
    return (obj.step_frame if hasattr(obj, "step_frame") else sim.step), records


def run_case(label, make, steps):
    t0 = time.perf_counter()
    obj = make()
    build_s = time.perf_counter() - t0
    sim = obj.sim if hasattr(obj, "sim") else obj
    if getattr(make, "legacy", False):
        sim.linear_solver = _Legacy(sim)
    advance, records = step_recorder(obj, sim)
    rows = []
    for k in range(steps + 1):
        records.clear()
        t0 = time.perf_counter()
        advance()
        secs = time.perf_counter() - t0
        for st in records:
            rows.append(dict(seconds=secs / len(records), newton=st.newton_iterations,
                             linear=st.linear_iterations, host_syncs=st.host_syncs, converged=bool(st.converged),
                             warmup=k == 0))
    timed = [r for r in rows if not r["warmup"]]
    solver = sim.linear_solver
    out = dict(case=label, solver=solver.name, vertices=sim.num_vertices, build_seconds=build_s,
               warmup_seconds=sum(r["seconds"] for r in rows if r["warmup"]),
               step_seconds=float(np.mean([r["seconds"] for r in timed])),
               newton_per_step=float(np.mean([r["newton"] for r in timed])),
               linear_per_step=float(np.mean([r["linear"] for r in timed])),
               host_syncs_per_step=float(np.mean([r["host_syncs"] for r in timed])),
               all_converged=all(r["converged"] for r in rows), steps=len(timed))
    if solver.name == "direct":
        out["backend"] = solver.backend_name
        out["symbolic_analyses"] = solver.symbolic_count
        out["prepares"] = solver.prepare_count
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=2)
    p.add_argument("--box-cells", type=int, nargs=3, default=[24, 6, 6])
    p.add_argument("--solvers", nargs="+", default=["pcg", "direct", "amg"])
    p.add_argument("--cases", nargs="+", default=["bunny", "octopus", "box"])
    p.add_argument("--nus", nargs="+", default=["scene", "0.49"])
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=str(ROOT / "kernels_bench" / "results" / "linear_solvers"))
    args = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    dev = wp.get_device(args.device)
    device_name = dev.name if dev.is_cuda else f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} logical cores)"
    results = []
    load_start = os.getloadavg()
    for case in args.cases:
        for nu_s in args.nus:
            nu = None if nu_s == "scene" else float(nu_s)
            label = f"{case}" + ("" if nu is None else f" nu={nu:g}")
            for solver_arg in args.solvers:
                solver = "pcg" if solver_arg == "pcg-legacy" else solver_arg
                if case == "box":
                    make = lambda s=solver, n=nu: _box_sim(args.box_cells, solver=s, nu=n, device=args.device)  # noqa: E731
                else:
                    path = ROOT / "examples" / "scenes" / f"{case}.toml"
                    make = lambda s=solver, n=nu, pth=path: _scene_run(pth, solver=s, nu=n, device=args.device)  # noqa: E731
                make.legacy = solver_arg == "pcg-legacy"
                r = run_case(label, make, args.steps)
                results.append(r)
                print(f"{label:18s} {r['solver']:7s} {r['step_seconds']*1e3:9.1f} ms/step  newton {r['newton_per_step']:5.1f}"
                      f"  linear {r['linear_per_step']:8.1f}  syncs {r['host_syncs_per_step']:6.1f}"
                      f"  converged {r['all_converged']}", flush=True)
    for r in results:
        base = [q for q in results if q["case"] == r["case"] and q["solver"] == "pcg"]
        r["ratio_to_pcg"] = r["step_seconds"] / base[0]["step_seconds"] if base else None
    meta = dict(device=device_name, warp=wp.__version__, box_cells=args.box_cells,
                box_tets=6 * int(np.prod(args.box_cells)), steps=args.steps,
                load_average_start=load_start, load_average_end=os.getloadavg(), cores=os.cpu_count())
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out + ".json").write_text(json.dumps(dict(meta=meta, results=results), indent=1))
    lines = [f"# Linear solvers per step ({device_name}; load average {meta['load_average_start'][0]:.1f} at the start, "
             f"{meta['load_average_end'][0]:.1f} at the end, {meta['cores']} cores)", "",
             "| case | vertices | solver | ms/step | vs pcg | Newton/step | linear it./step | host syncs/step |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results:
        ratio = "" if r["ratio_to_pcg"] is None else f"{r['ratio_to_pcg']:.2f}"
        name = r["solver"] + (f" ({r['backend']})" if "backend" in r else "")
        lines.append(f"| {r['case']} | {r['vertices']} | {name} | {r['step_seconds']*1e3:.0f} | {ratio} | "
                     f"{r['newton_per_step']:.1f} | {r['linear_per_step']:.0f} | {r['host_syncs_per_step']:.0f} |")
    Path(args.out + ".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
