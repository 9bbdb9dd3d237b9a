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
    newton, fastest = 0, float("inf")
    for _ in range(steps):
        t1 = time.perf_counter()
        newton += sim.step().newton_iterations
        wp.synchronize_device(device)
        fastest = min(fastest, time.perf_counter() - t1)
    ms = 1e3 * (time.perf_counter() - t0) / steps
    return {"warpfem": os.path.dirname(warpfem.__file__), "device": str(wp.get_device(device)), "ms_per_step": ms,
            "fastest_step_ms": 1e3 * fastest, "newton_per_step": newton / steps,
            "launches_per_step": counts["launches"] / 3, "repacks_per_step": counts["repacks"] / 3,
            "repack_us": repack_cost(), **kernel_times(sim)}


def kernel_times(sim, calls: int = 200) -> dict:
    """Fastest of ``calls`` timed calls (microseconds; the minimum resists machine load) of the Hessian
    assembly (``assemble_stiffness``: one launch) and of the elastic forces (``elastic_forces``: one
    launch plus a read-back)."""
    import warp as wp

    vals = sim.new_matrix_values()
    out = {}
    for name, fn in (("hessian_us", lambda: sim.assemble_stiffness(sim.x, vals)), ("force_us", sim.elastic_forces)):
        best = float("inf")
        for _ in range(calls):
            t0 = time.perf_counter()
            fn()
            wp.synchronize_device(sim.device)
            best = min(best, time.perf_counter() - t0)
        out[name] = 1e6 * best
    return out


def repack_cost(calls: int = 20000) -> float:
    """Mean microseconds of one re-pack of a non-array argument (a Warp scalar or a struct) of the
    recorded launch of the elastic force kernel."""
    import warp as wp
    from warpfem.kernels import generic

    for (kernel, *_), (cmd, _m, _k, last) in generic._LAUNCH_CACHE.items():
        if kernel.key.startswith("qp_force_and_abs_kernel"):
            idx = [i for i, v in enumerate(last) if not isinstance(v, wp.array) and type(v) not in (int, float, bool)]
            t0 = time.perf_counter()
            for _ in range(calls // len(idx)):
                for i in idx:
                    cmd.set_param_at_index(i, last[i])
            return 1e6 * (time.perf_counter() - t0) / (calls // len(idx) * len(idx))
    return float("nan")


def child(pythonpath: str, cwd: str, steps: int, device: str) -> dict:
    env = dict(os.environ, PYTHONPATH=pythonpath)
    res = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "--steps", str(steps), "--device", device],
                         env=env, cwd=cwd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group()
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
    if not (args.baseline or args.baseline_dir):
        ap.error("give --baseline REV or --baseline-dir DIR")
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
        for k in range(args.rounds):  # alternating, and which goes first alternates too
            order = (("baseline", base_dir), ("this", ROOT))
            for name, where in order if k % 2 == 0 else order[::-1]:
                runs[name].append(child(where, where, args.steps, args.device))
        load1 = os.getloadavg()[0]
    r0, r1 = runs["baseline"][0], runs["this"][0]
    b = statistics.median(r["ms_per_step"] for r in runs["baseline"])
    t = statistics.median(r["ms_per_step"] for r in runs["this"])
    print(f"480-tet cantilever, backward Euler, float64, {r1['device']} ({platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, load {load0:.1f} -> {load1:.1f}); {args.rounds} alternating rounds of {args.steps} steps")
    print(f"{'':10s} {'ms/step median':>14s} {'min':>6s} {'fastest step':>12s} {'newton/step':>11s} "
          f"{'all rounds':>40s} {'launches/step':>14s} "
          f"{'re-packs/step':>14s} {'us/re-pack':>10s} {'us hessian':>10s} {'us force':>9s}")
    for name, med, rs in (("baseline", b, runs["baseline"]), ("this", t, runs["this"])):
        each = " ".join("%.2f" % r["ms_per_step"] for r in rs)
        print(f"{name:10s} {med:14.2f} {min(r['ms_per_step'] for r in rs):6.2f} "
              f"{min(r['fastest_step_ms'] for r in rs):12.2f} {rs[0]['newton_per_step']:11.2f} {each:>40s} "
              f"{rs[0]['launches_per_step']:14.1f} {rs[0]['repacks_per_step']:14.1f} "
              f"{statistics.median(r['repack_us'] for r in rs):10.2f} {min(r['hessian_us'] for r in rs):10.1f} "
              f"{min(r['force_us'] for r in rs):9.1f}")
    fast = (min(r["fastest_step_ms"] for r in runs["this"])
            / min(r["fastest_step_ms"] for r in runs["baseline"]))
    print(f"this / baseline: {t / b:.3f} (median of the rounds' ms per step), {fast:.3f} (fastest single step); "
          f"warpfem: {r0['warpfem']} vs {r1['warpfem']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
