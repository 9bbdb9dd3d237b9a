"""What a rigid (affine) body costs against a soft one of the same mesh, and the share of a step
spent in the map E between the unknown and the vertices (docs/rigid.md).

Cases (each run once rigid, once soft, in this process, one after the other; ``--repeats N`` keeps
each step's smallest time over N interleaved runs):

  cube_incline  a 0.1 m cube (``--cells`` per side, default 4: 125 vertices, 384 tets) dropped from
                1 cm onto a 30 degree incline (friction 0.5), dt 0.01, backward Euler; soft: stable
                neo-Hookean E 1e7, nu 0.3; both 1000 kg/m^3
  ball_slab     a ball (icosphere, 2 subdivisions) of radius 5 cm dropped 2 mm onto a soft slab (0.3 x
                0.04 x 0.3 m, 6 x 1 x 6 cells, E 1e5) on a floor, surface contact, damped (alpha 10);
                soft ball: the icosphere's volume tetrahedralised as a fan around its centre

Per case and kind: Newton iterations per step, seconds per step (the first step, which compiles and
sets up, left out), and for the rigid runs the seconds in the map's passes (E q, E^T g, the Hessian
map; timed around the launches with the device synchronised) as a fraction of the step time.

    .venv/bin/python kernels_bench/bench_rigid.py [--steps 30] [--repeats 1] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402
from warpfem.mesh import TetMesh  # noqa: E402
from warpfem.mesh.box import icosphere_surface  # noqa: E402
from warpfem.rigid.embedding import RigidSystem  # noqa: E402

G = 9.81
MAP_TIME = {"s": 0.0}


def _timed(fn):
    def wrapper(*a, **kw):
        wp.synchronize()
        t0 = time.perf_counter()
        out = fn(*a, **kw)
        wp.synchronize()
        MAP_TIME["s"] += time.perf_counter() - t0
        return out
    return wrapper


for _name in ("embed", "gather", "map_hessian"):
    setattr(RigidSystem, _name, _timed(getattr(RigidSystem, _name)))


def cube_incline(rigid, cells):
    theta = math.radians(30.0)
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    box = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(cells,) * 3, origin=(-0.05, 0.01, -0.05))
    mesh = TetMesh(np.asarray(box.vertices) @ R.T, box.tets)
    if rigid:
        model = wf.Model.from_bodies([wf.RigidBody(mesh, density=1000.0, name="cube")], gravity=(0, -G, 0))
    else:
        mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e7, poisson_ratio=0.3, density=1000.0)
        model = wf.Model.from_bodies([wf.Body(mesh, mat, name="cube")], gravity=(0, -G, 0))
    sim = wf.Simulator(model, dt=0.01, colliders=[wf.Plane(point=(0, 0, 0), normal=R[:, 1], friction=0.5)])
    return sim


def _ball_tets(radius):
    V, F = icosphere_surface(radius, 2)
    X = np.vstack([V, np.zeros((1, 3))])
    tets = np.hstack([F[:, [0, 2, 1]], np.full((len(F), 1), len(V))])
    return TetMesh(X, tets)


def ball_slab(rigid, cells):
    slab = wf.Body(wf.box_tet_mesh(size=(0.3, 0.04, 0.3), cells=(6, 1, 6), origin=(-0.15, 0.001, -0.15)),
                   wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=500.0),
                   name="slab")
    off = (0.0, 0.093, 0.0)
    if rigid:
        ball = wf.RigidBody(icosphere_surface(0.05, 2), density=1000.0, name="ball", offset=off)
    else:
        ball = wf.Body(_ball_tets(0.05), wf.make_material("stable_neo_hookean", youngs_modulus=1e7, poisson_ratio=0.3,
                                                           density=1000.0), name="ball", offset=off)
    m = wf.Model.from_bodies([slab, ball], gravity=(0, -G, 0))
    sim = wf.Simulator(m, dt=0.01, damping_mass=10.0, colliders=[wf.Plane(point=(0, 0, 0), normal=(0, 1, 0))])
    sim.set_contact(bodies=True)
    return sim


CASES = {"cube_incline": cube_incline, "ball_slab": ball_slab}


def run(case, rigid, steps, cells):
    sim = CASES[case](rigid, cells)
    its, secs, maps = [], [], []
    for _ in range(steps):
        MAP_TIME["s"] = 0.0
        t0 = time.perf_counter()
        st = sim.step()
        secs.append(time.perf_counter() - t0)
        maps.append(MAP_TIME["s"])
        its.append(st.newton_iterations)
    return np.array(its), np.array(secs), np.array(maps)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--cells", type=int, default=4)
    ap.add_argument("--case", action="append", choices=sorted(CASES))
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    cases = a.case or list(CASES)
    env = {"machine": platform.machine(), "processor": platform.processor(), "cpus": os.cpu_count(),
           "load": round(os.getloadavg()[0], 2), "device": "cpu", "steps": a.steps, "repeats": a.repeats}
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {env['load']}, "
          f"{a.steps} steps, best of {a.repeats}")
    print(f"{'case':13s} {'kind':6s} {'newton/step':>11s} {'s/step':>8s} {'map share':>9s}")
    out = {"environment": env, "results": []}
    for case in cases:
        best = {}
        for _ in range(a.repeats):
            for rigid in (True, False):
                its, secs, maps = run(case, rigid, a.steps, a.cells)
                b = best.get(rigid)
                best[rigid] = (its, secs, maps) if b is None else (its, np.minimum(b[1], secs), np.minimum(b[2], maps))
        for rigid in (True, False):
            its, secs, maps = best[rigid]
            share = float(maps[1:].sum() / secs[1:].sum()) if rigid else 0.0
            kind = "rigid" if rigid else "soft"
            print(f"{case:13s} {kind:6s} {its.mean():11.2f} {secs[1:].mean():8.4f} {share:9.3f}", flush=True)
            out["results"].append({"case": case, "kind": kind, "newton_per_step": float(its.mean()),
                                   "seconds_per_step": float(secs[1:].mean()), "map_share": share})
        r, s = out["results"][-2], out["results"][-1]
        print(f"{case:13s} rigid/soft: time {r['seconds_per_step'] / s['seconds_per_step']:.2f}, "
              f"Newton iterations {r['newton_per_step'] / s['newton_per_step']:.2f}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
