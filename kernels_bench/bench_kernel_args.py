"""Per-step cost of the kernels' argument passing: the 480-tet cantilever (examples/scenes/cantilever.toml,
backward Euler, float64) stepped by this checkout and by a baseline, in alternating child processes
of one run (the same machine load for both).

Reported per step: wall time (ms), kernel launches, and argument re-packs of recorded launches
(``warp.Launch.set_param_at_index`` calls: what ``kernels.generic.launch`` pays for each argument
that is not the very object of the previous launch). The baseline is a git revision extracted with
``git archive`` (``--baseline REV``) or a directory holding a ``warpfem`` package (``--baseline-dir``).

    .venv/bin/python kernels_bench/bench_kernel_args.py --baseline REV [--rounds 3] [--steps 20] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = os.path.join(ROOT, "examples", "scenes", "cantilever.toml")


def measure(steps: int, device: str) -> dict:
    import warp as wp

    wp.config.quiet = True
    import warpfem
    from warpfem.scenes import load_scene

    sim = load_scene(SCENE).build(device=device, precision="float64").sim
    for _ in range(3):  # warm-up: every module loaded
        sim.step()
    counts = {"repacks": 0, "launches": 0}
    set_param, replay, launch = wp.Launch.set_param_at_index, wp.Launch.launch, wp.launch

    def counted_set_param(self, *a, **kw):
        counts["repacks"] += 1
        return set_param(self, *a, **kw)

    def counted_replay(self, *a, **kw):
        counts["launches"] += 1
        return replay(self, *a, **kw)

    def counted_launch(kernel, *a, **kw):
        counts["launches"] += not kw.get("record_cmd")
        return launch(kernel, *a, **kw)

    wp.Launch.set_param_at_index, wp.Launch.launch, wp.launch = counted_set_param, counted_replay, counted_launch
    try:
        for _ in range(3):
            sim.step()
    finally:
        wp.Launch.set_param_at_index, wp.Launch.launch, wp.launch = set_param, replay, launch
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step()
    wp.synchronize_device(device)
    ms = 1e3 * (time.perf_counter() - t0) / steps
    return {"warpfem": os.path.dirname(warpfem.__file__), "device": str(wp.get_device(device)), "ms_per_step": ms,
            "launches_per_step": counts["launches"] / 3, "repacks_per_step": counts["repacks"] / 3}


def child(pythonpath: str, cwd: str, steps: int, device: str) -> dict:
    env = dict(os.environ, PYTHONPATH=pythonpath)
    res = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "--steps", str(steps), "--device", device],
                         env=env, cwd=cwd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--baseline", help="git revision to compare against")
    src.add_argument("--baseline-dir", help="a directory holding the baseline's warpfem package")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.steps, args.device)))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        if args.baseline:
            archive = subprocess.run(["git", "-C", ROOT, "archive", args.baseline, "warpfem"], check=True,
                                     capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
            base_dir = tmp
        else:
            base_dir = os.path.abspath(args.baseline_dir)
        load0 = os.getloadavg()[0]
        runs = {"baseline": [], "this": []}
        for _ in range(args.rounds):
            runs["baseline"].append(child(base_dir, base_dir, args.steps, args.device))
            runs["this"].append(child(ROOT, ROOT, args.steps, args.device))
        load1 = os.getloadavg()[0]
    r0, r1 = runs["baseline"][0], runs["this"][0]
    b = statistics.median(r["ms_per_step"] for r in runs["baseline"])
    t = statistics.median(r["ms_per_step"] for r in runs["this"])
    print(f"480-tet cantilever, backward Euler, float64, {r1['device']} ({platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, load {load0:.1f} -> {load1:.1f}); {args.rounds} alternating rounds of {args.steps} steps")
    print(f"{'':10s} {'ms/step (median)':>16s} {'all rounds':>28s} {'launches/step':>14s} {'re-packs/step':>14s}")
    for name, med, rs in (("baseline", b, runs["baseline"]), ("this", t, runs["this"])):
        each = " ".join("%.2f" % r["ms_per_step"] for r in rs)
        print(f"{name:10s} {med:16.2f} {each:>28s} "
              f"{rs[0]['launches_per_step']:14.1f} {rs[0]['repacks_per_step']:14.1f}")
    print(f"this / baseline: {t / b:.3f} (ms per step); warpfem: {r0['warpfem']} vs {r1['warpfem']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
