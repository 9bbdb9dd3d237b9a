"""A user's scan end to end at the default settings: meshing, then 48 frames of a drop onto a floor
with friction and onto a sphere, as a new user would run it (``warpfem run`` does the same calls).

The scan stand-in is ``kernels_bench/scan_surface.py``'s (the shipped bunny, ``--subdivisions``
midpoint subdivisions: 2 gives 55,730 vertices and 111,456 triangles, about a 43k-vertex scan's
size, with scanner-like noise of ``--noise`` mean edge lengths along the normals). The scene names
the surface file in ``[mesh] path`` and says nothing else about meshing or solving: the default
``target_tets``, integrator, tolerances, linear solver and contact parameters decide. The body
starts 5 cm above a floor plane (friction 0.5) with a fixed sphere (radius 40 % of the body's
height, friction 0.5) under one side, so it lands on both; 48 frames at 48 fps (1 s).

The mesh cache is an empty temporary folder (``WARPFEM_CACHE_DIR``): the surface is meshed as on a
user's first run. Recorded: the wall seconds of meshing (scene load and build), of every frame, and of the whole
job; per frame the Newton iterations, whether every step converged, the worst relative gradient
of a step that did not; the physics mesh's size. The target of this job: the whole of it within
10 minutes on a 2-core CPU with every frame converged (docs/meshing.md, "A scan end to end").

    .venv/bin/python kernels_bench/bench_scan_job.py [--frames 48] [--subdivisions 2] [--noise 0.05]
        [--precision float64] [--integrator KEYS] [--contact KEYS] [--out kernels_bench/results/scan_job]
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

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from kernels_bench.bench_scan import write_obj  # noqa: E402
from kernels_bench.scan_surface import make_scan  # noqa: E402

SCENE = """name = "scan_drop"
gravity = [0.0, -9.81, 0.0]
[mesh]
path = "scan.obj"
[material]
model = "stable_neo_hookean"
youngs_modulus = 5.0e4
poisson_ratio = 0.4
density = 1000.0
[[collider]]
type = "plane"
name = "floor"
point = [0.0, {floor!r}, 0.0]
normal = [0.0, 1.0, 0.0]
friction = 0.5
[[collider]]
type = "sphere"
name = "ball"
center = [{sx!r}, {sy!r}, {sz!r}]
radius = {r!r}
friction = 0.5
[output]
fps = 48
frames = {frames}
{integrator}{contact}"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--subdivisions", type=int, default=2)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--precision", default="float64")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--integrator", default="", help="extra [integrator] keys, TOML (e.g. 'max_iters = 100'); "
                    "default: none, the defaults decide")
    ap.add_argument("--contact", default="", help="extra [contact] keys, TOML (e.g. 'friction_lag_below = 0.1'); "
                    "default: none")
    ap.add_argument("--out", default=str(ROOT / "kernels_bench" / "results" / "scan_job"))
    a = ap.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    from warpfem.scenes import load_scene

    load0 = os.getloadavg()
    V, F, h = make_scan(a.subdivisions, a.noise)
    lo, hi = V.min(axis=0), V.max(axis=0)
    height = float(hi[1] - lo[1])
    r = 0.4 * height
    # the sphere's top 1 cm below the body's lowest point, under its +x side; the floor 5 cm below
    floor = float(lo[1] - 0.05)
    centre = (float(lo[0] + 0.75 * (hi[0] - lo[0])), floor + 0.5 * r, float(0.5 * (lo[2] + hi[2])))
    if centre[1] + r > lo[1] - 0.01:
        centre = (centre[0], float(lo[1] - 0.01 - r), centre[2])
    t_job = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        # an empty mesh cache: the job meshes the surface as a user's first run does
        os.environ["WARPFEM_CACHE_DIR"] = os.path.join(tmp, "cache")
        write_obj(os.path.join(tmp, "scan.obj"), V, F)
        with open(os.path.join(tmp, "scan.toml"), "w") as f:
            f.write(SCENE.format(floor=floor, sx=centre[0], sy=centre[1], sz=centre[2], r=r, frames=a.frames,
                                  integrator=f"[integrator]\n{a.integrator}\n" if a.integrator else "",
                                  contact=f"[contact]\n{a.contact}\n" if a.contact else ""))
        t0 = time.perf_counter()
        scene = load_scene(os.path.join(tmp, "scan.toml"))
        run = scene.build(device=a.device, precision=a.precision)
        mesh_s = time.perf_counter() - t0
        m = run.model.mesh
        print(f"meshed and built in {mesh_s:.1f} s: {m.num_elements:,} tets, {m.num_vertices:,} vertices", flush=True)
        frames = []
        for k in range(a.frames):
            t = time.perf_counter()
            fs = run.step_frame(total_frames=a.frames)
            frames.append(dict(frame=fs.frame, seconds=time.perf_counter() - t, newton=fs.newton_iterations,
                               steps=fs.steps, converged=bool(fs.converged), unconverged_steps=fs.unconverged_steps,
                               worst_residual=fs.worst_residual))
            print(frames[-1], flush=True)
    job_s = time.perf_counter() - t_job
    unconverged = sum(1 for f in frames if not f["converged"])
    meta = dict(device=a.device, cpu=platform.processor() or platform.machine(), cores=os.cpu_count(),
                precision=a.precision, integrator_keys=a.integrator, contact_keys=a.contact, surface_vertices=int(len(V)), surface_triangles=int(len(F)),
                noise=a.noise, subdivisions=a.subdivisions, tets=int(m.num_elements), vertices=int(m.num_vertices),
                mesh_and_build_seconds=mesh_s, job_seconds=job_s, frames=a.frames, unconverged_frames=unconverged,
                newton_per_frame=float(np.mean([f["newton"] for f in frames])),
                load_average_start=load0, load_average_end=os.getloadavg())
    with open(a.out + ".json", "w") as f:
        json.dump(dict(meta=meta, frames=frames), f, indent=1)
    lines = [f"Scan job ({a.precision}, {a.device}, {meta['cpu']}, {meta['cores']} cores; load average "
             f"{load0[0]:.1f} -> {meta['load_average_end'][0]:.1f}): {len(V):,}-vertex surface -> "
             f"{m.num_elements:,} tets in {mesh_s:.1f} s; {a.frames} frames in {job_s - mesh_s:.0f} s; "
             f"whole job {job_s / 60:.1f} min; {unconverged} frames not converged.", "",
             "| frame | s | Newton | steps | converged |", "| ---: | ---: | ---: | ---: | --- |"]
    lines += [f"| {f['frame']} | {f['seconds']:.1f} | {f['newton']} | {f['steps']} | "
              f"{'yes' if f['converged'] else 'no (worst %.1e)' % f['worst_residual']} |" for f in frames]
    text = "\n".join(lines) + "\n"
    with open(a.out + ".md", "w") as f:
        f.write(text)
    print(text)
    return 0 if unconverged == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
