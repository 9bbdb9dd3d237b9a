"""Cost of the adjoint (reverse pass) of implicit steps against the forward steps, in the same run.

The 480-tet cantilever (examples/scenes/cantilever.toml: 189 vertices, stable neo-Hookean, gravity)
is stepped ``--steps`` times with a gradient recording (:class:`warpfem.solvers.adjoint.Recording`),
then the reverse pass of a loss on every state's positions runs. Reported per linear solver
(direct: the forward's factorisation reused by the refinement; pcg) and integrator: forward ms per
step (with the recording, and without it in a second run), backward ms per step, their ratio,
adjoint refinements and re-preparations per step (the fastest of ``--repeats`` runs of each: the
machine's load only adds time), and host memory per recorded step (the vectors,
and the factorisations the direct solver keeps for the reverse pass within ``--budgets`` MiB;
0 = none kept, the reverse pass refines on the solver's last factorisation or refactorises).

    .venv/bin/python kernels_bench/bench_adjoint.py [--steps 20] [--device cpu] [--tol 1e-8] [--budgets 1024 0] [--repeats 3]
        [--adjoint-tol 1e-12] [--json out.json]
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

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
SCENE = os.path.join(ROOT, "examples", "scenes", "cantilever.toml")


def measure(solver: str, integrator: str, steps: int, device: str, tol: float, dt: float = 1.0 / 48.0,
            cells=None, factor_budget=None, repeats: int = 1, adjoint_tol=None) -> dict:
    import numpy as np
    import warp as wp

    wp.config.quiet = True
    import warpfem as wf
    from warpfem.scenes import load_scene
    from warpfem.solvers.adjoint import Recording

    scene = load_scene(SCENE)
    if cells is not None:  # a finer cantilever (the scene's is 20 x 2 x 2 cells)
        scene.spec.mesh["cells"] = list(cells)
    model = scene.build(device=device, precision="float64").model

    def make():
        opts = {"linear_solver": solver, "tol": tol, "max_iters": 50}
        if solver == "pcg":
            opts.update(cg_tol=1e-6, max_cg_iters=5000)
        return wf.Simulator(model, device=device, dt=dt, integrator=integrator, **opts)

    # without recording (the plain forward), then with it, same settings; each ``repeats`` times,
    # the fastest of each kept (a shared machine's load only ever adds time)
    plain = fwd = bwd = np.inf
    ratios = []
    for _ in range(repeats):
        sim = make()
        sim.step()  # warm-up (kernels loaded, solver analysed)
        t = time.perf_counter()
        for _ in range(steps):
            sim.step()
        plain = min(plain, (time.perf_counter() - t) / steps)
        sim = make()
        sim.step()
        rec = Recording(sim, params=("youngs_modulus", "poisson_ratio", "density", "forces"), factor_budget=factor_budget,
                        tol=adjoint_tol)
        newton = 0
        t = time.perf_counter()
        with rec:
            for _ in range(steps):
                newton += sim.step().newton_iterations
        f = (time.perf_counter() - t) / steps
        rng = np.random.default_rng(0)
        xg = {k: rng.standard_normal((sim.num_vertices, 3)) for k in range(steps + 1)}
        adj = rec.adjoint
        r0, p0, k0 = adj.refinements, adj.prepares, adj.kept_solves
        t = time.perf_counter()
        g = rec.backward(xg)
        b = (time.perf_counter() - t) / steps
        assert np.isfinite(g["youngs_modulus"])
        fwd, bwd = min(fwd, f), min(bwd, b)
        ratios.append(b / f)
        kept_bytes = rec.factor_nbytes
        parts = _breakdown(rec, sim, np) if solver == "direct" and rec.records[-1].factor is not None else None
        rec.release()
    return {"solver": solver, "integrator": integrator, "steps": steps, "newton_tol": tol,
            "newton_iterations_per_step": newton / steps, "forward_ms": 1e3 * plain, "forward_recorded_ms": 1e3 * fwd,
            "backward_ms": 1e3 * bwd, "ratio": bwd / fwd, "ratio_to_plain": bwd / plain,
            "repeats": repeats, "ratio_per_repeat": ratios, "adjoint_tol": adj.tol,
            "refinements_per_step": (adj.refinements - r0) / steps, "prepares_per_step": (adj.prepares - p0) / steps,
            "bytes_per_step": rec.nbytes / steps, "factor_bytes_per_step": kept_bytes / steps,
            "kept_solves_per_step": (adj.kept_solves - k0) / steps,
            "factor_budget": adj.factor_budget if solver == "direct" else None,
            "backend": getattr(sim.linear_solver, "backend_name", None), "vertices": sim.num_vertices, "dt": dt,
            "breakdown_ms": parts}


def _breakdown(rec, sim, np, reps: int = 20) -> dict:
    """ms of each device and solver stage of one reverse step (the last recorded one), each timed
    alone ``reps`` times, fastest kept: the exact Hessian's assembly, one triangular solve pair
    with the kept factor, one product with the host H, the parameter-work launch (E / nu / element
    gradients). Their sum with the measured refinement count is the floor of a reverse step
    without any Python or host vector algebra."""
    adj, r = rec.adjoint, rec.records[-1]
    w = np.random.default_rng(1).standard_normal((sim.num_vertices, 3))

    def best(f):
        f()
        t = np.inf
        for _ in range(reps):
            t0 = time.perf_counter()
            f()
            t = min(t, time.perf_counter() - t0)
        return 1e3 * t

    x_dev = adj._assemble_K(r.x_next)
    H = adj._host_H(adj._K, 1.0, r.s * r.s)
    b = w.reshape(-1)
    return {"assembly": best(lambda: adj._assemble_K(r.x_next)), "kept_solve": best(lambda: r.factor.solve(b)),
            "host_product": best(lambda: H @ b), "host_matrix": best(lambda: adj._host_H(adj._K, 1.0, r.s * r.s)),
            "parameter_work": best(lambda: adj._parameter_work(x_dev, w, False))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--tol", type=float, default=1e-8, help="Newton tolerance of the forward steps")
    ap.add_argument("--solvers", nargs="+", default=["direct", "pcg"])
    ap.add_argument("--integrators", nargs="+", default=["backward_euler", "bdf2", "newmark"])
    ap.add_argument("--dt", type=float, default=1.0 / 48.0, help="time step (s); the scene's is 1/48")
    ap.add_argument("--cells", nargs=3, type=int, help="mesh cells of the cantilever (default the scene's 20 2 2)")
    ap.add_argument("--budgets", nargs="+", type=float, default=[1024.0, 0.0],
                    help="factor_budget values (MiB) to measure with the direct solver (0: refactorise)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="runs of each case; the fastest forward and backward are reported (ratio: theirs)")
    ap.add_argument("--adjoint-tol", type=float, help="the adjoint solve's relative residual (default: default_adjoint_tol)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = []
    for s in args.solvers:
        for i in args.integrators:
            for b in (args.budgets if s == "direct" else [0.0]):
                rows.append(measure(s, i, args.steps, args.device, args.tol, args.dt, args.cells,
                                    factor_budget=int(b * 2**20), repeats=args.repeats,
                                    adjoint_tol=args.adjoint_tol))
    machine = f"{platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}"
    r0 = rows[0]
    print(f"cantilever ({r0['vertices']} vertices), {args.steps} steps of {args.dt:.4g} s, Newton tol {args.tol:g}, "
          f"adjoint tol {r0['adjoint_tol']:g}, fastest of {args.repeats} runs, device {args.device} ({machine})")
    print("| solver | factor_budget MiB | integrator | Newton it./step | forward ms/step (recorded / plain) | "
          "backward ms/step | backward / forward | kept solves / refinements / prepares per step | "
          "KiB per recorded step (vectors + factor) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        fb = "-" if r["factor_budget"] is None else f"{r['factor_budget'] / 2**20:g}"
        print(f"| {r['solver']} | {fb} | {r['integrator']} | {r['newton_iterations_per_step']:.1f} | "
              f"{r['forward_recorded_ms']:.1f} / {r['forward_ms']:.1f} | {r['backward_ms']:.2f} | {r['ratio']:.3f} | "
              f"{r['kept_solves_per_step']:.2f} / {r['refinements_per_step']:.1f} / {r['prepares_per_step']:.2f} | "
              f"{r['bytes_per_step'] / 1024:.1f} + {r['factor_bytes_per_step'] / 1024:.1f} |")
    parts = [r for r in rows if r["breakdown_ms"]]
    if parts:
        print("\nStages of one reverse step (direct, kept factor; each timed alone, fastest of 20), ms and / forward ms; "
              "floor = assembly + refinements x (solve + product) + parameter work")
        print("| integrator | assembly | kept solve | product with H | parameter work | host H | floor / forward | measured / forward |")
        print("|---|---|---|---|---|---|---|---|")
        for r in parts:
            b, f = r["breakdown_ms"], r["forward_recorded_ms"]
            floor = b["assembly"] + r["refinements_per_step"] * (b["kept_solve"] + b["host_product"]) + b["parameter_work"]
            r["floor_ratio"] = floor / f
            print(f"| {r['integrator']} | {b['assembly']:.3f} | {b['kept_solve']:.3f} | {b['host_product']:.3f} | "
                  f"{b['parameter_work']:.3f} | {b['host_matrix']:.3f} | {floor / f:.3f} | {r['ratio']:.3f} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": machine, "device": args.device, "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
