"""Step time against mesh size for each linear solver: boxes of increasing size and the bunny.

Cases: the clamped box 2 x 0.5 x 0.5 m (stable neo-Hookean, E 1e5, density 1000,
gravity, backward Euler, dt 1/60, 4c x c x c hex cells of 6 tets: c = 8, 13, 16, 25 give 12k,
53k, 98k, 375k tets), at poisson_ratio 0.3 and 0.49, and the bunny scene
(examples/scenes/bunny.toml, 22.9k tets, its own nu 0.4 and dt 1/24) and the octopus scene
(``--octopus``, examples/scenes/octopus.toml, 1.1k tets, nu 0.35) and ``--bunny-fine`` (bunny.off
meshed at max_edge_length 0.004, ~190k tets, dt 1/24). ``multigrid@NAME`` runs the multigrid with
the options MG_VARIANTS[NAME] (``legacy``: the defaults before the spectral estimate). For every (case, solver):
build the simulator, one warm-up step (kernel loads, the solver's set-up: a factorisation's
symbolic analysis, the multigrid hierarchy), then ``--steps`` timed steps. Recorded per step: wall
seconds, Newton iterations, linear iterations per Newton solve (CG iterations; 1 per direct solve),
and the step time as a ratio to one Hessian assembly of the same mesh (elastic Hessian into the
block pattern, fastest of 3), measured in the same run. Per solver and Poisson ratio, the slope of
log(step time) against log(tets) over the box sizes is fitted.

The device and the load average at start and end are recorded: on a shared machine compare
ratios, not absolutes.

    .venv/bin/python kernels_bench/bench_scale.py [--quick] [--sizes 8 13 16] [--nus 0.3 0.49]
        [--solvers pcg amg multigrid multigrid@legacy direct auto] [--bunny] [--octopus] [--steps 2] [--device cpu] [--out PATH]

``--quick``: boxes c = 8 and 13 only, one timed step.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):  # host BLAS on one thread: the 2 shared cores
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402
from kernels_bench.bench_linear_solvers import step_recorder  # noqa: E402


#: ``--solvers multigrid@NAME``: the multigrid with these options (compared in the same run)
MG_VARIANTS = {
    # the defaults before the spectral estimate and the block-weighted prolongation smoothing
    "legacy": dict(upper=1.0, smooth=("jacobi", {"omega": 4.0 / 3.0})),
    "coarse6": dict(degree=(3, 6)),  # degree 6 below the finest level
    "coarse4": dict(degree=(3, 4)),
    "degree4": dict(degree=4),
    "estfine": dict(estimate_finest=True),  # the finest level's interval estimated too
    "mp32": dict(preconditioner_precision="float32"),  # float32 V-cycle inside the float64 CG
    "mpsame": dict(preconditioner_precision="same"),  # the V-cycle in the solver's precision
}


def solver_and_options(solver):
    """'multigrid@NAME' -> ('multigrid', MG_VARIANTS[NAME]); any other name -> (name, None)."""
    if "@" not in solver:
        return solver, None
    name, variant = solver.split("@", 1)
    return name, dict(MG_VARIANTS[variant])


def box_sim(c, *, nu, solver, device, precision):
    cells = (4 * c, c, c)
    mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=cells)
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=nu, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    solver, options = solver_and_options(solver)
    return wf.Simulator(model, device=device, dt=1.0 / 60.0, linear_solver=solver, linear_solver_options=options,
                        precision=precision), 6 * int(np.prod(cells))


_FINE_MESH = {}


def bunny_fine_sim(*, solver, device, precision):
    """examples/meshes/bunny.off tetrahedralised at max_edge_length 0.004 (TetGen: ~190k tets, a
    scanned-statue-sized mesh; meshed once per run), E 5e4, nu 0.4, base fixed, dt 1/24 (as
    kernels_bench/bench_projection.py's ``bunny_fine``)."""
    if "mesh" not in _FINE_MESH:
        _FINE_MESH["mesh"] = wf.load_mesh(ROOT / "examples" / "meshes" / "bunny.off", max_edge_length=0.004)
    mesh = _FINE_MESH["mesh"]
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=5e4, poisson_ratio=0.4, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1, 0.038, 1)))
    solver, options = solver_and_options(solver)
    return wf.Simulator(model, device=device, dt=1.0 / 24.0, linear_solver=solver, linear_solver_options=options,
                        precision=precision), mesh.num_elements


