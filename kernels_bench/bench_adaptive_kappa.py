"""Adaptive against fixed barrier stiffness: Newton iterations and seconds per step on the example
contact scenes and a collider drop (docs/contact.md, "Adaptive barrier stiffness").

Cases (short runs, each from the scene's start; the counts are those of the steps in contact):

* ``stack``: examples/scenes/stack.toml (two cubes on a floor, the upper one dropped 15 cm);
* ``ball_bowl``: examples/scenes/ball_bowl.toml (a soft ball dropped into a soft bowl);
* ``twisted_bar``: examples/scenes/twisted_bar.toml (self contact as the bar coils);
* ``collider_drop``: a 0.1 m soft box (E 1e5, 6^3 cells) placed 0.5 mm above a floor collider
  with friction 0.3, moving down at 1.4 m/s (the speed of a 10 cm fall), Newmark, h = 1/240 s.

``--mode fixed`` runs the scenes as they are (no ``stiffness`` given: the fixed default,
``default_stiffness``: E x mean surface edge, converted for the squared-distance barrier);
``--mode auto`` sets every barrier's stiffness to ``"auto"`` (adaptive, warpfem.contact.stiffness). Every frame is checked with
IPC Toolkit (``ipctk.has_intersections``).

    .venv/bin/python kernels_bench/bench_adaptive_kappa.py --mode auto --case stack --frames 12 --json PATH
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

import warpfem as wf  # noqa: E402
from warpfem.scenes import load_scene  # noqa: E402

SCENES = {"stack": "stack.toml", "ball_bowl": "ball_bowl.toml", "twisted_bar": "twisted_bar.toml"}


def _collision_mesh(model):
    import ipctk

    faces = np.asarray(model.mesh.boundary_faces(), dtype=np.int64)
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    return ipctk.CollisionMesh(np.asarray(model.rest_positions, dtype=np.float64), edges, faces)


def _set_stiffness(sim, value):
    """Every barrier's stiffness set to ``value`` ("auto": adaptive; None: the fixed default)."""
    from warpfem.contact.stiffness import parse_stiffness

    sc = getattr(sim, "surface_contact", None)
    if sc is not None:
        sim.set_contact(**{"bodies": sc.bodies, "self": sc.self_contact, "friction": sc.friction, "dhat": sc.dhat,
                           "friction_velocity": sc.friction_velocity, "stiffness": value})
    cs = getattr(sim, "contact", None)
    if cs is not None and len(cs):
        for c in cs.colliders:
            c.adaptive_stiffness, c.stiffness = parse_stiffness(value)
        cs._upload()


def _kappas(sim):
    out = {}
    sc = getattr(sim, "surface_contact", None)
    if sc is not None:
        out["surface"] = float(sc.kappa)
    cs = getattr(sim, "contact", None)
    if cs is not None and len(cs):
        out["colliders"] = [float(k) for k in np.atleast_1d(cs.kappa)]
    return out


def _record(sim, rows):
    step = sim.step

    def recorded(*a, **kw):
        t = time.perf_counter()
        st = step(*a, **kw)
        rows.append({"time": float(sim.time), "newton": st.newton_iterations, "linear": st.linear_iterations,
                     "line_search": st.line_search_steps, "seconds": time.perf_counter() - t,
                     "converged": bool(st.converged), "friction_iterations": st.friction_iterations,
                     "adaptations": getattr(st, "adaptations", 0),
                     "kappa": _kappas(sim)})
        return st

    sim.step = recorded


def _in_contact(sim):
    sc = getattr(sim, "surface_contact", None)
    near = False
    if sc is not None and sc.num_pairs:
        near = sc.min_distance() < sc.dhat
    cs = getattr(sim, "contact", None)
    if cs is not None and len(cs):
        near = near or bool((cs.distances() < cs.dhat[None, :]).any())
    return near


