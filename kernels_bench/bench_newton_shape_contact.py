"""What SolverFEM's ``shape_contact="surface"`` costs against the default colliders (docs/newton.md,
"Shapes as kinematic bodies").

The case: a soft grid (newton ``add_soft_grid``, 6 x 3 x 1 cells of 25 x 33 x 20 mm, k_mu 2e4,
k_lambda 3e4, 300 kg/m^3) dropped from 2 cm across the edge of a static 0.2 x 0.2 x 0.1 m box shape
standing on the ground plane, dt 0.01, damping_mass 5, backward Euler. Both ways are built in this
process and stepped interleaved (one step of each in turn); ``--repeats N`` runs the whole
sequence N times and keeps each step's smallest time. Per way: Newton iterations per step,
seconds per step (the first step, which compiles and sets up, left out) and the steps at whose end
the grid's surface intersects the box's (IPC Toolkit, ``ipctk``, when installed).

    .venv/bin/python kernels_bench/bench_newton_shape_contact.py [--steps 30] [--repeats 1] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402

WAYS = ("collider", "surface")


def build():
    import newton

    b = newton.ModelBuilder()
    b.add_ground_plane()
    b.add_shape_box(-1, xform=wp.transform(wp.vec3(0.0, 0.0, 0.05), wp.quat_identity()), hx=0.1, hy=0.1, hz=0.05)
    b.add_soft_grid(pos=wp.vec3(0.03, -0.05, 0.12), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                    dim_x=6, dim_y=3, dim_z=1, cell_x=0.025, cell_y=0.033, cell_z=0.02,
                    density=300.0, k_mu=2.0e4, k_lambda=3.0e4, k_damp=0.0)
    return b.finalize(device="cpu")


def run(steps, repeats):
    from warpfem.interop.newton import SolverFEM

    try:
        import ipctk
    except ImportError:
        ipctk = None
    times = {w: np.full(steps, np.inf) for w in WAYS}
    out = {}
    for _ in range(repeats):
        runs = {}
        for w in WAYS:
            model = build()
            runs[w] = dict(model=model, solver=SolverFEM(model, damping_mass=5.0, shape_contact=w),
                           s=[model.state(), model.state()], its=[], bad=[])
        Vb, Fb = wf.Box(box_min=(-0.1, -0.1, 0.0), box_max=(0.1, 0.1, 0.1)).surface(1.0)
        model = runs["collider"]["model"]
        q0 = model.particle_q.numpy().astype(np.float64)
        Fs = np.asarray(wf.TetMesh(q0, model.tet_indices.numpy()).boundary_faces())
        F = np.vstack([Fs, Fb + len(q0)])
        cm = None if ipctk is None else ipctk.CollisionMesh(np.vstack([q0, Vb]), ipctk.edges(F), F)
        for i in range(steps):
            for w in WAYS:
                r = runs[w]
                s0, s1 = r["s"]
                s0.clear_forces()
                t0 = time.perf_counter()
                r["solver"].step(s0, s1, r["model"].control(), None, 0.01)
                times[w][i] = min(times[w][i], time.perf_counter() - t0)
                r["s"] = [s1, s0]
                r["its"].append(int(r["solver"].last_stats.newton_iterations))
                q = s1.particle_q.numpy().astype(np.float64)
                if cm is not None and ipctk.has_intersections(cm, np.asfortranarray(np.vstack([q, Vb]))):
                    r["bad"].append(i)
        for w in WAYS:
            r = runs[w]
            out[w] = {"newton_iterations_per_step": float(np.mean(r["its"])),
                      "intersecting_steps": None if cm is None else len(r["bad"]),
                      "first_intersecting_step": (r["bad"][0] if r["bad"] else None) if cm is not None else None}
    for w in WAYS:
        out[w]["seconds_per_step"] = float(np.mean(times[w][1:]))
    out["time_ratio_surface_to_collider"] = out["surface"]["seconds_per_step"] / out["collider"]["seconds_per_step"]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    res = {"case": "soft grid dropped across a static box's edge (newton SolverFEM)", "steps": a.steps,
           "repeats": a.repeats, "device": "cpu", "machine": platform.machine(), "processor": platform.processor(),
           "results": run(a.steps, a.repeats)}
    print(json.dumps(res, indent=1))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    main()
