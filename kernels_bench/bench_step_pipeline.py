"""Cost of one time step and of one Newton iteration on the peer benchmark's beam.

The cantilever of ``kernels_bench/bench_peer_vbd.py`` (480 tets, 189 vertices; 1 m x 0.2 m x 0.2 m, stable neo-Hookean,
E 1e6 Pa, nu 0.3, lumped mass, gravity, clamped at x = 0), backward Euler and Newmark at dt 1/60 s with
the loose tolerances of that benchmark (tol 1e-2, cg_tol 1e-1) and converged ones (tol 1e-5, cg_tol 1e-3),
PCG. For this checkout and for a baseline revision (extracted with ``git archive`` and run in a child
process in the same run, so both see the same machine load): ms per step, ms per Newton iteration (mean, and of the fastest step),
kernel launches and host read-backs per step and per Newton iteration (counted by wrapping
``warp.launch``, ``warp.Launch.launch``, ``warp.capture_launch`` and ``warp.array.numpy``: "launch/newton"
are the launch calls made from Python, "kernels/newton" the kernel launches the step reports
(``SolveStats.launches``, the launches inside replayed graphs included), "graphs/newton" the graph
replays) and the tip displacement after the timed steps (both checkouts must agree).
``--cells 16,3,3`` is the peer benchmark's 864-tet beam (272 vertices), ``--precision float32`` the other precision.

    .venv/bin/python kernels_bench/bench_step_pipeline.py [--baseline a3ec050] [--steps 30] [--device cpu] [--json PATH]
        [--cells 20,2,2] [--E 1e6] [--nu 0.3] [--precision float64]
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
import warnings

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIGS = [("backward_euler", 1e-2, 1e-1), ("backward_euler", 1e-5, 1e-3), ("newmark", 1e-2, 1e-1)]


def measure(steps: int, device="cpu", cells=(20, 2, 2), E=1e6, nu=0.3, precision="float64") -> dict:
    import numpy as np
    import warp as wp

    wp.config.quiet = True
    import warpfem as wf

    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=tuple(cells))
    fixed = np.flatnonzero(mesh.vertices[:, 0] < 1e-9)
    tip = np.flatnonzero(mesh.vertices[:, 0] > 1.0 - 1e-9)
    out = {"warpfem": os.path.dirname(wf.__file__), "device": str(wp.get_device(device)), "tets": int(mesh.num_tets),
           "precision": precision, "E": E, "nu": nu,
           "runs": []}
    for integ, tol, cg_tol in CONFIGS:
        mat = wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=nu, density=1000.0)
        model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81), mass_matrix="lumped")
        model.fix(fixed)
        sim = wf.Simulator(model, device=device, dt=1.0 / 60.0, integrator=integ, tol=tol, cg_tol=cg_tol,
                           linear_solver="pcg", max_iters=50, max_cg_iters=5000, precision=precision)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for _ in range(3):  # warm-up: compile every kernel
                sim.step()
            counts = collections.Counter()
            launch, to_numpy, replay = wp.launch, wp.array.numpy, wp.Launch.launch
            graph_launch = getattr(wp, "capture_launch", None)

            def counted_graph(graph, *a, **kw):
                counts["graphs"] += 1
                return graph_launch(graph, *a, **kw)

            def counted_launch(kernel, *a, **kw):
                if not kw.get("record_cmd"):
                    counts["launches"] += 1
                return launch(kernel, *a, **kw)

            def counted_replay(self, *a, **kw):
                counts["launches"] += 1
                return replay(self, *a, **kw)

            def counted_numpy(self):
                counts["readbacks"] += 1
                return to_numpy(self)

            counted, newton_c, kernel_launches = 5, 0, 0
            wp.launch, wp.array.numpy, wp.Launch.launch = counted_launch, counted_numpy, counted_replay
            wp.capture_launch = counted_graph
            try:
                for _ in range(counted):
                    st = sim.step()
                    newton_c += st.newton_iterations
                    kernel_launches += st.launches
            finally:
                wp.launch, wp.array.numpy, wp.Launch.launch = launch, to_numpy, replay
                wp.capture_launch = graph_launch
            wp.synchronize_device(device)
            newton = cg = 0
            times, iters, cpu = [], [], []
            for _ in range(steps):
                t0, c0 = time.perf_counter(), time.process_time()
                st = sim.step()
                wp.synchronize_device(device)
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
                iters.append(st.newton_iterations)
                newton += st.newton_iterations
                cg += st.cg_iterations
            sec = float(np.sum(times))
            # the fastest step over its Newton iterations: the cost with the least interference from
            # other jobs on a shared machine (every step here takes the same 2-5 iterations)
            k = int(np.argmin(times))
        z = float(sim.positions()[tip, 2].mean() - mesh.vertices[tip, 2].mean())
        out["runs"].append(dict(integrator=integ, tol=tol, cg_tol=cg_tol, ms_per_step=1e3 * sec / steps,
                                ms_per_newton=1e3 * sec / max(newton, 1), newton_per_step=newton / steps,
                                fastest_ms_per_step=1e3 * times[k], fastest_step_newton=iters[k],
                                fastest_ms_per_newton=1e3 * times[k] / max(iters[k], 1),
                                cpu_ms_per_newton_median=1e3 * float(np.median(np.array(cpu) / np.maximum(iters, 1))),
                                cpu_ms_per_newton_fastest=1e3 * float(np.min(np.array(cpu) / np.maximum(iters, 1))),
                                cg_per_newton=cg / max(newton, 1), launches_per_step=counts["launches"] / counted,
                                readbacks_per_step=counts["readbacks"] / counted,
                                launches_per_newton=counts["launches"] / max(newton_c, 1),
                                kernel_launches_per_newton=kernel_launches / max(newton_c, 1),
                                graph_replays_per_newton=counts["graphs"] / max(newton_c, 1),
                                readbacks_per_newton=counts["readbacks"] / max(newton_c, 1), tip_z=z))
    return out


def baseline(rev: str, steps: int, device: str, extra=()) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "-C", ROOT, "archive", rev, "warpfem"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        env = dict(os.environ, PYTHONPATH=tmp)
        res = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "--steps", str(steps),
                              "--device", device, *extra], env=env, cwd=tmp, capture_output=True, text=True, check=True)
        return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default="a3ec050", help="git revision to compare against ('' to skip)")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cells", default="20,2,2", help="cells of the 1 x 0.2 x 0.2 m beam (x6 tets); 16,3,3: 864 tets")
    ap.add_argument("--E", type=float, default=1e6, help="Young's modulus (Pa)")
    ap.add_argument("--nu", type=float, default=0.3, help="Poisson ratio")
    ap.add_argument("--precision", default="float64", choices=("float64", "float32"))
    ap.add_argument("--json")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    cells = tuple(int(c) for c in args.cells.split(","))
    kw = dict(cells=cells, E=args.E, nu=args.nu, precision=args.precision)
    extra = ["--cells", args.cells, "--E", repr(args.E), "--nu", repr(args.nu), "--precision", args.precision]
    if args.child:
        print(json.dumps(measure(args.steps, args.device, **kw)))
        return 0
    base = None
    if args.baseline:
        try:
            base = baseline(args.baseline, args.steps, args.device, extra)
        except subprocess.CalledProcessError as e:
            print(f"baseline {args.baseline} not measured: {e}", file=sys.stderr)
    sys.path.insert(0, ROOT)
    new = measure(args.steps, args.device, **kw)
    from warpfem.paths import portable_path

    for d in (base, new):
        if d:
            d["warpfem"] = portable_path(d["warpfem"])
    print(f"{new['tets']}-tet beam, dt 1/60, PCG, {args.precision}, {new['device']} ({platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}); baseline {args.baseline or '-'}")
    print(f"{'':44s} {'ms/step':>8s} {'ms/newton':>9s} {'fastest step: ms/newton':>23s} {'cpu ms/newton med/min':>21s} "
          f"{'newton':>6s} {'cg/newton':>9s} "
          f"{'launch/newton':>13s} {'kernels/newton':>14s} {'graphs/newton':>13s} {'read/newton':>11s} {'read/step':>9s} {'tip z (m)':>12s}")
    for label, d in (("baseline", base), ("this checkout", new)):
        if not d:
            continue
        for r in d["runs"]:
            name = f"{label} {r['integrator']} tol {r['tol']:g}/{r['cg_tol']:g}"
            print(f"{name:44s} {r['ms_per_step']:8.2f} {r['ms_per_newton']:9.2f} {r['fastest_ms_per_newton']:23.2f} "
                  f"{r['cpu_ms_per_newton_median']:14.2f}/{r['cpu_ms_per_newton_fastest']:.2f} "
                  f"{r['newton_per_step']:6.2f} "
                  f"{r['cg_per_newton']:9.1f} {r['launches_per_newton']:13.1f} {r.get('kernel_launches_per_newton', float('nan')):14.1f} "
                  f"{r.get('graph_replays_per_newton', 0.0):13.2f} {r['readbacks_per_newton']:11.2f} "
                  f"{r['readbacks_per_step']:9.1f} {r['tip_z']:12.6e}")
    if base:
        for b, r in zip(base["runs"], new["runs"]):
            print(f"{r['integrator']} tol {r['tol']:g}: ms per Newton iteration ratio (baseline / this) "
                  f"{b['ms_per_newton'] / r['ms_per_newton']:.2f} (mean), "
                  f"{b['fastest_ms_per_newton'] / r['fastest_ms_per_newton']:.2f} (fastest step), "
                  f"{b['cpu_ms_per_newton_median'] / r['cpu_ms_per_newton_median']:.2f} (median CPU time)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"baseline": base, "new": new, "load": os.getloadavg()[0]}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