def scene_sim(name, *, solver, device, precision):
    from warpfem.scenes import load_scene

    solver, options = solver_and_options(solver)
    scene = load_scene(ROOT / "examples" / "scenes" / f"{name}.toml")
    scene.spec.integrator["linear_solver"] = solver
    run = scene.build(device=device, precision=precision)
    if options is not None:  # the variant in place of the scene's solver (before its first step)
        from warpfem.solvers.linear import make_linear_solver

        sim = run.sim
        sim.linear_solver = make_linear_solver(solver, sim.pattern, vec_type=sim.vector_type, scalar=sim.scalar_type,
                                               positions=sim.model.mesh.vertices, **options)
    return run, run.model.mesh.num_elements


def hessian_seconds(sim, repeats=3):
    vals = sim.new_matrix_values()
    sim.assemble_stiffness(values=vals)  # warm
    wp.synchronize_device(sim.device)
    best = float("inf")
    for _ in range(repeats):
        vals.zero_()
        t0 = time.perf_counter()
        sim.assemble_stiffness(values=vals)
        wp.synchronize_device(sim.device)
        best = min(best, time.perf_counter() - t0)
    return best


def run_one(make, steps):
    t0 = time.perf_counter()
    obj, tets = make()
    build = time.perf_counter() - t0
    sim = obj.sim if hasattr(obj, "sim") else obj
    advance, records = step_recorder(obj, sim)
    rows = []
    for k in range(steps + 1):
        records.clear()
        t0 = time.perf_counter()
        advance()
        wp.synchronize_device(sim.device)
        secs = time.perf_counter() - t0
        for st in records:
            rows.append(dict(seconds=secs / len(records), newton=st.newton_iterations, linear=st.linear_iterations,
                             converged=bool(st.converged), warmup=k == 0))
    timed = [r for r in rows if not r["warmup"]]
    newton = float(np.sum([r["newton"] for r in timed]))
    ls = sim.linear_solver
    levels = [lv.size for lv in ls.levels] if getattr(ls, "levels", None) else None
    return sim, tets, dict(levels=levels, intervals=getattr(ls, "intervals", None),
        solver=ls.name, chose=getattr(ls, "active", None), auto_costs=getattr(ls, "costs", None),
        auto_explorations=getattr(ls, "explorations", None), vertices=sim.num_vertices, tets=tets, build_seconds=build,
        warmup_seconds=float(sum(r["seconds"] for r in rows if r["warmup"])),
        step_seconds=float(np.mean([r["seconds"] for r in timed])),
        newton_per_step=newton / len(timed),
        linear_per_newton=float(np.sum([r["linear"] for r in timed])) / max(newton, 1.0),
        all_converged=all(r["converged"] for r in rows), steps=len(timed))


