"""CPU threads: 2 threads against 1 in one run, and the scaling law projected to 8 and 16 cores.

warpfem splits its CPU kernel launches across a pool of threads (``warpfem.threads``: element,
gather, vector and multigrid V-cycle kernels); results are bit-identical whatever the thread
count (checked here too). Cases, each measured with 1 and with ``--threads`` threads (default 2)
in the same process, interleaved, best of ``--repeats``:

  force-24k / force-200k      the elastic gradient of a Newton iteration (per-point slots, gather per
                              vertex, the magnitude's dot; one dispatch per thread count, the threads'
                              point ranges overlapping at the seam): clamped boxes of 24,000 and
                              192,000 tets
  hessian-24k / hessian-200k  the elastic Hessian (zero the values, SPD-projected per-point blocks,
                              gather per block)
  box-98k-step                one backward-Euler step of the 98,304-tet box at nu 0.49 (the scene of
                              bench_scale.py: 2 x 0.5 x 0.5 m, E 1e5, gravity, dt 1/60), linear solver
                              ``--box-solver`` (default multigrid, what ``auto`` picks there)
  beam-864-step               one backward-Euler step of the 864-tet beam (16 x 3 x 3 cells of 6 tets,
                              1 x 0.2 x 0.2 m, E 1e6, nu 0.3, gravity, dt 1/60, default solver)

Each figure is given twice: wall clock, and process CPU time over the critical path (the CPU time
of the operation minus, per split launch, its chunks' CPU time beyond the longest chunk: what an
idle machine would take if a chunk's dispatch and memory bandwidth cost nothing). On a loaded
machine a process gets a share of the cores whatever its thread count, so the wall-clock speed-up
stays near 1 there, while the CPU-time figure still shows how much of the work runs in parallel.

A step case builds one simulator per thread count; both start from the same state and take the same
steps (the same numbers: the step times compare the same work), alternately, after one warm-up step.
Also measured, on one thread: the atomic scatter that the gather replaced (force and Hessian kernels
with ``slots`` 0), the cost of determinism on one core; and, for the force, the previous way of
splitting it (three split launches: the points' slots, the gather, the magnitude's dot product, each
dispatched on its own) on 1 and ``--threads`` threads, and the other cut of the current one (the
points split evenly, then the gather: two dispatches and no points computed twice at the seam). Runtime: about 3 minutes on the idle 2-core
machine (1 minute with ``--quick``).

Scaling law (Amdahl): from the measured speed-up S on p threads, the serial fraction
f = (p / S - 1) / (p - 1), and the projected speed-up on N cores 1 / (f + (1 - f) / N). It assumes the
parallel part keeps scaling (memory bandwidth and the chunks' dispatch cost grow with N): an upper
estimate.

The machine's load average is recorded at the start and the end: on a shared machine the ratios are
noisy (re-run it on a quiet one).

    .venv/bin/python kernels_bench/bench_threads.py [--threads 2] [--repeats 5] [--steps 3] [--quick]
        [--box-solver multigrid] [--out kernels_bench/results/threads_cpu.json]

``--quick``: the 24k assembly cases and the beam only. ``--probe``: only what the machine gives p
threads, apart from warpfem's code (streaming memory bandwidth with numpy copies on 1 and p threads;
the force's per-point kernel on the 192k-tet box as one launch and as p chunks at once through the
pool, with each chunk's start delay and duration; ``threads_probe.json`` next to ``--out``).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import sys
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):  # host BLAS on one thread: only warpfem's threads vary
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402
from warpfem.kernels import fem as FK  # noqa: E402
from warpfem.kernels import linalg as LK  # noqa: E402
from warpfem.kernels.generic import launch  # noqa: E402
import warpfem.solvers.forms as FORMS  # noqa: E402
import warpfem.threads as TH  # noqa: E402
from warpfem.threads import available_cores, set_threads  # noqa: E402

class CriticalPath:
    """CPU-time accounting of split launches, for a speed-up that a loaded machine does not blur:
    the process CPU time of an operation minus, per split launch, its chunks' CPU time beyond the
    longest chunk (what the other threads did at the same time) is its critical path; one thread's
    CPU time over the critical path with p threads is the speed-up an idle machine would give if
    dispatch and memory bandwidth cost nothing (an upper estimate, next to the wall-clock figure)."""

    def __init__(self):
        self.overlap = 0.0
        self._orig = TH.run_chunks
        TH.run_chunks = self._run

    def _run(self, fns):
        times = [0.0] * len(fns)

        def timed(i, fn):
            def run():
                t0 = time.thread_time()
                fn()
                times[i] = time.thread_time() - t0
            return run

        self._orig([timed(i, fn) for i, fn in enumerate(fns)])
        self.overlap += sum(times) - max(times)

    def measure(self, fn):
        """(wall seconds, process CPU seconds, critical-path CPU seconds) of fn()."""
        o0, c0, t0 = self.overlap, time.process_time(), time.perf_counter()
        fn()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        return wall, cpu, cpu - (self.overlap - o0)


TARGETS = {"force-24k": 1.8, "force-200k": 1.8, "hessian-24k": 1.8, "hessian-200k": 1.8, "box-98k-step": 1.6,
           "beam-864-step": 1.3}


def box(c, nu, solver=None):
    """The clamped box of bench_scale.py: 4c x c x c cells of 6 tets."""
    cells = (4 * c, c, c)
    mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=cells)
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=nu, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    kw = {} if solver is None else {"linear_solver": solver}
    return wf.Simulator(model, device="cpu", dt=1.0 / 60.0, precision="float64", **kw)


def beam():
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(16, 3, 3))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(np.nonzero(mesh.vertices[:, 0] < 1e-9)[0])
    return wf.Simulator(model, device="cpu", dt=1.0 / 60.0, precision="float64")


def load():
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


CP = None  # the CriticalPath of the run (installed by main)


def assembly_case(c, threads, repeats):
    """{force, hessian}: best seconds per thread count, bit-identity, and the 1-thread atomic baseline."""
    sim = box(c, 0.3)
    rng = np.random.default_rng(0)
    X = sim.model.mesh.vertices
    x = wp.array(X + 0.01 * rng.standard_normal(X.shape), dtype=wp.vec3d, device="cpu")
    el = sim._elastic
    acc = wp.zeros(64, dtype=wp.float64, device="cpu")
    el.bind(acc, 8)
    g = sim.ops.new_vector()
    vals = sim.new_matrix_values()
    S = sim.scalar_type
    fa = sim.ops.new_vector()

    def force():
        acc.zero_()
        g.zero_()
        el.gradient(None, x, 1.0, g, acc)

    def hessian():
        vals.zero_()
        el.assemble(x, 1.0, vals, project=True)

    qs = el.qp_sets[0]
    bi = el.pattern.block_indices[0]

    def force_atomic():  # the scatter the gather replaced (same kernel, slots 0), and the same dot
        acc.zero_()
        g.zero_()
        fa.zero_()
        launch(FK.qp_force_and_abs_kernel, qs.count, [x, qs.points, qs.material, S(-1.0), g, fa, 0], "cpu")
        launch(LK.dot_slot_kernel, sim.num_vertices, [fa, fa, wp.float64(1.0), acc, 10], "cpu")

    off, ent, slots = el._gather(qs)["force"]
    fp = sim.ops.new_vector()

    def force_previous():  # the force as it was split before (three split launches: points, gather, dot)
        acc.zero_()
        g.zero_()
        fp.zero_()
        launch(FK.qp_force_and_abs_kernel, qs.count, [x, qs.points, qs.material, S(-1.0), slots, slots, 1], "cpu")
        launch(FK.gather_force_kernel, off.shape[0] - 1, [off, ent, slots, g, fp, 1, FK.no_rows("cpu"), 0], "cpu")
        launch(LK.dot_slot_kernel, sim.num_vertices, [fp, fp, wp.float64(1.0), acc, 10], "cpu")

    def hessian_atomic():
        vals.zero_()
        launch(FK.qp_hessian_kernel, qs.count, [x, qs.points, qs.material, S(1.0), 1, bi, vals, 0], "cpu")

    out = {}
    for name, fn, base in (("force", force, force_atomic), ("hessian", hessian, hessian_atomic)):
        best = {k: np.full(3, np.inf) for k in (1, threads, "atomic")}  # wall, CPU, critical path
        results = {}
        for T in (1, threads):  # warm (kernel loads, maps) and the numbers of each thread count
            set_threads(T)
            fn()
            results[T] = (g.numpy().tobytes(), vals.numpy().tobytes(), acc.numpy().tobytes())
        set_threads(1)
        base()
        prev = force_previous if name == "force" else None
        for _ in range(repeats):
            for T in (1, threads):
                set_threads(T)
                best[T] = np.minimum(best[T], CP.measure(fn))
                if prev is not None:
                    prev()
                    best[("previous", T)] = np.minimum(best.get(("previous", T), np.inf), CP.measure(prev))
                    if T > 1:  # the other cut: points split evenly, then the gather (two dispatches, no seam)
                        seam, FORMS.FORCE_SEAM_MAX_POINTS = FORMS.FORCE_SEAM_MAX_POINTS, -1
                        fn()
                        best["two_phase"] = np.minimum(best.get("two_phase", np.inf), CP.measure(fn))
                        FORMS.FORCE_SEAM_MAX_POINTS = seam
            set_threads(1)
            best["atomic"] = np.minimum(best["atomic"], CP.measure(base))
        out[name] = dict(tets=qs.count, vertices=sim.num_vertices, seconds_1=best[1][0], seconds_p=best[threads][0],
                         speedup=best[1][0] / best[threads][0], cpu_seconds_1=best[1][1],
                         critical_seconds_p=best[threads][2], cpu_speedup=best[1][1] / best[threads][2],
                         atomic_seconds_1=best["atomic"][0], atomic_cpu_seconds_1=best["atomic"][1],
                         gather_over_atomic_1=best[1][0] / best["atomic"][0],
                         gather_over_atomic_cpu_1=best[1][1] / best["atomic"][1],
                         identical=results[1] == results[threads])
        if prev is not None:
            b1, bp = best[("previous", 1)], best[("previous", threads)]
            out[name].update(previous_seconds_1=b1[0], previous_seconds_p=bp[0], previous_speedup=b1[0] / bp[0],
                             previous_cpu_speedup=b1[1] / bp[2], new_p_over_previous_1=b1[0] / best[threads][0],
                             new_p_over_previous_1_cpu=b1[1] / best[threads][2],
                             two_phase_seconds_p=best["two_phase"][0],
                             two_phase_speedup=best[1][0] / best["two_phase"][0],
                             two_phase_cpu_speedup=best[1][1] / best["two_phase"][2],
                             seam=bool(el._force_plan(threads)[2]))
    return out


def step_case(make, threads, steps):
    """Step seconds with 1 and ``threads`` threads: one simulator each, alternate steps (the same
    steps), after one warm-up step each; bit-identity of the final positions."""
    sims = {}
    for T in (1, threads):
        set_threads(T)
        sims[T] = make()
        sims[T].step()  # warm-up: kernel loads, the solver's set-up
    secs = {1: [], threads: []}
    stats = None
    for _ in range(steps):
        for T in (1, threads):
            set_threads(T)
            gc.collect()  # not inside a timed step (the previous cases' arrays, the other simulator's garbage)
            res = {}
            secs[T].append(CP.measure(lambda: res.setdefault("st", sims[T].step())))
            stats = res["st"]
    same = sims[1].state.x.numpy().tobytes() == sims[threads].state.x.numpy().tobytes()
    s1, sp = (np.sum(secs[T], axis=0) for T in (1, threads))
    return dict(tets=sims[1].model.mesh.num_elements, vertices=sims[1].num_vertices, steps=steps,
                seconds_1=s1[0] / steps, seconds_p=sp[0] / steps, speedup=s1[0] / sp[0],
                cpu_seconds_1=s1[1] / steps, critical_seconds_p=sp[2] / steps, cpu_speedup=s1[1] / sp[2],
                newton_iterations=int(stats.newton_iterations), linear_iterations=int(stats.linear_iterations),
                linear_solver=getattr(sims[1].linear_solver, "name", None),
                chose=getattr(sims[1].linear_solver, "active", None), identical=same)


def amdahl(speedup, p):
    """(serial fraction, projected speed-ups on 8 and 16 cores) from a speed-up on p threads."""
    f = min(1.0, max(0.0, (p / speedup - 1.0) / (p - 1.0))) if speedup > 0 else 1.0
    return f, {n: 1.0 / (f + (1.0 - f) / n) for n in (8, 16)}


def probe(p, repeats):
    """What the machine gives p threads, apart from warpfem's code: (1) streaming memory bandwidth,
    numpy copies of 200 MB arrays on one thread and on p at once (numpy releases the GIL); (2) the
    elastic force's per-point kernel on the 192k-tet box, its whole range on one thread against p
    equal chunks launched at once through the pool (``warpfem.threads.run_chunks``), with each
    chunk's start delay and duration: a chunk that starts late or runs slower than alone shows the
    scheduling of the machine's cores, not the code."""
    import threading

    from warpfem.threads import run_chunks

    n = 25_000_000
    src = [np.ones(n) for _ in range(p)]
    dst = [np.empty(n) for _ in range(p)]

    def copy(i, reps=4):
        for _ in range(reps):
            np.copyto(dst[i], src[i])

    bw1, bwp = [], []
    gb = 4 * n * 8 * 2 / 1e9  # bytes read and written by one copy(i)
    for _ in range(repeats):
        t = time.perf_counter()
        copy(0)
        bw1.append(gb / (time.perf_counter() - t))
        th = [threading.Thread(target=copy, args=(i,)) for i in range(p)]
        t = time.perf_counter()
        for x in th:
            x.start()
        for x in th:
            x.join()
        bwp.append(p * gb / (time.perf_counter() - t))
    del src, dst
    gc.collect()
    sim = box(20, 0.3)
    el = sim._elastic
    qs = el.qp_sets[0]
    X = sim.model.mesh.vertices
    x = wp.array(X + 0.001 * np.random.default_rng(0).standard_normal(X.shape), dtype=wp.vec3d, device="cpu")
    slots = el._gather(qs)["force"][2]
    S = sim.scalar_type
    m = qs.count
    cuts = [m * k // p for k in range(p + 1)]
    marks = [None] * p

    def chunk(k, t0):
        def run():
            a = time.perf_counter()
            wp.launch(FK.qp_force_and_abs_kernel, dim=cuts[k + 1] - cuts[k], device="cpu",
                      inputs=[x, qs.points, qs.material, S(-1.0), slots, slots, 1, cuts[k]])
            marks[k] = (a - t0[0], time.perf_counter() - a)
        return run

    t0 = [0.0]
    fns = [chunk(k, t0) for k in range(p)]
    chunk(0, t0)()  # compile / load
    one, many, delays, spans = [], [], [], []
    for _ in range(max(repeats, 5) * 3):
        t = time.perf_counter()
        wp.launch(FK.qp_force_and_abs_kernel, dim=m, device="cpu",
                  inputs=[x, qs.points, qs.material, S(-1.0), slots, slots, 1, 0])
        one.append(time.perf_counter() - t)
        t0[0] = time.perf_counter()
        run_chunks(fns)
        many.append(time.perf_counter() - t0[0])
        delays.append(max(mk[0] for mk in marks))
        spans.append(max(mk[1] for mk in marks))
    q = lambda v: [float(np.min(v)), float(np.median(v)), float(np.max(v))]  # noqa: E731
    out = dict(copy_gb_s_1=q(bw1), copy_gb_s_p=q(bwp), copy_scaling_median=float(np.median(bwp) / np.median(bw1)),
               force_points=m, force_points_s_1=q(one), force_points_s_p=q(many),
               force_points_speedup_best=float(np.min(one) / np.min(many)),
               force_points_speedup_median=float(np.median(one) / np.median(many)),
               chunk_start_delay_s=q(delays), chunk_longest_s=q(spans))
    print(f"probe: memory copy {np.median(bw1):.1f} GB/s on 1 thread, {np.median(bwp):.1f} GB/s on {p} "
          f"({out['copy_scaling_median']:.2f}x); force points ({m}): 1 thread {np.min(one) * 1e3:.2f} ms best, "
          f"{np.median(one) * 1e3:.2f} median; {p} chunks {np.min(many) * 1e3:.2f} best, {np.median(many) * 1e3:.2f} "
          f"median, {np.max(many) * 1e3:.2f} worst ({out['force_points_speedup_best']:.2f}x best, "
          f"{out['force_points_speedup_median']:.2f}x median); the last chunk started {np.median(delays) * 1e3:.2f} ms "
          f"(median, worst {np.max(delays) * 1e3:.2f}) after the dispatch, the longest chunk took "
          f"{np.median(spans) * 1e3:.2f} ms (median, worst {np.max(spans) * 1e3:.2f})", flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--box-solver", default="multigrid")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--probe", action="store_true", help="only the machine probe (memory bandwidth and the force "
                    "kernel's chunks on p threads; results: threads_probe.json next to --out)")
    ap.add_argument("--out", default=str(ROOT / "kernels_bench" / "results" / "threads_cpu.json"))
    args = ap.parse_args(argv)
    p = int(args.threads)
    if p < 2:
        ap.error("--threads must be at least 2 (compared with 1)")
    if p > available_cores():
        print(f"note: {p} threads on {available_cores()} cores: the count is clamped to {available_cores()}")
        p = available_cores()
    global CP
    CP = CriticalPath()
    start_load = load()
    if args.probe:
        result = dict(device=f"cpu ({platform.machine()}, {os.cpu_count()} logical cores)", warp=wp.config.version,
                      threads=p, load_start=start_load, probe=probe(p, args.repeats), load_end=load())
        out = Path(args.out).with_name("threads_probe.json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {out.relative_to(ROOT) if out.is_relative_to(ROOT) else out.name}")
        return result
    rows = {"beam-864-step": step_case(beam, p, max(args.steps, 5))}  # first: no garbage of the big cases yet
    gc.collect()
    for c, tag in ((10, "24k"),) + (() if args.quick else ((20, "200k"),)):
        for name, row in assembly_case(c, p, args.repeats).items():
            rows[f"{name}-{tag}"] = row
            print(f"{name}-{tag}: {row['tets']} tets, 1 thread {row['seconds_1'] * 1e3:.2f} ms, {p} threads "
                  f"{row['seconds_p'] * 1e3:.2f} ms: {row['speedup']:.2f}x (CPU time / critical path "
                  f"{row['cpu_speedup']:.2f}x); atomic scatter on 1 thread {row['atomic_seconds_1'] * 1e3:.2f} ms "
                  f"(gather / atomic: wall {row['gather_over_atomic_1']:.2f}, CPU {row['gather_over_atomic_cpu_1']:.2f}); "
                  f"identical {row['identical']}", flush=True)
            if "previous_speedup" in row:
                print(f"  previous split (3 split launches): 1 thread {row['previous_seconds_1'] * 1e3:.2f} ms, {p} threads "
                      f"{row['previous_seconds_p'] * 1e3:.2f} ms: {row['previous_speedup']:.2f}x (CPU "
                      f"{row['previous_cpu_speedup']:.2f}x); now on {p} threads against it on 1: "
                      f"{row['new_p_over_previous_1']:.2f}x (CPU {row['new_p_over_previous_1_cpu']:.2f}x)", flush=True)
                print(f"  two dispatches (points, then gather; no seam): {p} threads {row['two_phase_seconds_p'] * 1e3:.2f} ms:"
                      f" {row['two_phase_speedup']:.2f}x (CPU {row['two_phase_cpu_speedup']:.2f}x); the default cut "
                      f"{'overlaps at the seam (one dispatch)' if row['seam'] else 'is these two dispatches'}", flush=True)
        gc.collect()
    if not args.quick:
        rows["box-98k-step"] = step_case(lambda: box(16, 0.49, args.box_solver), p, args.steps)
    for name in ("box-98k-step", "beam-864-step"):
        if name in rows:
            r = rows[name]
            print(f"{name}: {r['tets']} tets, 1 thread {r['seconds_1']:.3f} s/step, {p} threads {r['seconds_p']:.3f} "
                  f"s/step: {r['speedup']:.2f}x (CPU time / critical path {r['cpu_speedup']:.2f}x; "
                  f"{r['linear_solver']}, Newton {r['newton_iterations']}); identical {r['identical']}", flush=True)
    for name, r in rows.items():
        f, proj = amdahl(r["speedup"], p)
        fc, projc = amdahl(r["cpu_speedup"], p)
        r.update(serial_fraction=f, projected_8=proj[8], projected_16=proj[16], target=TARGETS.get(name),
                 met=bool(r["speedup"] >= TARGETS.get(name, 0.0)), cpu_serial_fraction=fc, cpu_projected_8=projc[8],
                 cpu_projected_16=projc[16])
    result = dict(device=f"cpu ({platform.machine()}, {os.cpu_count()} logical cores)", warp=wp.config.version,
                  cores=available_cores(), threads=p, precision="float64", load_start=start_load, load_end=load(),
                  rows=rows)
    lines = [f"# CPU threads: {p} against 1 ({result['device']}; load average {start_load} at the start, "
             f"{result['load_end']} at the end)", "",
             f"| case | tets | 1 thread | {p} threads | speed-up (wall) | speed-up (CPU / critical path) | target "
             "| serial fraction | 8 cores | 16 cores | identical |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        unit, k = ("s", 1.0) if name.endswith("step") else ("ms", 1e3)
        lines.append(f"| {name} | {r['tets']} | {r['seconds_1'] * k:.3g} {unit} | {r['seconds_p'] * k:.3g} {unit} | "
                     f"{r['speedup']:.2f}x | {r['cpu_speedup']:.2f}x | {r['target']}x | {r['serial_fraction']:.2f} "
                     f"({r['cpu_serial_fraction']:.2f}) | {r['projected_8']:.1f}x ({r['cpu_projected_8']:.1f}x) | "
                     f"{r['projected_16']:.1f}x ({r['cpu_projected_16']:.1f}x) | {r['identical']} |")
    lines.append("")
    lines.append("Serial fraction and projections from the wall-clock speed-up (in brackets: from the CPU-time "
                 "critical path).")
    print("\n".join(lines))
    set_threads(None)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out.relative_to(ROOT) if out.is_relative_to(ROOT) else out.name}")
    return result


if __name__ == "__main__":
    main()
