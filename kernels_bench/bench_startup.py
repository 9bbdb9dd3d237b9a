"""Start-up time: how long ``import warpfem`` and a small scene's way to its first step take, for the
working tree and for the code of earlier revisions, measured in the same run.

Per tree, each a fresh Python process (``sys.executable``):

  import      ``import warpfem`` timed inside the process (interpreter start-up not included)
  first step  ``import warpfem``, ``load_scene(SCENE).build(device="cpu")`` and one ``step()``, timed
              inside the process from before the import to after the step
  cli         wall time of the whole process ``python -m warpfem run SCENE --frames 1 --quiet``
              (USD output into a temporary folder), as a user sees it
  stages      the same command, per scene of ``--scenes`` (default the cantilever and the two-cube
              stack, a contact scene), with the time from the process's start to the first step's
              start split by stage (``startup_marks.py``: wall clock and the process's CPU time at
              each stage): interpreter, ``import warpfem``, command-line parsing, scene load and
              validation, build (output checks, Warp's initialisation, solver imports, mesh, model,
              simulator, colliders), outputs and progress set-up (the USD writer with its pxr
              import); then the first step itself and the process's exit; and, inside those, the
              pxr and scipy imports and Warp's module loads from the kernel cache

The revisions' code (``--before``, repeatable; default f92ae69, the last commit before the lazy
imports, and afe5c6e, the last before this benchmark's CLI stages were cut) is ``git archive``d into
temporary folders and put first on PYTHONPATH; the working tree's folder is put first for the
"after" runs. Warm: one untimed run of each command per tree first (Warp's kernel cache and
Python's bytecode cache filled; PYTHONDONTWRITEBYTECODE is removed from the children's environment,
so every tree runs from .pyc files as an installed package does). Then ``--repeats`` rounds, the
trees alternating, so that they see the same load; best and median reported (the best of each stage
separately: the stages' bests need not add up to the best total). CPU time is reported beside the
wall clock because a shared machine's load inflates it less.

    python kernels_bench/bench_startup.py                       # 5 rounds
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
DEFAULT_STAGE_SCENES = [DEFAULT_SCENE, os.path.join("examples", "scenes", "stack.toml")]
DEFAULT_BEFORE = ["f92ae69", "afe5c6e"]
MARKS_CODE_PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "startup_marks.py")

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

# (stage, from mark, to mark): the start-up of `warpfem run` in order; "spawn" is the parent's clock
# just before it started the process
STAGES = [("interpreter", "spawn", "python"), ("import warpfem", "python", "imported"),
          ("command-line parsing", "imported", "parsed"), ("scene load + validation", "parsed", "scene_loaded"),
          ("build", "scene_loaded", "built"), ("outputs + progress set-up", "built", "first_step"),
          ("to the first step", "spawn", "first_step"), ("the first step", "first_step", "first_step_done"),
          ("exit", "end", "exit"), ("process", "spawn", "exit")]
INSIDE = ["import_pxr", "import_scipy", "usd_writer", "warp_init", "mesh", "model", "warp_module_load"]


def cpu_name() -> str:
    """The processor as Python's ``platform`` names it."""
    return platform.processor() or platform.machine()


def child_env(tree: str) -> dict:
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.pop("WARPFEM_VERBOSE", None)
    env["PYTHONPATH"] = os.pathsep.join([tree, *filter(None, [os.environ.get("PYTHONPATH")])])
    return env


def _run_command(scene: str, outdir: str) -> list:
    return ["run", scene, "--frames", "1", "--quiet", "--out", os.path.join(outdir, "startup.usda")]


def measure(kind: str, tree: str, scene: str, outdir: str) -> dict:
    env = child_env(tree)
    if kind == "import":
        cmd = [sys.executable, "-c", IMPORT_CODE]
    elif kind == "first_step":
        cmd = [sys.executable, "-c", FIRST_STEP_CODE, scene]
    else:
        cmd = [sys.executable, "-m", "warpfem", *_run_command(scene, outdir)]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=outdir)
    wall = time.perf_counter() - t0
    if res.returncode:
        raise SystemExit(f"{kind} in {tree}: exit {res.returncode}\n{res.stderr[-2000:]}")
    out = {"process": wall}
    if kind != "cli":
        out.update(eval(res.stdout.strip().splitlines()[-1]))  # the dict printed by the child
    return out


def measure_stages(tree: str, scene: str, outdir: str) -> dict:
    """One ``warpfem run SCENE --frames 1`` process with the marks of ``startup_marks.py``: per stage
    of STAGES its wall and CPU seconds (CPU: the process's, from its start), and the INSIDE timers
    (wall seconds) before the first step and in all."""
    with open(MARKS_CODE_PATH, encoding="utf-8") as f:
        code = f.read()
    marks_json = os.path.join(outdir, "marks.json")
    if os.path.exists(marks_json):
        os.remove(marks_json)
    t_spawn = time.time()
    res = subprocess.run([sys.executable, "-c", code, marks_json, *_run_command(scene, outdir)],
                         capture_output=True, text=True, env=child_env(tree), cwd=outdir)
    t_exit = time.time()
    if res.returncode or not os.path.exists(marks_json):
        raise SystemExit(f"stages of {scene} in {tree}: exit {res.returncode}\n{res.stderr[-2000:]}")
    with open(marks_json, encoding="utf-8") as f:
        doc = json.load(f)
    marks = {k: tuple(v) for k, v in doc["marks"].items()}
    marks["spawn"] = (t_spawn, 0.0)
    marks["exit"] = (t_exit, None)
    out = {}
    for stage, a, b in STAGES:
        if a in marks and b in marks:
            (wa, ca), (wb, cb) = marks[a], marks[b]
            out[stage] = {"wall": wb - wa, "cpu": None if cb is None else cb - ca}
    for name in INSIDE:
        total = doc["inside"].get(name, [0.0, 0])
        before = doc["inside_at_first_step"].get(name, [0.0, 0])
        out[f"{name} (before the first step)"] = {"wall": before[0], "calls": before[1]}
        out[f"{name} (in all)"] = {"wall": total[0], "calls": total[1]}
    return out


