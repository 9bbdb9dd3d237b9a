"""Run the whole benchmark suite and write kernels_bench/results/summary.{json,md}.

Each benchmark runs as its own subprocess (so one failure or time-out does not stop the others; the
Warp kernel cache is shared, so only the first run of a module compiles it), its stdout goes to
``results/<name>.log`` and its JSON/markdown (where the script writes one) next to it:

  kernels-float32, kernels-float64  bench_kernels.py   every kernel family, items/s, bandwidth, numpy baseline
  forces                            bench_forces.py    force and Hessian throughput vs numpy
  assembly                          bench_assembly.py  force vs Hessian Mtets/s, where the Hessian's time goes
  warping                           bench_warping.py   stiffness warping vs Newton, cost and error
  elements                          bench_elements.py  Tet4/Tet10/Hex8/Hex27 accuracy per second
  reduced                           bench_reduced.py   reduced (cubature) vs full steps
  stability                         stability.py       stability at the extremes, every material
  integrators                       bench_integrators.py  error vs dt and wall time per time integrator
  solver-overhead                   bench_solver_overhead.py  launches / read-backs / ms per Newton step vs a baseline
  peer-vbd                          bench_peer_vbd.py  warpfem vs newton's VBD on the cantilever (skips without newton)
  contact-cost                      bench_contact_cost.py  Newton iterations and seconds per free vs contact frame,
                                    before = e18de72's code (git archive, a subprocess) / after = the working tree
                                    (needs git; skips without ipctk; quick: box_drop and stack, few frames)
  threads                           bench_threads.py   CPU threads: 2 against 1 on assembly and steps, Amdahl projection
                                    (CPU only; quick: the 24k-tet assembly and the 864-tet beam)

``--quick`` shrinks every benchmark (about 5 minutes on 2 idle CPU cores); ``--only`` / ``--skip`` take
comma-separated names (with ``--only`` the other entries of an existing summary of the same mode and
device are kept, marked with the time of their run). The summary records the device, the load average before and after (the
numbers are only comparable within one run), each benchmark's status, time and results.

    .venv/bin/python kernels_bench/run_all.py [--quick] [--device cpu] [--out kernels_bench/results]
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # this checkout's warpfem (for warpfem.paths only)
from warpfem.paths import portable_message, portable_path  # noqa: E402


def shown_command(cmd) -> str:
    """The command as the summary records it: no absolute path of this machine (see warpfem.paths)."""
    return " ".join(portable_path(a) if os.path.isabs(a) else a for a in cmd[1:])


def flags(script: str, candidates):
    """The (flag, value...) groups whose flag the script's source defines: the other benchmarks' options
    change as they evolve, and an unknown flag would stop them."""
    src = (HERE / script).read_text()
    chosen = []
    for group in candidates:
        if f'"{group[0]}"' in src:
            chosen += list(group)
    return chosen


def plan(args, out: Path):
    """(name, argv, json path or None, markdown path or None) for every benchmark."""
    q = args.quick
    dev = ["--device", args.device]
    py = [sys.executable]
    P = []
    for prec in ("float32", "float64"):
        j, m = out / f"kernels_{prec}.json", out / f"kernels_{prec}.md"
        P.append((f"kernels-{prec}", py + [str(HERE / "bench_kernels.py"), *dev, "--precision", prec, "--json", str(j),
                                           "--markdown", str(m)] + (["--quick"] if q else []), j, m))
    j = out / "forces.json"
    P.append(("forces", py + [str(HERE / "bench_forces.py"), *dev, "--json", str(j)]
              + (["--cells", "40", "10", "10", "--repeats", "5"] if q else []), j, None))
    j = out / "assembly_cpu.json" if args.device == "cpu" else out / f"assembly_{args.device.replace(':', '')}.json"
    P.append(("assembly", py + [str(HERE / "bench_assembly.py"), *dev, "--json", str(j)]
              + (["--sizes", "40,10,10", "--batches", "3"] if q else []), j, None))
    j = out / "warping.json"
    P.append(("warping", py + [str(HERE / "bench_warping.py"), *dev, "--json", str(j)]
              + (["--steps", "10", "--refine", "4"] if q else []), j, None))
    P.append(("elements", py + [str(HERE / "bench_elements.py"), *dev] + (["--quick"] if q else []), None, None))
    quick_reduced = [("--quick",)] if '"--quick"' in (HERE / "bench_reduced.py").read_text() else [
        ("--objects", "beam"), ("--steps", "10"), ("--beam-steps", "10"), ("--modes", "10"), ("--tols", "0.05"),
        ("--poses", "random")]
    P.append(("reduced", py + [str(HERE / "bench_reduced.py")] + flags("bench_reduced.py", [("--device", args.device)])
              + (flags("bench_reduced.py", quick_reduced) if q else []), None, None))
    j, m = out / "stability.json", out / "stability.md"
    P.append(("stability", py + [str(HERE / "stability.py")]
              + flags("stability.py", [("--device", args.device), ("--json", str(j)), ("--markdown", str(m))]
                      + ([("--quick",)] if q else [])), j, m))
    j = out / "integrators.json"
    P.append(("integrators", py + [str(HERE / "bench_integrators.py"), *dev, "--json", str(j)]
              + (["--quick"] if q else []), j, None))
    j = out / "solver_overhead.json"
    P.append(("solver-overhead", py + [str(HERE / "bench_solver_overhead.py"), *dev, "--json", str(j)]
              + (["--steps", "10"] if q else []), j, None))
    j = out / "adjoint.json"
    P.append(("adjoint", py + [str(HERE / "bench_adjoint.py"), *dev, "--json", str(j)]
              + (["--steps", "5", "--integrators", "backward_euler"] if q else []), j, None))
    j, m = out / "scale.json", out / "scale.md"
    P.append(("scale", py + [str(HERE / "bench_scale.py"), *dev, "--out", str(out / "scale")]
              + (["--quick"] if q else ["--bunny"]), j, m))
    j, m = out / "peer_vbd.json", out / "peer_vbd.md"
    P.append(("peer-vbd", py + [str(HERE / "bench_peer_vbd.py"), *dev, "--json", str(j), "--markdown", str(m)]
              + (["--quick"] if q else []), j, m))
    j, m = out / "contact_cost.json", out / "contact_cost.md"
    P.append(("contact-cost", py + [str(HERE / "bench_contact_cost.py"), *dev, "--json", str(j), "--md", str(m)]
              + (["--cases", "box_drop,stack", "--frames", "box_drop=15,stack=6", "--precision", "float64", "--repeats", "2"]
                 if q else []),
              j, m))
    if str(args.device).startswith("cpu"):  # CPU threads: 2 against 1 (CUDA launches are not split)
        j = out / "threads_cpu.json"
        P.append(("threads", py + [str(HERE / "bench_threads.py"), "--out", str(j)]
                  + (["--quick", "--repeats", "3"] if q else []), j, None))
    return P


def table_lines(text: str) -> str:
    """The markdown-table lines (and the line just before each table) of a benchmark's stdout."""
    lines = text.splitlines()
    keep = []
    for i, ln in enumerate(lines):
        if ln.startswith("|"):
            if i > 0 and not lines[i - 1].startswith("|") and lines[i - 1].strip():
                keep += ["", lines[i - 1], ""]
            keep.append(ln)
    return "\n".join(keep)


