"""What contact costs per step: the bunny drop (examples/scenes/bunny_drop.toml) with and without
its floor.

Phase 1 (the cost of having a collider): the first ``--free-steps`` steps, before the bunny
reaches the floor, run with the floor and again with the floor removed; Newton iterations, linear
(PCG) iterations and wall seconds per step are compared (ratio against the baseline measured in the
same run). Phase 2: the impact and the bounce: the bunny placed 0.5 mm above the floor moving down
at 1.4 m/s (the speed of the scene's 10 cm fall), per step (Newton and linear iterations, line-search
halvings, seconds, gap to the floor, mean vertical velocity).

    .venv/bin/python kernels_bench/bench_contact.py [--device cpu] [--free-steps 15] [--steps 12] [--json PATH]
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
from warpfem.scenes import load_scene  # noqa: E402

SCENE = os.path.join(ROOT, "examples", "scenes", "bunny_drop.toml")


def run(steps, *, floor, device, precision, log_every=0, impact=False):
    scene = load_scene(SCENE)
    if not floor:
        scene.spec.collider = []
    r = scene.build(device=device, precision=precision)
    sim = r.sim
    sim.step()  # warm-up (kernel compilation, first allocations): not timed
    if impact:
        x = sim.positions()
        x[:, 1] += -0.0695 - x[:, 1].min()
        sim.set_positions(x)
        sim.set_velocities(np.tile([0.0, -1.4, 0.0], (len(x), 1)))
    rows = []
    for k in range(steps):
        t = time.perf_counter()
        st = sim.step()
        dt = time.perf_counter() - t
        x, v = sim.positions(), sim.velocities()
        rows.append({"step": k + 2, "time": sim.time, "newton": st.newton_iterations, "linear": st.linear_iterations,
                     "line_search": st.line_search_steps, "seconds": dt, "converged": st.converged,
                     "ymin": float(x[:, 1].min()), "vy": float(v[:, 1].mean())})
        rows[-1]["ymin"] += 0.07  # gap to the floor
        if log_every and k % log_every == 0:
            print(rows[-1], flush=True)
    return rows


def summary(rows):
    n = len(rows)
    return {k: sum(r[k] for r in rows) / n for k in ("newton", "linear", "seconds")} | {"steps": n}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--free-steps", type=int, default=15)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    with_floor = run(a.free_steps, floor=True, device=a.device, precision=a.precision)
    without = run(a.free_steps, floor=False, device=a.device, precision=a.precision)
    s1, s0 = summary(with_floor), summary(without)
    print(f"device {a.device} ({platform.processor() or platform.machine()}), {a.precision}, load {os.getloadavg()[0]:.2f}")
    print(f"before impact, per step: floor {s1}, no floor {s0}; time ratio {s1['seconds'] / s0['seconds']:.2f}")
    full = run(a.steps, floor=True, device=a.device, precision=a.precision, log_every=1, impact=True) if a.steps else []
    if full:
        print("impact steps, per step:", summary(full))
        print("smallest gap", min(r["ymin"] for r in full), "m; largest upward mean velocity", max(r["vy"] for r in full),
              "m/s (in: -1.4); converged", sum(r["converged"] for r in full), "of", len(full))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"device": a.device, "precision": a.precision, "free_with_floor": s1, "free_without": s0,
                       "full": full, "load": os.getloadavg()}, f, indent=1)


if __name__ == "__main__":
    main()
