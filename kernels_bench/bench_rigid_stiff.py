"""Rigid bodies against very stiff soft bodies in a scene: what a step costs and how far the stiff
soft body is from rigid (docs/rigid.md, "Rigid or stiff?").

The scene is ``examples/scenes/rigid_toys_box.toml`` (two soft toys, two rigid blocks falling into a
box of five planes). It runs as shipped (the blocks rigid: 4 nodes each) and with the blocks as soft
bodies of the same meshes (1 x 1 x 1 box cells, 6 tets) of stable neo-Hookean material,
E = 1e7, 1e8 and 1e9 Pa (nu 0.3, the blocks' density, a consistent mass matrix: exact second
moments, as the rigid body's; a lumped one puts the mass at the corners and triples them), each for ``--frames`` frames, in this
process, interleaved (``--repeats N``: each frame's smallest time over N rounds).

Per run: Newton iterations per step, seconds per step (frame 1, which compiles, left out), steps
that did not converge; for the soft runs the blocks' largest strain over the run (max over frames
and vertex pairs of |d - d0| / d0) and the largest distance of a block vertex from where the
rigid run has it (the trajectory difference, m; contact makes it grow with time whatever E is).

    .venv/bin/python kernels_bench/bench_rigid_stiff.py [--frames 12] [--repeats 1] [--json PATH] [--md PATH]
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

SCENE = os.path.join(ROOT, "examples", "scenes", "rigid_toys_box.toml")
STIFFNESSES = (1e7, 1e8, 1e9)


def build(E):
    """The scene, its blocks rigid (E None) or soft of Young's modulus E; returns the SceneRun."""
    from warpfem.scenes.scene import Scene
    from warpfem.scenes.schema import SceneError, parse_scene_dict, read_toml

    doc = read_toml(SCENE, SceneError, what="scene")
    if E is not None:
        for b in doc["body"]:
            if b.get("kind") == "rigid":
                b.pop("kind")
                b.pop("initial_angular_velocity", None)  # given as vertex velocities below
                b["material"] = {"model": "stable_neo_hookean", "youngs_modulus": E, "poisson_ratio": 0.3,
                                 "density": b["material"]["density"], "mass_matrix": "consistent"}
    run = Scene(parse_scene_dict(doc, path=SCENE)).build(device="cpu")
    if E is not None:  # the rigid blocks' spin as the soft blocks' vertex velocities (w x (x - c) + v)
        rigid = {b["name"]: b for b in read_toml(SCENE, SceneError, what="scene")["body"] if b.get("kind") == "rigid"}
        v = run.sim.velocities()
        x = run.model.rest_positions
        for name, b in rigid.items():
            i = run.model.body_names.index(name)
            lo, hi = run.model.body_offsets[i:i + 2]
            c = x[lo:hi].mean(axis=0)  # a box of one cell: its vertices' mean is its centre of mass
            w = np.asarray(b.get("initial_angular_velocity", (0.0, 0.0, 0.0)))
            v[lo:hi] = np.asarray(b.get("initial_velocity", (0.0, 0.0, 0.0))) + np.cross(w, x[lo:hi] - c)
        run.sim.set_velocities(v)
    return run


def one_run(E, frames):
    run = build(E)
    blocks = [run.model.body_names.index(n) for n in ("block_a", "block_b")]
    ranges = [tuple(int(o) for o in run.model.body_offsets[i:i + 2]) for i in blocks]
    xs, secs, its, steps, bad = [run.sim.vertex_positions()], [], 0, 0, 0
    for _ in range(frames):
        t0 = time.perf_counter()
        fs = run.step_frame(total_frames=frames)
        secs.append(time.perf_counter() - t0)
        its += fs.newton_iterations
        steps += fs.steps
        bad += fs.unconverged_steps
        xs.append(run.sim.vertex_positions())
    return {"x": np.array(xs), "ranges": ranges, "secs": np.array(secs), "newton": its, "steps": steps,
            "unconverged": bad}


def strain(xs, lo, hi):
    P = xs[:, lo:hi]
    d = np.linalg.norm(P[:, :, None] - P[:, None, :], axis=-1)
    iu = np.triu_indices(hi - lo, 1)
    return float(np.max(np.abs(d[:, iu[0], iu[1]] - d[0, iu[0], iu[1]]) / d[0, iu[0], iu[1]]))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--json", default=None)
    ap.add_argument("--md", default=None)
    a = ap.parse_args()
    kinds = [None, *STIFFNESSES]
    best = {}
    for _ in range(a.repeats):
        for E in kinds:
            r = one_run(E, a.frames)
            if E in best:
                r["secs"] = np.minimum(best[E]["secs"], r["secs"])
            best[E] = r
    ref = best[None]
    env = {"machine": platform.machine(), "processor": platform.processor(), "cpus": os.cpu_count(),
           "load": round(os.getloadavg()[0], 2), "device": "cpu", "frames": a.frames, "repeats": a.repeats,
           "scene": "examples/scenes/rigid_toys_box.toml"}
    rows = []
    for E in kinds:
        r = best[E]
        row = {"blocks": "rigid" if E is None else f"soft E {E:.0e} Pa", "youngs_modulus": E,
               "newton_per_step": r["newton"] / r["steps"], "seconds_per_step": float(r["secs"][1:].sum()) / (
                   r["steps"] - r["steps"] / a.frames), "unconverged_steps": r["unconverged"]}
        if E is not None:
            row["max_strain"] = max(strain(r["x"], lo, hi) for lo, hi in r["ranges"])
            row["max_trajectory_difference_m"] = max(
                float(np.linalg.norm(r["x"][:, lo:hi] - ref["x"][:, rlo:rhi], axis=-1).max())
                for (lo, hi), (rlo, rhi) in zip(r["ranges"], ref["ranges"]))
            row["time_vs_rigid"] = row["seconds_per_step"] / 1.0
        rows.append(row)
    t_rigid = rows[0]["seconds_per_step"]
    for row in rows[1:]:
        row["time_vs_rigid"] = row["seconds_per_step"] / t_rigid
    lines = [f"rigid_toys_box, {a.frames} frames ({best[None]['steps']} steps), CPU ({platform.machine()}, "
             f"{os.cpu_count()} cores, load {env['load']}), best of {a.repeats}", "",
             "| blocks | Newton its / step | s / step | time vs rigid | unconverged steps | max strain | "
             "max trajectory difference (m) |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for row in rows:
        lines.append(f"| {row['blocks']} | {row['newton_per_step']:.2f} | {row['seconds_per_step']:.4f} | "
                     f"{row.get('time_vs_rigid', 1.0):.2f} | {row['unconverged_steps']} | "
                     f"{row['max_strain']:.2e} | {row['max_trajectory_difference_m']:.3g} |" if 'max_strain' in row else
                     f"| {row['blocks']} | {row['newton_per_step']:.2f} | {row['seconds_per_step']:.4f} | 1.00 | "
                     f"{row['unconverged_steps']} | 0 (by construction) | - |")
    print("\n".join(lines))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"environment": env, "results": rows}, f, indent=1)
    if a.md:
        with open(a.md, "w") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