def plain_block(text: str, max_lines: int = 40) -> str:
    """A benchmark's fixed-width stdout as a code block (Warp's start-up and module-load lines dropped)."""
    noise = ("Module ", "Warp ", "   CUDA", "   Devices", "     \"", "   Kernel cache", "     /")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith(noise)]
    return "```\n" + "\n".join(lines[-max_lines:]) + "\n```" if lines else ""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="small sizes everywhere (about 5 minutes on 2 cores)")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--only", default="", help="comma-separated benchmark names to run")
    ap.add_argument("--skip", default="", help="comma-separated benchmark names to leave out")
    ap.add_argument("--timeout", type=float, default=None, help="seconds per benchmark (default 420 quick, 1800 full)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    timeout = args.timeout or (420.0 if args.quick else 1800.0)
    only = {s for s in args.only.split(",") if s}
    skip = {s for s in args.skip.split(",") if s}
    env = dict(os.environ, PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.setdefault("MPLBACKEND", "Agg")

    summary = dict(started=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), device=args.device,
                   host=f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {platform.system()}",
                   python=platform.python_version(), quick=args.quick, load_average_before=os.getloadavg(), benchmarks=[])
    t_all = time.perf_counter()
    for name, cmd, jpath, mpath in plan(args, out):
        if (only and name not in only) or name in skip:
            continue
        print(f"[run_all] {name}: {shown_command(cmd)}", flush=True)
        log = out / f"{name}.log"
        t0 = time.perf_counter()
        try:
            p = subprocess.run(cmd, cwd=HERE.parent, env=env, capture_output=True, text=True, timeout=timeout)
            status = "ok" if p.returncode == 0 else f"failed (exit {p.returncode})"
            stdout, stderr = p.stdout, p.stderr
        except subprocess.TimeoutExpired as exc:
            status = f"timed out after {timeout:.0f} s"
            stdout = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
            stderr = exc.stderr.decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        secs = time.perf_counter() - t0
        stdout, stderr = portable_message(stdout), portable_message(stderr)  # e.g. Warp's kernel cache: ~/.cache/...
        if "SKIP:" in stdout:
            status = "skipped: " + stdout.split("SKIP:", 1)[1].strip().splitlines()[0]
        log.write_text(stdout + ("\n--- stderr ---\n" + stderr if stderr.strip() else ""))
        entry = dict(name=name, command=shown_command(cmd), status=status, seconds=round(secs, 1), log=portable_path(log),
                     run_started=summary["started"])
        if jpath is not None and Path(jpath).exists() and Path(jpath).stat().st_mtime >= time.time() - secs - 1:
            try:
                entry["results"] = json.loads(Path(jpath).read_text())
            except json.JSONDecodeError as exc:
                entry["results_error"] = str(exc)
        if mpath is not None and Path(mpath).exists() and Path(mpath).stat().st_mtime >= time.time() - secs - 1:
            entry["markdown"] = Path(mpath).read_text()
        else:
            entry["markdown"] = table_lines(stdout) or plain_block(stdout)
        if status != "ok":
            entry["stderr_tail"] = "\n".join(stderr.strip().splitlines()[-15:])
        summary["benchmarks"].append(entry)
        print(f"[run_all] {name}: {status} in {secs:.0f} s", flush=True)
    summary["seconds"] = round(time.perf_counter() - t_all, 1)
    old_path = out / "summary.json"
    if only and old_path.exists():  # a partial re-run: keep the other benchmarks' entries of the last summary
        old = json.loads(old_path.read_text())
        if old.get("quick") == args.quick and old.get("device") == args.device:
            done = {b["name"] for b in summary["benchmarks"]}
            kept = [b for b in old.get("benchmarks", []) if b["name"] not in done]
            for b in kept:
                b["status"] = b["status"].split(" (from the run of")[0]
                b.setdefault("run_started", old["started"])
            order = [name for name, *_ in plan(args, out)]
            summary["benchmarks"] = sorted(summary["benchmarks"] + kept, key=lambda b: order.index(b["name"]) if b["name"] in order else 99)
            summary["seconds"] += sum(b["seconds"] for b in kept)
    summary["load_average_after"] = os.getloadavg()
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    (out / "summary.md").write_text(markdown(summary))
    print(f"[run_all] wrote {out / 'summary.json'} and {out / 'summary.md'} ({summary['seconds']:.0f} s)")
    bad = [b["name"] for b in summary["benchmarks"] if not (b["status"].startswith("ok") or b["status"].startswith("skipped"))]
    return 1 if bad else 0


def markdown(s):
    L = ["# warpfem benchmark summary", "",
         f"Run {s['started']} on device `{s['device']}` ({s['host']}), python {s['python']}, "
         f"{'quick' if s['quick'] else 'full'} mode, {s['seconds']:.0f} s in all. Load average (1, 5, 15 min) before "
         f"{tuple(round(x, 2) for x in s['load_average_before'])}, after {tuple(round(x, 2) for x in s['load_average_after'])}: "
         "timings are comparable within this run only.", "",
         "| benchmark | status | seconds | run started (UTC) |", "|---|---|---|---|"]
    for b in s["benchmarks"]:
        L.append(f"| {b['name']} | {b['status']} | {b['seconds']:.0f} | {b.get('run_started', s['started'])} |")
    for b in s["benchmarks"]:
        L += ["", f"## {b['name']}", "", f"`{b['command']}`", ""]
        if b.get("markdown"):
            L.append(b["markdown"].strip())
        if b.get("stderr_tail"):
            L += ["", "```", b["stderr_tail"], "```"]
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    sys.exit(main())