def run_scene(name, frames, mode, precision):
    scene = load_scene(os.path.join(ROOT, "examples", "scenes", SCENES[name]))
    r = scene.build(precision=precision)
    _set_stiffness(r.sim, "auto" if mode == "auto" else None)
    cm = _collision_mesh(r.model)
    import ipctk

    rows, frames_out = [], []
    _record(r.sim, rows)
    for _ in range(frames):
        n0 = len(rows)
        fs = r.step_frame()
        x = r.sim.positions()
        bad = bool(ipctk.has_intersections(cm, np.asarray(x, dtype=np.float64)))
        contact = _in_contact(r.sim)
        for row in rows[n0:]:
            row["contact"] = contact
        frames_out.append({"frame": fs.frame, "intersects": bad, "converged": fs.converged, "contact": contact})
        print(f"{name} {mode} frame {fs.frame}: {fs.newton_iterations} Newton in {fs.steps} steps, "
              f"{fs.step_seconds:.2f} s, contact {contact}, intersects {bad}, kappa {rows[-1]['kappa']}", flush=True)
    return rows, frames_out


def run_collider_drop(steps, mode, precision, friction=0.3, friction_velocity=None):
    import ipctk

    mesh = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(6, 6, 6))
    model = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.4, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    sim = wf.Simulator(model, dt=1 / 240, integrator="newmark", precision=precision, max_iters=100)
    x = sim.positions()
    floor_y = float(x[:, 1].min()) - 5e-4
    sim.add_collider(wf.Plane(point=(0.0, floor_y, 0.0), normal=(0.0, 1.0, 0.0), friction=friction, name="floor",
                             friction_velocity=friction_velocity))
    _set_stiffness(sim, "auto" if mode == "auto" else None)
    sim.set_velocities(np.tile([0.3, -1.4, 0.0], (len(x), 1)))
    rows = []
    _record(sim, rows)
    cm = _collision_mesh(model)
    frames = []
    for k in range(steps):
        sim.step()
        x = sim.positions()
        gap = float(x[:, 1].min()) - floor_y
        rows[-1]["gap"] = gap
        rows[-1]["contact"] = bool(gap < float(sim.contact.dhat[0]))
        frames.append({"frame": k + 1, "intersects": bool(gap <= 0.0 or ipctk.has_intersections(cm, x)),
                       "converged": rows[-1]["converged"], "contact": rows[-1]["contact"]})
        print(f"collider_drop {mode} step {k + 1}: {rows[-1]['newton']} Newton, {rows[-1]['seconds']:.2f} s, gap {gap:.3g} m, "
              f"vy {sim.velocities()[:, 1].mean():+.3f}, kappa {rows[-1]['kappa']}", flush=True)
    return rows, frames


def summary(rows):
    out = {}
    for key, sel in (("all", rows), ("contact", [r for r in rows if r.get("contact")])):
        n = len(sel)
        if n:
            out[key] = {"steps": n, "newton_per_step": sum(r["newton"] for r in sel) / n,
                        "seconds_per_step": sum(r["seconds"] for r in sel) / n,
                        "max_newton": max(r["newton"] for r in sel),
                        "not_converged": sum(not r["converged"] for r in sel)}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", required=True, choices=list(SCENES) + ["collider_drop"])
    ap.add_argument("--mode", default="auto", choices=("auto", "fixed"))
    ap.add_argument("--frames", type=int, default=12, help="frames (scenes) or steps (collider_drop)")
    ap.add_argument("--precision", default="float64")
    ap.add_argument("--friction", type=float, default=0.3, help="collider_drop: the floor's friction")
    ap.add_argument("--friction-velocity", type=float, default=None, help="collider_drop: eps_v (m/s; default 1e-3 "
                                                                             "body diagonals per second)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    load0 = os.getloadavg()[0]
    if a.case == "collider_drop":
        rows, frames = run_collider_drop(a.frames, a.mode, a.precision, a.friction, a.friction_velocity)
    else:
        rows, frames = run_scene(a.case, a.frames, a.mode, a.precision)
    s = summary(rows)
    res = {"case": a.case, "mode": a.mode, "friction": a.friction if a.case == "collider_drop" else "scene's",
           "friction_velocity": a.friction_velocity if a.case == "collider_drop" else "scene's", "precision": a.precision, "frames": a.frames,
           "device": f"cpu ({platform.processor() or platform.machine()}), 2 cores shared with other jobs",
           "load_average": [load0, os.getloadavg()[0]], "summary": s,
           "frames_intersecting": sum(f["intersects"] for f in frames), "steps": rows, "frame_checks": frames}
    print(json.dumps({k: res[k] for k in ("case", "mode", "precision", "summary", "frames_intersecting", "load_average")}))
    if a.json:
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