def slope(points):
    """Least-squares slope of log(seconds) against log(tets)."""
    if len(points) < 2:
        return None
    x, y = np.log([p[0] for p in points]), np.log([p[1] for p in points])
    return float(np.polyfit(x, y, 1)[0])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="boxes c = 8, 13 and one timed step")
    p.add_argument("--sizes", type=int, nargs="*", default=None, help="box cells c (4c x c x c); default 8 13 16; none: no boxes")
    p.add_argument("--nus", type=float, nargs="+", default=[0.3, 0.49])
    p.add_argument("--solvers", nargs="+", default=["pcg", "amg", "multigrid", "direct", "auto"])
    p.add_argument("--skip", nargs="*", default=[], help="solver:c pairs not to run (e.g. direct:25)")
    p.add_argument("--bunny", action="store_true", help="also the bunny scene")
    p.add_argument("--octopus", action="store_true", help="also the octopus scene")
    p.add_argument("--bunny-fine", action="store_true", help="also bunny.off meshed at max_edge_length 0.004 (~190k tets)")
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--device", default="cpu")
    p.add_argument("--precision", default="float64")
    p.add_argument("--out", default=str(ROOT / "kernels_bench" / "results" / "scale"))
    args = p.parse_args(argv)
    sizes = args.sizes if args.sizes is not None else ([8, 13] if args.quick else [8, 13, 16])
    steps = args.steps or (1 if args.quick else 2)
    wp.config.quiet = True
    wp.init()
    dev = wp.get_device(args.device)
    device_name = dev.name if dev.is_cuda else f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} logical cores)"
    load_start = os.getloadavg()
    results = []

    def record(case, nu, make_for):
        hess = None
        for solver in args.solvers:
            if f"{solver}:{case}" in args.skip:
                continue
            sim, tets, r = run_one(lambda s=solver: make_for(s), steps)
            if "@" in solver:
                r["solver"] = solver
            if hess is None:
                hess = hessian_seconds(sim)
            r.update(case=case, nu=nu, hessian_seconds=hess, step_per_hessian=r["step_seconds"] / hess,
                     load=os.getloadavg()[0])
            results.append(r)
            print(f"{case:>6} nu={nu} {r['solver'] + (':' + r['chose'] if r.get('chose') else ''):9s} tets {tets:7d}  {r['step_seconds']:7.2f} s/step "
                  f"({r['step_per_hessian']:6.0f} Hessians)  Newton {r['newton_per_step']:4.1f}  "
                  f"CG/Newton {r['linear_per_newton']:6.1f}  converged {r['all_converged']}  load {r['load']:.1f}  levels {r['levels']}",
                  flush=True)
            del sim

    for nu in args.nus:
        for c in sizes:
            record(str(c), nu, lambda s, c=c, nu=nu: box_sim(c, nu=nu, solver=s, device=args.device,
                                                             precision=args.precision))
    if args.bunny:
        record("bunny", 0.4, lambda s: scene_sim("bunny", solver=s, device=args.device, precision=args.precision))
    if args.octopus:
        record("octopus", 0.35, lambda s: scene_sim("octopus", solver=s, device=args.device, precision=args.precision))
    if args.bunny_fine:
        record("bunny_fine", 0.4, lambda s: bunny_fine_sim(solver=s, device=args.device, precision=args.precision))

    slopes = {}
    for solver in args.solvers:
        for nu in args.nus:
            pts = [(r["tets"], r["step_seconds"]) for r in results
                   if r["solver"] == solver and r["nu"] == nu and r["case"] not in ("bunny", "octopus", "bunny_fine")]
            slopes[f"{solver} nu={nu}"] = slope(pts)
    meta = dict(device=device_name, warp=wp.__version__, precision=args.precision, steps=steps, sizes=sizes,
                load_average_start=load_start, load_average_end=os.getloadavg(), cores=os.cpu_count())
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(dict(meta=meta, results=results, slopes=slopes), indent=1))
    lines = [f"# Step time against mesh size ({device_name}, {args.precision}; load average "
             f"{load_start[0]:.1f} at the start, {meta['load_average_end'][0]:.1f} at the end, {meta['cores']} cores)",
             "", "| case | nu | tets | solver | s/step | step / Hessian assembly | Newton/step | CG it./Newton solve | converged |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        name = r["solver"] + (f" ({r['chose']})" if r.get("chose") else "")
        lines.append(f"| {r['case'] if r['case'] in ('bunny', 'octopus', 'bunny_fine') else 'box'} | {r['nu']} | {r['tets']} | {name} | "
                     f"{r['step_seconds']:.2f} | {r['step_per_hessian']:.0f} | {r['newton_per_step']:.1f} | "
                     f"{r['linear_per_newton']:.1f} | {r['all_converged']} |")
    lines += ["", "| solver | slope of log(s/step) vs log(tets), boxes |", "|---|---|"]
    lines += [f"| {k} | {'' if v is None else f'{v:.2f}'} |" for k, v in slopes.items()]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
