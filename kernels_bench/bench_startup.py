"""Start-up time: how long ``import warpfem`` and a small scene's way to its first step take, for the
working tree and for the code of an earlier revision, measured in the same run.

Three numbers per tree, each a fresh Python process (``sys.executable``):

  import      ``import warpfem`` timed inside the process (interpreter start-up not included)
  first step  ``import warpfem``, ``load_scene(SCENE).build(device="cpu")`` and one ``step()``, timed
              inside the process from before the import to after the step
  cli         wall time of the whole process ``python -m warpfem run SCENE --frames 1 --quiet``
              (USD output into a temporary folder), as a user sees it

The revision's code (``--before``, default f92ae69, the last commit before the lazy imports) is
``git archive``d into a temporary folder and put first on PYTHONPATH; the working tree's folder is
put first for the "after" runs. Warm: one untimed run of each command per tree first (Warp's kernel
cache and Python's bytecode cache filled; PYTHONDONTWRITEBYTECODE is removed from the children's
environment, so both trees run from .pyc files as an installed package does). Then ``--repeats``
rounds, the two trees alternating, so that both see the same load; best and median reported.

    python kernels_bench/bench_startup.py                       # cantilever (480 tets), 5 rounds
    python kernels_bench/bench_startup.py --out kernels_bench/results/startup.json
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

from revisions import ROOT, extract_revision  # noqa: E402  (kernels_bench/revisions.py)

DEFAULT_SCENE = os.path.join("examples", "scenes", "cantilever.toml")

IMPORT_CODE = """
import time
t0 = time.perf_counter()
import warpfem
print({"import": time.perf_counter() - t0})
"""

FIRST_STEP_CODE = """
import sys, time
t0 = time.perf_counter()
import warpfem
t1 = time.perf_counter()
from warpfem.scenes import load_scene
run = load_scene(sys.argv[1]).build(device="cpu", precision="float64")
t2 = time.perf_counter()
run.sim.step()
t3 = time.perf_counter()
print({"import": t1 - t0, "build": t2 - t1, "step": t3 - t2, "first_step": t3 - t0})
"""


def cpu_name() -> str:
    """The processor as Python's ``platform`` names it."""
    return platform.processor() or platform.machine()


def child_env(tree: str) -> dict:
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.pop("WARPFEM_VERBOSE", None)
    env["PYTHONPATH"] = os.pathsep.join([tree, *filter(None, [os.environ.get("PYTHONPATH")])])
    return env


def measure(kind: str, tree: str, scene: str, outdir: str) -> dict:
    env = child_env(tree)
    if kind == "import":
        cmd = [sys.executable, "-c", IMPORT_CODE]
    elif kind == "first_step":
        cmd = [sys.executable, "-c", FIRST_STEP_CODE, scene]
    else:
        cmd = [sys.executable, "-m", "warpfem", "run", scene, "--frames", "1", "--quiet",
               "--out", os.path.join(outdir, "startup.usda")]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=outdir)
    wall = time.perf_counter() - t0
    if res.returncode:
        raise SystemExit(f"{kind} in {tree}: exit {res.returncode}\n{res.stderr[-2000:]}")
    out = {"process": wall}
    if kind != "cli":
        out.update(eval(res.stdout.strip().splitlines()[-1]))  # the dict printed by the child
    return out


def summarise(samples: list[dict]) -> dict:
    keys = samples[0].keys()
    return {k: {"best": min(s[k] for s in samples), "median": statistics.median(s[k] for s in samples)} for k in keys}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", default="f92ae69", help="the revision to compare with (default f92ae69)")
    p.add_argument("--scene", default=DEFAULT_SCENE, help="scene file, relative to the repository (default cantilever)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", help="write the results as JSON here")
    a = p.parse_args(argv)

    scene = os.path.join(ROOT, a.scene)
    kinds = ("import", "first_step", "cli")
    with tempfile.TemporaryDirectory() as tmp:
        before_tree, outdir = os.path.join(tmp, "before"), os.path.join(tmp, "out")
        os.makedirs(before_tree)
        os.makedirs(outdir)
        commit = extract_revision(a.before, before_tree)
        trees = {"before": before_tree, "after": ROOT}
        for name, tree in trees.items():  # warm: kernel cache, bytecode
            for kind in kinds:
                measure(kind, tree, scene, outdir)
        samples = {name: {k: [] for k in kinds} for name in trees}
        for _ in range(a.repeats):
            for kind in kinds:
                for name, tree in trees.items():
                    samples[name][kind].append(measure(kind, tree, scene, outdir))

    results = {name: {k: summarise(v) for k, v in per.items()} for name, per in samples.items()}
    machine = {"device": "cpu", "cpu": cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(),
               "load": round(os.getloadavg()[0], 2)}
    rows = [("import warpfem (in process)", "import", "import"),
            ("to the first step (import + build + step)", "first_step", "first_step"),
            ("  of which build", "first_step", "build"),
            ("  of which the first step", "first_step", "step"),
            ("warpfem run --frames 1 (process)", "cli", "process")]
    print(f"start-up, {a.scene}; before = {a.before} ({commit[:10]}), after = working tree; "
          f"{machine['cpu']}, {machine['cores']} cores, load {machine['load']}; best (median) of {a.repeats} s")
    print(f"{'':45s} {'before':>16s} {'after':>16s} {'after/before':>13s}")
    for label, kind, key in rows:
        b, f = results["before"][kind][key], results["after"][kind][key]
        print(f"{label:45s} {b['best']:7.3f} ({b['median']:6.3f}) {f['best']:7.3f} ({f['median']:6.3f}) "
              f"{f['best'] / b['best']:13.2f}")
    if a.out:
        doc = {"scene": a.scene.replace(os.sep, "/"), "before": {"revision": a.before, "commit": commit},
               "after": "working tree", "repeats": a.repeats, "machine": machine, "seconds": results}
        with open(a.out, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
