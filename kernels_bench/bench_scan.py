"""A scanned-statue-sized surface through a scene's ``[mesh] path``, at the default settings.

A user measured a 43k-vertex scanned statue surface given as ``[mesh] path``: it became a
71k-vertex simulation mesh, steps took 117-419 s and the third did not converge. The statue is
not in this repository, so this benchmark makes a surface of that size from the bunny
(``examples/meshes/bunny.off``, 3,485 vertices): ``--subdivisions`` midpoint subdivisions of every
triangle (2: 55,730 vertices, 111,456 triangles), then scanner-like noise along the vertex
normals (Gaussian, ``--noise`` times the mean edge length, seeded), written to a temporary folder
with a scene that names it in ``[mesh] path`` and nothing else about meshing: the default
``target_tets`` decides the physics mesh and the surface is embedded as the render surface.

Scene: stable neo-Hookean E = 5e4 Pa, nu = 0.4, rho = 1000, the lowest 10 % of the height fixed,
gravity, backward Euler at dt = 1/24 s (the statue's), float64, the default (auto) linear solver.
Recorded: meshing seconds, the physics and render sizes, per step the seconds, Newton iterations,
whether it converged and its reason, and the step time as a ratio to one Hessian assembly of the
same mesh (fastest of 3, same run).

    .venv/bin/python kernels_bench/bench_scan.py [--steps 6] [--subdivisions 2] [--noise 0.05]
        [--max-edge-length L] [--out PATH]

``--max-edge-length`` meshes at that edge bound instead of the default ``target_tets`` (the old
behaviour: the surface's own resolution).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):  # host BLAS on one thread: the 2 shared cores
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from kernels_bench.scan_surface import make_scan  # noqa: E402


def write_obj(path, V, F):
    with open(path, "w") as f:
        f.write("".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V))
        f.write("".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))


SCENE = """name = "scan"
gravity = [0.0, -9.81, 0.0]
[mesh]
path = "scan.obj"
{mesh_extra}
[material]
model = "stable_neo_hookean"
youngs_modulus = 5.0e4
poisson_ratio = 0.4
density = 1000.0
[[fixed]]
box_min = [-10.0, -10.0, -10.0]
box_max = [10.0, {y_fix!r}, 10.0]
[integrator]
type = "backward_euler"
dt = 0.041666666666666664
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--subdivisions", type=int, default=2)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--max-edge-length", type=float, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=str(ROOT / "kernels_bench" / "results" / "scan"))
    args = ap.parse_args()

    import warp as wp

    wp.config.quiet = True
    from kernels_bench.bench_scale import hessian_seconds
    from warpfem.scenes import load_scene

    load0 = os.getloadavg()
    V, F, h = make_scan(args.subdivisions, args.noise)
    y0, y1 = V[:, 1].min(), V[:, 1].max()
    with tempfile.TemporaryDirectory() as tmp:
        write_obj(os.path.join(tmp, "scan.obj"), V, F)
        extra = f"max_edge_length = {args.max_edge_length!r}" if args.max_edge_length else ""
        with open(os.path.join(tmp, "scan.toml"), "w") as f:
            f.write(SCENE.format(mesh_extra=extra, y_fix=float(y0 + 0.1 * (y1 - y0))))
        t0 = time.perf_counter()
        scene = load_scene(os.path.join(tmp, "scan.toml"))
        run = scene.build(device=args.device, precision="float64")
        build_s = time.perf_counter() - t0
        print("\n".join(scene.describe_lines()) if hasattr(scene, "describe_lines") else "", flush=True)
        sim = run.sim
        mesh = run.model.mesh
        hess = hessian_seconds(sim)
        rows = []
        for k in range(args.steps):
            t = time.perf_counter()
            st = sim.step()
            secs = time.perf_counter() - t
            rows.append(dict(step=k, seconds=secs, step_per_hessian=secs / hess, newton=st.newton_iterations,
                             linear_iterations=getattr(st, "linear_iterations", None),
                             converged=bool(st.converged), reason=st.reason))
            print(rows[-1], flush=True)
        render = getattr(run, "skinner", None)
    meta = dict(device=args.device, cpu=platform.processor() or platform.machine(), cores=os.cpu_count(),
                surface_vertices=int(len(V)), surface_triangles=int(len(F)), mean_edge_m=h, noise=args.noise,
                subdivisions=args.subdivisions, max_edge_length=args.max_edge_length,
                tets=int(mesh.num_elements), vertices=int(mesh.num_vertices), build_seconds=build_s,
                hessian_seconds=hess, embedded_render_surface=render is not None,
                load_average_start=load0, load_average_end=os.getloadavg())
    with open(args.out + ".json", "w") as f:
        json.dump(dict(meta=meta, steps=rows), f, indent=1)
    lines = [f"Synthetic scan: {len(V):,} vertices, {len(F):,} triangles -> {mesh.num_elements:,} tets, "
             f"{mesh.num_vertices:,} vertices (build {build_s:.1f} s, one Hessian {1e3 * hess:.1f} ms); "
             f"load {load0[0]:.1f} -> {meta['load_average_end'][0]:.1f}", "",
             "| step | s | step / Hessian | Newton | converged |", "| ---: | ---: | ---: | ---: | --- |"]
    lines += [f"| {r['step']} | {r['seconds']:.2f} | {r['step_per_hessian']:.0f} | {r['newton']} | "
              f"{r['converged']} ({r['reason']}) |" for r in rows]
    text = "\n".join(lines) + "\n"
    with open(args.out + ".md", "w") as f:
        f.write(text)
    print(text)


if __name__ == "__main__":
    main()
