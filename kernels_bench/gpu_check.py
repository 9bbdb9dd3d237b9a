"""The GPU check (``make gpu-check``): on a machine with a CUDA device, in at most 8 minutes, run the
device test subset (tests/device_subset.txt) on it and the force/assembly, step-pipeline, scale and
peer benchmarks, each with its JSON in ``kernels_bench/results/cuda/``, and a summary
``gpu_check.json`` (what ran, its status and seconds). Without a CUDA device it prints one line and
runs nothing (exit status 0).

Each stage is a subprocess with its own time limit, cut to what is left of the total budget
(``--budget``, 480 s): a stage that does not fit is recorded as skipped, one that fails or runs
out of time as such, and the next stage runs.

    .venv/bin/python kernels_bench/gpu_check.py [--device cuda:0] [--out kernels_bench/results/cuda] [--budget 480]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))  # this checkout's warpfem

from warpfem.paths import portable_message, portable_path  # noqa: E402

#: (name, seconds allowed) of each stage, in order; the sum stays under the 8-minute budget
STAGES = (("tests", 200), ("forces", 40), ("assembly", 60), ("step-pipeline", 45), ("scale", 70), ("peer-vbd", 50))
#: the benchmarks run_all.py knows (run through it, ``--quick``)
RUN_ALL = ("forces", "assembly", "scale", "peer-vbd")


def cuda_devices() -> int:
    """CUDA devices Warp sees here (0 without an NVIDIA driver or GPU); quiet."""
    from warpfem.device import init_warp

    init_warp("cpu")
    import warp as wp

    return int(wp.get_cuda_device_count())


def device_subset():
    lines = (ln.split("#", 1)[0].strip() for ln in (ROOT / "tests" / "device_subset.txt").read_text().splitlines())
    return [ln for ln in lines if ln]


def plan(device: str, out: Path):
    """{stage name: argv} (relative to the repository root)."""
    py = sys.executable
    cmds = {"tests": [py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--device", device, *device_subset()]}
    for name in RUN_ALL:
        cmds[name] = [py, str(HERE / "run_all.py"), "--device", device, "--quick", "--only", name, "--out", str(out),
                      "--timeout", str(dict(STAGES)[name])]
    cmds["step-pipeline"] = [py, str(HERE / "bench_step_pipeline.py"), "--device", device, "--baseline", "",
                             "--steps", "10", "--json", str(out / "step_pipeline.json")]
    return cmds


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--out", default=str(HERE / "results" / "cuda"))
    ap.add_argument("--budget", type=float, default=480.0, help="seconds for everything (default 8 minutes)")
    args = ap.parse_args(argv)
    count = cuda_devices()
    if count == 0:
        print("gpu-check: no CUDA device here (no NVIDIA driver or GPU); nothing run")
        return 0
    if not (args.device.startswith("cuda:") and args.device[5:].isdigit() and int(args.device[5:]) < count):
        print(f"gpu-check: device {args.device!r} is not one of the {count} CUDA device(s) here (cuda:0 ...)")
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import warp as wp

    name = wp.get_device(args.device).name
    summary = dict(device=args.device, gpu=name, machine=platform.machine(), python=platform.python_version(),
                   warp=wp.config.version, budget_seconds=args.budget, stages=[])
    cmds = plan(args.device, out)
    t_start = time.perf_counter()
    env = dict(os.environ, WARPFEM_TEST_DEVICE=args.device)
    env.pop("WARPFEM_STRICT_DEVICE", None)  # the real device, not the CPU's imitation of one
    print(f"gpu-check on {args.device} ({name}), budget {args.budget:.0f} s; results in {portable_path(str(out))}")
    for stage, limit in STAGES:
        left = args.budget - (time.perf_counter() - t_start)
        entry = dict(name=stage, command=" ".join(portable_path(a) if os.path.isabs(a) else a for a in cmds[stage][1:]))
        if left < 15:
            entry.update(status="skipped", reason="no time left in the budget")
        else:
            t0 = time.perf_counter()
            log = out / f"gpu_check_{stage}.log"
            try:
                with open(log, "w") as f:
                    rc = subprocess.run(cmds[stage], cwd=ROOT, env=env, stdout=f, stderr=subprocess.STDOUT,
                                        timeout=min(limit, left)).returncode
                entry.update(status="ok" if rc == 0 else f"failed (exit {rc})")
            except subprocess.TimeoutExpired:
                entry.update(status=f"timed out after {min(limit, left):.0f} s")
            entry["seconds"] = round(time.perf_counter() - t0, 1)
            tail = [ln for ln in log.read_text(errors="replace").splitlines() if ln.strip()][-1:]
            entry["last_line"] = portable_message(tail[0][:300]) if tail else ""
        summary["stages"].append(entry)
        print(f"  {stage:14s} {entry['status']}" + (f" ({entry['seconds']} s): {entry['last_line']}" if "seconds" in entry else ""),
              flush=True)
    summary["seconds"] = round(time.perf_counter() - t_start, 1)
    (out / "gpu_check.json").write_text(json.dumps(summary, indent=1) + "\n")
    bad = [s["name"] for s in summary["stages"] if s["status"] != "ok"]
    print(f"gpu-check: {len(STAGES) - len(bad)} of {len(STAGES)} stages ok in {summary['seconds']:.0f} s"
          + (f"; not ok: {', '.join(bad)}" if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
