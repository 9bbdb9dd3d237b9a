"""How coarse may the physics mesh under a render surface be? Error against cost of ``target_tets``.

A surface file given as ``[mesh] path`` is meshed with at most ``target_tets`` tets (the surface is
decimated for the physics mesh, TetGen fills it) and the input surface is embedded as the render
surface. This benchmark runs the same scene at several ``target_tets`` and measures, on the
*render surface* (what a user sees):

* error: RMS over the surface's vertices and the steps of |x - x_ref|, relative to the RMS
  displacement of the reference, x_ref from the finest mesh of the run (the bunny's own
  resolution, 35,870 tets, when the largest target exceeds it); and the same at the last step
  (with mass damping the bunny is then near its static sag, less sensitive to the phase of the
  transient);
* cost: median seconds per step, and its ratio to the finest mesh's step (same run, same machine).

Scene: ``examples/meshes/bunny.off`` (3,485 vertices, 6,966 triangles), stable neo-Hookean
E = 5e4 Pa, nu = 0.4, rho = 1000 kg/m^3, the lowest 10 % of its height fixed, gravity, backward
Euler at dt = 1/30 s with mass damping 10 1/s (``--damping``), from rest; the auto linear solver.

    .venv/bin/python kernels_bench/bench_target_tets.py [--targets 2500 5000 ...] [--steps 15]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def run(target, steps, surface_path, device, damping, dt):
    import warpfem as wf
    from warpfem.mesh import load_mesh
    from warpfem.mesh.tetrahedralization import read_surface
    from warpfem.skinning import embed_points_in_mesh

    t0 = time.perf_counter()
    mesh = load_mesh(surface_path, target_tets=target, cache=False)
    mesh_s = time.perf_counter() - t0
    SV, _ = read_surface(surface_path)
    emb = embed_points_in_mesh(SV, mesh)
    W = emb.matrix()
    X = mesh.vertices
    y0, y1 = X[:, 1].min(), X[:, 1].max()
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=5e4, poisson_ratio=0.4, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.flatnonzero(X[:, 1] <= y0 + 0.1 * (y1 - y0)))
    sim = wf.Simulator(model, device=device, precision="float64", dt=dt, damping_mass=damping)
    sim.step()  # compiles kernels and factorises once outside the timing
    sim.set_positions(X)
    sim.set_velocities(np.zeros_like(X))
    frames, secs, newton = [], [], 0
    for _ in range(steps):
        t = time.perf_counter()
        st = sim.step()
        secs.append(time.perf_counter() - t)
        newton += st.newton_iterations
        frames.append(W @ sim.positions())
    return dict(target_tets=target, tets=mesh.num_elements, vertices=mesh.num_vertices,
                simulation_surface_faces=mesh.tetrahedralization.extra.get("simulation_surface_faces"),
                render_outside=int(emb.num_outside), render_max_outside=float(emb.max_outside_distance),
                mesh_seconds=mesh_s, step_seconds_median=float(np.median(secs)),
                newton_per_step=newton / steps, frames=np.array(frames), rest=SV)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", type=int, nargs="+", default=[2500, 5000, 10000, 20000, 30000, 60000])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--dt", type=float, default=1.0 / 30.0)
    ap.add_argument("--damping", type=float, default=10.0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=os.path.join(ROOT, "kernels_bench", "results", "target_tets"))
    args = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    surface = os.path.join(ROOT, "examples", "meshes", "bunny.off")
    rows = [run(t, args.steps, surface, args.device, args.damping, args.dt) for t in sorted(args.targets)]
    ref = rows[-1]
    disp = ref["frames"] - ref["rest"][None]
    scale = float(np.sqrt(np.mean(np.sum(disp ** 2, axis=2))))
    out = []
    for r in rows:
        err = float(np.sqrt(np.mean(np.sum((r["frames"] - ref["frames"]) ** 2, axis=2)))) / scale
        last = ref["frames"][-1] - ref["rest"]
        err_last = float(np.sqrt(np.mean(np.sum((r["frames"][-1] - ref["frames"][-1]) ** 2, axis=1)))
                         / np.sqrt(np.mean(np.sum(last ** 2, axis=1))))
        out.append({k: v for k, v in r.items() if k not in ("frames", "rest")} |
                   dict(error_vs_finest=err, last_step_error_vs_finest=err_last,
                        cost_vs_finest=r["step_seconds_median"] / ref["step_seconds_median"]))
    meta = dict(device=args.device, cpu=platform.processor() or platform.machine(), cores=os.cpu_count(),
                steps=args.steps, dt=args.dt, damping_mass=args.damping, surface="examples/meshes/bunny.off", reference_tets=ref["tets"],
                rms_displacement_of_reference_m=scale,
                load_average=os.getloadavg() if hasattr(os, "getloadavg") else None)
    with open(args.out + ".json", "w") as f:
        json.dump(dict(meta=meta, rows=out), f, indent=1)
    lines = ["| target_tets | tets | vertices | physics surface triangles | render vertices outside | s / step | x finest "
             "| trajectory error vs finest | last-step error vs finest |",
             "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in out:
        lines.append(f"| {r['target_tets']} | {r['tets']} | {r['vertices']} | {r['simulation_surface_faces']} | "
                     f"{r['render_outside']} (max {r['render_max_outside'] * 1e3:.2f} mm) | {r['step_seconds_median']:.3f} | "
                     f"{r['cost_vs_finest']:.3f} | {100 * r['error_vs_finest']:.2f} % | "
                     f"{100 * r['last_step_error_vs_finest']:.2f} % |")
    from kernels_bench.report import write_markdown

    write_markdown(args.out + ".md", lines, meta)


if __name__ == "__main__":
    main()