def summarise(samples: list[dict]) -> dict:
    keys = samples[0].keys()
    return {k: {"best": min(s[k] for s in samples), "median": statistics.median(s[k] for s in samples)} for k in keys}


def summarise_stages(samples: list[dict]) -> dict:
    out = {}
    for key in samples[0]:
        out[key] = {}
        for field in samples[0][key]:
            values = [s[key][field] for s in samples if key in s and s[key].get(field) is not None]
            if values and field != "calls":
                out[key][field] = {"best": min(values), "median": statistics.median(values)}
            elif values:
                out[key][field] = max(values)
    return out


def _label(revision: str) -> str:
    return f"before {revision}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", action="append", default=None,
                   help=f"a revision to compare with (repeatable; default {' and '.join(DEFAULT_BEFORE)})")
    p.add_argument("--scene", default=DEFAULT_SCENE, help="scene of import/first step/cli, relative to the repository")
    p.add_argument("--scenes", nargs="+", default=DEFAULT_STAGE_SCENES,
                   help="scenes of the stages measure (default: the cantilever and the stack)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", help="write the results as JSON here")
    a = p.parse_args(argv)
    befores = a.before or DEFAULT_BEFORE

    scene = os.path.join(ROOT, a.scene)
    stage_scenes = {sc.replace(os.sep, "/"): os.path.join(ROOT, sc) for sc in a.scenes}
    kinds = ("import", "first_step", "cli")
    with tempfile.TemporaryDirectory() as tmp:
        outdir = os.path.join(tmp, "out")
        os.makedirs(outdir)
        trees, commits = {}, {}
        for k, rev in enumerate(befores):
            tree = os.path.join(tmp, f"before{k}")
            os.makedirs(tree)
            commits[_label(rev)] = extract_revision(rev, tree)
            trees[_label(rev)] = tree
        trees["after"] = ROOT
        for name, tree in trees.items():  # warm: kernel cache, bytecode
            for kind in kinds:
                measure(kind, tree, scene, outdir)
            for path in stage_scenes.values():
                measure_stages(tree, path, outdir)
        samples = {name: {k: [] for k in kinds} for name in trees}
        stage_samples = {name: {sc: [] for sc in stage_scenes} for name in trees}
        for _ in range(a.repeats):
            for kind in kinds:
                for name, tree in trees.items():
                    samples[name][kind].append(measure(kind, tree, scene, outdir))
            for sc, path in stage_scenes.items():
                for name, tree in trees.items():
                    stage_samples[name][sc].append(measure_stages(tree, path, outdir))

    results = {name: {k: summarise(v) for k, v in per.items()} for name, per in samples.items()}
    stages = {name: {sc: summarise_stages(v) for sc, v in per.items()} for name, per in stage_samples.items()}
    machine = {"device": "cpu", "cpu": cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(),
               "load": round(os.getloadavg()[0], 2)}
    names = list(trees)
    rows = [("import warpfem (in process)", "import", "import"),
            ("to the first step (import + build + step)", "first_step", "first_step"),
            ("  of which build", "first_step", "build"),
            ("  of which the first step", "first_step", "step"),
            ("warpfem run --frames 1 (process)", "cli", "process")]
    print(f"start-up, {a.scene}; " + ", ".join(f"{n} = {commits[n][:10]}" for n in names if n in commits)
          + f", after = working tree; {machine['cpu']}, {machine['cores']} cores, load {machine['load']}; "
          f"best (median) of {a.repeats}, seconds")
    print(f"{'':45s}" + "".join(f"{n:>22s}" for n in names) + "".join(f"{'after/' + n.split()[-1]:>16s}" for n in names[:-1]))
    for label, kind, key in rows:
        vals = [results[n][kind][key] for n in names]
        print(f"{label:45s}" + "".join(f"{v['best']:13.3f} ({v['median']:6.3f})" for v in vals)
              + "".join(f"{vals[-1]['best'] / v['best']:16.2f}" for v in vals[:-1]))
    for sc in stage_scenes:
        print(f"\nwarpfem run {sc} --frames 1: stages, wall / CPU seconds, best (median CPU) of {a.repeats}")
        print(f"{'':45s}" + "".join(f"{n:>28s}" for n in names))
        for stage, _, _ in STAGES:
            cells = []
            for n in names:
                st = stages[n][sc].get(stage, {})
                w, c = st.get("wall"), st.get("cpu")
                cells.append("" if w is None else f"{w['best']:7.3f} / " + ("   -  " if c is None else
                             f"{c['best']:6.3f} ({c['median']:5.3f})"))
            print(f"{stage:45s}" + "".join(f"{c:>28s}" for c in cells))
        for name in INSIDE:
            key = f"{name} (before the first step)"
            cells = [stages[n][sc].get(key, {}).get("wall", {}).get("best") for n in names]
            print(f"{'  ' + key:45s}" + "".join(f"{'' if c is None else f'{c:7.3f}':>28s}" for c in cells))
    if a.out:
        doc = {"scene": a.scene.replace(os.sep, "/"), "stage_scenes": list(stage_scenes),
               "trees": {n: ({"revision": n.split()[-1], "commit": commits[n]} if n in commits else "working tree")
                         for n in names},
               "repeats": a.repeats, "machine": machine, "seconds": results, "stages": stages}
        with open(a.out, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
