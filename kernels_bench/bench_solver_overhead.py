"""Per-step overhead of the Newton solver: kernel launches, host read-backs and wall time per step
on the 480-tet cantilever (examples/scenes/cantilever.toml: stable neo-Hookean, dt 1/48 s,
tol 1e-5, cg_tol 1e-3), for this checkout and for a baseline revision measured in the same run.

The baseline is the revision's ``warpfem`` package extracted with ``git archive`` into a temporary
folder and run in a child process (so both use the same machine at the same time). Counts come
from wrapping ``warp.launch``, ``warp.Launch.launch`` (recorded launches) and ``warp.array.numpy``
during a few counted steps; times from
separate, uncounted steps after a warm-up (every kernel compiled first).

    .venv/bin/python kernels_bench/bench_solver_overhead.py [--baseline e400908] [--steps 40] [--device cpu] [--json PATH]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = os.path.join(ROOT, "examples", "scenes", "cantilever.toml")


def measure(steps: int, integrators, device="cpu") -> dict:
    import warp as wp

    wp.config.quiet = True
    import warpfem as wf
    from warpfem.scenes import load_scene

    out = {"warpfem": os.path.dirname(wf.__file__), "device": str(wp.get_device(device)), "runs": []}
    for integ in integrators:
        run = load_scene(SCENE).build(device=device, precision="float64")
        sim = run.sim
        if integ != "backward_euler":
            try:
                sim = wf.Simulator(run.model, device=device, dt=sim.dt, integrator=integ, tol=sim.options.tol,
                                   cg_tol=sim.options.cg_tol, max_iters=sim.options.max_iters)
            except TypeError:
                continue  # the baseline has no integrators
        for _ in range(3):  # warm-up: compile every kernel
            sim.step()
        counts = collections.Counter()
        launch, to_numpy = wp.launch, wp.array.numpy

        depth = [0]  # inside the linear solver (block-Jacobi PCG) or not

        def count_launch():
            counts["launches"] += 1
            counts["launches_outside_linear_solve"] += depth[0] == 0

        def counted_launch(kernel, *a, **kw):
            if not kw.get("record_cmd"):  # a recorded launch counts when it is launched
                count_launch()
            return launch(kernel, *a, **kw)

        replay = wp.Launch.launch

        def counted_replay(self, *a, **kw):
            count_launch()
            return replay(self, *a, **kw)

        def counted_numpy(self):
            counts["readbacks"] += 1
            counts["readbacks_outside_linear_solve"] += depth[0] == 0
            return to_numpy(self)

        pcg_type = type(sim.linear_solver)
        solve = pcg_type.solve

        def counted_solve(self, *a, **kw):
            depth[0] += 1
            try:
                return solve(self, *a, **kw)
            finally:
                depth[0] -= 1

        newton = cg = 0
        wp.launch, wp.array.numpy, pcg_type.solve = counted_launch, counted_numpy, counted_solve
        wp.Launch.launch = counted_replay
        try:
            for _ in range(5):
                st = sim.step()
                newton += st.newton_iterations
                cg += st.cg_iterations
        finally:
            wp.launch, wp.array.numpy, pcg_type.solve = launch, to_numpy, solve
            wp.Launch.launch = replay
        t0 = time.perf_counter()
        n_it = 0
        for _ in range(steps):
            n_it += sim.step().newton_iterations
        seconds = (time.perf_counter() - t0) / steps
        out["runs"].append(dict(integrator=integ, ms_per_step=1e3 * seconds, newton_per_step=n_it / steps,
                                cg_per_newton=cg / max(newton, 1),
                                launches_per_step=counts["launches"] / 5, readbacks_per_step=counts["readbacks"] / 5,
                                launches_per_newton=counts["launches"] / max(newton, 1),
                                readbacks_per_newton=counts["readbacks"] / max(newton, 1),
                                outside_launches_per_newton=counts["launches_outside_linear_solve"] / max(newton, 1),
                                outside_readbacks_per_newton=counts["readbacks_outside_linear_solve"] / max(newton, 1)))
    return out


def baseline(rev: str, steps: int, device: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "-C", ROOT, "archive", rev, "warpfem"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        env = dict(os.environ, PYTHONPATH=tmp)
        res = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "--steps", str(steps),
                              "--device", device],
                             env=env, cwd=tmp, capture_output=True, text=True, check=True)
        return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default="e400908", help="git revision to compare against (default: e400908)")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--json")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.steps, ["backward_euler"], args.device)))
        return 0
    try:
        base = baseline(args.baseline, args.steps, args.device)
    except subprocess.CalledProcessError as e:  # no git history (a shallow clone) or an unknown revision
        print(f"baseline {args.baseline} not measured: {e}", file=sys.stderr)
        base = None
    sys.path.insert(0, ROOT)
    new = measure(args.steps, ["backward_euler", "bdf2", "newmark"], args.device)
    from warpfem.paths import portable_path  # this checkout's (the baseline's warpfem may predate it)

    for d in (base, new):  # where each warpfem was, as results record paths (no absolute path of this machine)
        if d:
            d["warpfem"] = portable_path(d["warpfem"])
    print(f"480-tet cantilever, {new['device']} ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}); baseline {args.baseline}")
    print(f"{'':28s} {'ms/step':>8s} {'newton':>7s} {'cg/newton':>9s} {'launch/step':>11s} {'read/step':>9s} "
          f"{'launch/newton':>13s} {'read/newton':>11s}  outside the linear solve: {'launch/newton':>13s} {'read/newton':>11s}")
    rows = ([(f"baseline {args.baseline} (BE)", base["runs"][0])] if base else []) + [
        (f"this checkout ({r['integrator']})", r) for r in new["runs"]]
    for name, r in rows:
        print(f"{name:28s} {r['ms_per_step']:8.2f} {r['newton_per_step']:7.2f} {r['cg_per_newton']:9.1f} "
              f"{r['launches_per_step']:11.1f} {r['readbacks_per_step']:9.1f} {r['launches_per_newton']:13.1f} "
              f"{r['readbacks_per_newton']:11.1f}  {'':26s}{r['outside_launches_per_newton']:13.1f} "
              f"{r['outside_readbacks_per_newton']:11.1f}")
    if base:
        be = new["runs"][0]
        print(f"backward Euler speed-up vs baseline: {base['runs'][0]['ms_per_step'] / be['ms_per_step']:.2f}x per step")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"baseline": base, "new": new, "load": os.getloadavg()[0]}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
