"""Cost of one reduced time step against the full step of the same scene, and against an older
checkout of warpfem (the "before" of a change), all in one run.

For each scene (default: the thin cantilever as in its scene file (Newmark, r = 10 + 10), the
same beam with backward Euler and r = 29 (``thin_cantilever_be``, the earlier rows) and the
octopus, with the subspace settings of the rows quoted in docs/reduced.md), the subspace is
trained once (``warpfem train``'s code; cached in
``--cache-dir``, reused when up to date) and then, each in a fresh process:

* the **full** step: the scene's full simulator with its current default solver settings
  (``linear_solver = "auto"``), over the first ``--full-frames`` (default ``--frames``) frames;
* the **reduced** step of this checkout over the first ``--frames`` frames (default: the whole
  48-frame scene, 96 steps);
* the **reduced** step of ``--baseline`` (another checkout's ``warpfem``, e.g. the unchanged
  main branch), the same frames, the same cache file.

Each is run ``--repeats`` times, interleaved, and the fastest run counts (on a shared machine load
only ever slows a run down). Reported per scene: ms per step (step() time, mean over the steps of
a run; the first frame is a warm-up and not counted),
Newton iterations, line-search halvings and Newton-matrix (Hessian) evaluations per step (Hessians
are counted by this checkout only; before, every Newton iteration evaluated one), the speed-up of
the reduced step over the full step and over the baseline's reduced step, and the largest
difference between this checkout's and the baseline's reduced positions (both converge each step to
the solver tolerance, so they agree to about that). The load of the machine (``os.getloadavg``)
is recorded before and after.

    .venv/bin/python kernels_bench/bench_reduced_step.py [--scenes thin_cantilever,thin_cantilever_be,octopus] [--frames 48]
        [--full-frames 48] [--repeats 2] [--baseline /path/to/other/checkout] [--cache-dir ~/.cache/warpfem/bench_reduced_step]
        [--out kernels_bench/results/reduced_step]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# scene -> [subspace] settings over the scene file's (the rows of docs/reduced.md: octopus 10 + 30 POD
# columns, tol 0.01, coarse training run at 2 dt -> r = 26, 172 points); "_file": another scene
# file, "_integrator": [integrator] settings over the file's
SCENES = {
    # the scene file as it is: Newmark, r = 10 modal + 10 POD columns over the whole swing -> 36 points
    "thin_cantilever": dict(),
    # the earlier rows: backward Euler, r = 20 + 10 (29), tol 0.002, 12 training frames -> 56 points
    "thin_cantilever_be": dict(modes=20, pod_modes=10, training_frames=12, training_dt_scale=1, cubature_tolerance=0.002,
                               _file="thin_cantilever", _integrator=dict(type="backward_euler")),
    "octopus": dict(modes=10, pod_modes=30, training_frames=48, training_dt_scale=2, cubature_tolerance=0.01,
                    max_cubature_points=400),
}


def _scene(name, cache_dir):
    """The example scene with the [subspace] settings above (validated by the scene schema) and its
    cache in ``cache_dir``."""
    from warpfem.scenes import Scene
    from warpfem.scenes.schema import SceneError, parse_scene_dict, read_toml

    settings = dict(SCENES[name])
    path = os.path.join(ROOT, "examples", "scenes", f"{settings.pop('_file', name)}.toml")
    data = read_toml(path, SceneError, what="scene file")
    data["integrator"] = dict(data.get("integrator", {}), **settings.pop("_integrator", {}))
    data["subspace"] = dict(data.get("subspace", {}), **settings,
                            cache=os.path.join(cache_dir, f"{name}.subspace.npz"))
    data.pop("surface", None)  # the render surface is not what is measured
    return Scene(parse_scene_dict(data, path=path))


def worker(args):
    """Run in a fresh process: the full or reduced steps of one scene; prints one JSON line."""
    import numpy as np
    import warnings
    import warp as wp

    wp.config.quiet = True
    import warpfem

    scene = _scene(args.scene, args.cache_dir)
    total = int(scene.spec.output["frames"])
    full = args.worker == "full"
    run = scene.build(full=True) if full else scene.build()
    sim = run.sim
    frames = args.full_frames if full else args.frames
    stats, xs = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        orig = sim.step

        def step():
            st = orig()
            stats.append(st)
            return st

        sim.step = step
        run.step_frame(total_frames=total)  # warm-up frame (kernel loads, first factorisations)
        stats.clear()
        for _ in range(frames - 1):
            run.step_frame(total_frames=total)
            xs.append(sim.positions())
    here = os.path.realpath(os.path.join(HERE, os.pardir, "warpfem"))
    checkout = "this checkout" if os.path.realpath(os.path.dirname(warpfem.__file__)) == here else "baseline checkout"
    out = dict(warpfem=checkout, steps=len(stats),  # which code ran, never a machine's path
               ms_per_step=1e3 * float(np.mean([s.seconds for s in stats])),
               newton_iterations=float(np.mean([s.newton_iterations for s in stats])),
               line_search_steps=float(np.mean([s.line_search_steps for s in stats])),
               hessians=(float(np.mean([s.hessian_evaluations for s in stats]))
                         if hasattr(stats[0], "hessian_evaluations") else None),
               converged=int(sum(bool(s.converged) for s in stats)))
    if not full:
        out["r"], out["points"] = int(sim.r), int(sim.forces.c)
    np.save(args.positions, np.array(xs))
    print("RESULT " + json.dumps(out), flush=True)


def _spawn(kind, scene, args, root, positions):
    env = dict(os.environ, PYTHONPATH=root)
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", kind, "--scene", scene, "--frames", str(args.frames),
           "--full-frames", str(args.full_frames), "--cache-dir", args.cache_dir, "--positions", positions]
    res = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
    for line in res.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"{kind} worker ({root}) failed:\n{res.stdout[-2000:]}\n{res.stderr[-4000:]}")


def train(name, args):
    from warpfem.reduced.scene import train_scene

    scene = _scene(name, args.cache_dir)
    t0 = time.perf_counter()
    sub = train_scene(scene, retrain=False)
    return dict(r=int(sub.U.shape[1]), points=int(sub.cubature.num_points), seconds=time.perf_counter() - t0,
                cache=sub.report.get("cache", "trained"))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="thin_cantilever,thin_cantilever_be,octopus")
    ap.add_argument("--frames", type=int, default=48, help="frames measured (the first one is a warm-up, not counted)")
    ap.add_argument("--full-frames", type=int, default=0, help="frames of full steps measured (default: --frames)")
    ap.add_argument("--repeats", type=int, default=2, help="runs of each (interleaved); the fastest counts")
    ap.add_argument("--baseline", default="", help="another checkout whose warpfem is measured as 'before'")
    ap.add_argument("--cache-dir", default=os.path.expanduser("~/.cache/warpfem/bench_reduced_step"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "reduced_step"))
    ap.add_argument("--machine", default="cpu, 2 cores shared with other jobs")
    ap.add_argument("--worker", default="", help=argparse.SUPPRESS)
    ap.add_argument("--scene", default="", help=argparse.SUPPRESS)
    ap.add_argument("--positions", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.full_frames = args.full_frames or args.frames
    if args.worker:
        return worker(args)
    import numpy as np

    os.makedirs(args.cache_dir, exist_ok=True)
    rows = []
    for name in args.scenes.split(","):
        tr = train(name, args)
        load0 = os.getloadavg()
        pos = {k: os.path.join(args.cache_dir, f"{name}.{k}.npy") for k in ("full", "after", "before")}
        res = {}
        for _ in range(args.repeats):  # interleaved; the fastest run of each counts (load spikes only slow down)
            runs = [("full", "full", ROOT), ("after", "reduced", ROOT)]
            if args.baseline:
                runs.append(("before", "reduced", os.path.abspath(args.baseline)))
            for key, kind, root in runs:
                out = _spawn(kind, name, args, root, pos[key])
                out["ms_per_step_runs"] = res.get(key, {}).get("ms_per_step_runs", []) + [out["ms_per_step"]]
                out["ms_per_step"] = min(out["ms_per_step_runs"])
                res[key] = out
        load1 = os.getloadavg()
        row = dict(scene=name, r=tr["r"], points=tr["points"], load_before=load0, load_after=load1, **{
            k: v for k, v in res.items()})
        after = np.load(pos["after"])
        if args.baseline:
            before = np.load(pos["before"])
            row["max_position_difference_m"] = float(np.abs(after - before).max())
        full = np.load(pos["full"])
        k = min(len(full), len(after))
        if k:
            row["max_difference_to_full_m"] = float(np.abs(after[:k] - full[:k]).max())
        row["speedup_vs_full"] = res["full"]["ms_per_step"] / res["after"]["ms_per_step"]
        if args.baseline:
            row["speedup_vs_before"] = res["before"]["ms_per_step"] / res["after"]["ms_per_step"]
            row["before_speedup_vs_full"] = res["full"]["ms_per_step"] / res["before"]["ms_per_step"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    device = f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} logical cores visible), {args.machine}"

    def commit(root):
        r = subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        return r.stdout.strip() or "unknown"

    commits = dict(this_checkout=commit(ROOT), **({"baseline": commit(args.baseline)} if args.baseline else {}))
    head = (f"Reduced step vs full step (bench_reduced_step.py, {args.frames} frames reduced, {args.full_frames} full, "
            f"the first frame a warm-up; fastest of {args.repeats} interleaved runs; full step: the scene's full simulator with its "
            f"default solver settings). Device: {device}.\n\n")
    table = ["| scene | r | cubature pts | full step ms | reduced before ms (Newton it / step) | reduced after ms "
             "(Newton it, Hessians / step) | after vs full | after vs before | load (1 min) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        b = row.get("before")
        a = row["after"]
        table.append(f"| {row['scene']} | {row['r']} | {row['points']} | {row['full']['ms_per_step']:.1f} | "
                     + (f"{b['ms_per_step']:.2f} ({b['newton_iterations']:.2f}) | " if b else "- | ")
                     + f"{a['ms_per_step']:.3f} ({a['newton_iterations']:.2f}, {a['hessians']:.2f}) | "
                     f"{row['speedup_vs_full']:.0f}x | " + (f"{row['speedup_vs_before']:.1f}x | " if b else "- | ")
                     + f"{row['load_before'][0]:.1f} - {row['load_after'][0]:.1f} |")
    md = head + "\n".join(table) + "\n"
    print(md)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out + ".json", "w") as f:
        json.dump(dict(device=device, commits=commits, frames=args.frames, full_frames=args.full_frames, rows=rows), f, indent=1)
    with open(args.out + ".md", "w") as f:
        f.write(md)


if __name__ == "__main__":
    main()
