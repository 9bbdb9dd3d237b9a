"""What contact with friction costs against free motion: Newton iterations and seconds per frame in
free fall and in contact, on a collider drop and the example contact scenes, under named solver
configurations run one after the other ("before" and "after" in one run): settings of the working
tree's code (run in this process), or the code of a git revision (each run a subprocess importing
that revision's warpfem, extracted into a temporary folder).

Cases (``--cases``; each runs from its start, default frame counts chosen to include the free fall
and the impact within a few minutes on 2 CPU cores; ``--frames N`` or ``--frames case=N,...``):

  box_drop       a soft 0.2 m box (4^3 cells, 384 tets, stable neo-Hookean E 1e5, nu 0.3, 1000 kg/m^3)
                 dropped from 10 cm onto a floor plane (friction 0.3), backward Euler, dt 1/240 s,
                 4 steps per frame (60 fps), max_iters 100; it lands in frame ~9
  bunny_drop     examples/scenes/bunny_drop.toml (Newmark, 5 steps per frame at 48 fps; lands in frame 7;
                 its impact frames take 300-550 Newton iterations, 20-40 s each on 2 CPU cores)
  stack          examples/scenes/stack.toml (4 steps per frame; the lower cube, 5 mm above the floor, lands
                 in frame 1: no free frame; the upper one lands in frame 6)
  ball_bowl      examples/scenes/ball_bowl.toml (4 steps per frame; the bowl, 5 mm above the floor, lands
                 in frame 1: no free frame)
  twisted_bar    examples/scenes/twisted_bar.toml (1 step per frame; self contact from frame ~62, as the
                 bar coils)
  bunny_octopus  examples/scenes/bunny_octopus.toml (4 steps per frame; self, body-body and floor contact
                 from frame 2)

A frame is "contact" when, at its start or after any of its steps, a surface vertex is within its
collider's dhat of a collider or a surface contact pair (the candidates of ``sim.surface_contact``;
self pairs already closer than dhat at rest, which get no barrier, are not among them) is within
dhat; otherwise "free". Per case, configuration and precision it reports Newton iterations per
frame (the sum over the frame's steps; mean and max, free and contact, and the ratio contact/free),
wall seconds per frame (the steps only: the checks are not timed; one discarded step of each case and
precision after ``wp.force_load`` of every module, and frame 1, which pays the new simulator's set-up, is left out
of the time means unless it is the only free (contact) frame; mean over free and over contact
frames, the ratio, and each contact frame's time over the time of one Hessian assembly
``sim.assemble_stiffness`` of the same mesh, best of batches at the run's final state, measured in
the same run), line-search halvings, steps that did not converge, friction re-solves, and whether
any frame intersects: IPC Toolkit's ``ipctk.has_intersections`` on the boundary surface for scenes
with surface contact (``ipctk``, the test extra, imported only then), and for every collider
whether a surface vertex is at distance <= 0 from it (``sim.contact.distances()``). Process CPU
times are recorded next to the wall times (a shared machine inflates them less).

Configurations (``--configs``; default before,after) are the entries of ``CONFIGS`` below: "before",
the code of e18de72 (the last commit before the friction solver changes: no stick/slip-aware Newton
step, friction re-solves), "after", the working tree, "before_closest", the code of f4b9087 (the
friction filter cut only the steps through the sticking zone), "after_no_filter", the working tree with
``friction_filter=False``, "after_no_extrapolation" with ``extrapolate=False``, "after_step_tol" with the
Newton step test ``step_tol=1e-3`` (body diagonals per second), "update_always" with friction's lag
updated inside the solve in every step (``friction_update_tol=0``, the default), "update_25" and
"update_50" with ``friction_update_tol=0.25`` and ``0.5``, "lag_once" (also "after_lag_once") with friction
lagged once from the step start (``friction_iterations=0``), "after_mu0" with friction 0 on every
collider and on surface contact (the key "friction"), "after_pin" / "after_no_pin" with ``friction_pin``
3 (the default) / 0, "eta_F" (F in 0.5, 0.3, 0.2, 0.1, 0.05, 0.02) with the collision step bound's
fraction (``STEP_ETA`` of ``warpfem.contact.contact`` and ``warpfem.contact.surface``, restored before
every run) set to F for colliders and surface pairs, "eta_cF" / "eta_sF" (F in 0.1, 0.05, 0.02) for
colliders / surface pairs alone, "mu0_eta_F" (F in 0.5, 0.2, 0.05, 0.02) with friction 0 too. A configuration with a "revision" runs in workers: ``git archive REV`` of
this repository extracted into a temporary folder (git needed), each case and precision then the
hidden ``--_worker OUT.json`` of this script with that folder first on PYTHONPATH; the worker checks
that ``warpfem.__file__`` is in that folder, and the outputs record per configuration the code that
ran (revision and commit, or "working tree" and its HEAD) and the warpfem path. Warp's kernel cache is
the default, shared one (the revision's kernels compile once). Every second and further
configuration is also reported as a ratio against the first (the baseline of the same run): Newton
iterations per contact and free frame, line-search halvings, seconds per frame.
``--repeats N`` runs each case, configuration and precision N times (configurations interleaved) and
keeps each frame's smallest time: on a shared machine identical configurations differ by 20-30 %
in a single run.

    .venv/bin/python kernels_bench/bench_contact_cost.py [--cases box_drop,stack] [--frames 15]
        [--precision float64,float32] [--configs before,after] [--repeats 1] [--device cpu] [--json PATH] [--md PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import gc
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# a worker (``--_worker``, a configuration with a "revision") imports warpfem from the extracted tree
# that its PYTHONPATH puts first, never from this one
_WORKER = "--_worker" in sys.argv[1:]
if not _WORKER:
    sys.path.insert(0, ROOT)

import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402
from revisions import extract_revision, working_tree_commit  # noqa: E402  (kernels_bench/revisions.py)
from warpfem.solvers.nonlinear import NewtonOptions  # noqa: E402

# Named solver configurations, each applied to the built simulator before its first step. The key
# "revision" (a git revision of this repository) runs the configuration on that revision's code: the
# revision is extracted into a temporary folder (``git archive``) and each of the configuration's
# runs is a subprocess of this script with that folder first on its PYTHONPATH, so that ``import
# warpfem`` there imports the old code (checked, and recorded with each run); without "revision" the
# runs are in this process, on the working tree. A key that is a NewtonOptions field (tol,
# max_iters, max_line_search, hessian_projection, friction_filter, ...) is set on ``sim.options``
# (validated); any other key must be an existing attribute of the simulator (e.g.
# ``friction_iterations``, ``friction_tol``, ``initial_guess``) and is set on ``sim``; an unknown key
# raises, except that under a "revision" a key the working tree knows but that revision's code does
# not is skipped, with a note in the results.
CONFIGS: dict[str, dict] = {
    # the code before the friction solver changes (stick/slip-aware Newton step, linear-spring
    # sticking zone, friction lag updated inside the solve): e18de72, the last commit before them
    "before": {"revision": "e18de72"},
    # the working tree with its defaults (friction_filter on, friction lagged again inside the solve)
    "after": {},
    # the code before the friction filter cut every step that goes past its point closest to u = 0
    # (it cut only the steps through the sticking zone): f4b9087, the last commit before that change
    "before_closest": {"revision": "f4b9087"},
    # the working tree without the stick/slip-aware Newton step for collider friction
    "after_no_filter": {"friction_filter": False},
    "after_no_extrapolation": {"extrapolate": False},
    # the working tree with the Newton step test on (NewtonOptions.step_tol, off by default)
    "after_step_tol": {"step_tol": 1e-3},
    # friction's lag update inside the solve made whenever the lag changes (friction_update_tol 0, the
    # default), only above 25 % / 50 % of the largest normal force, never
    "update_always": {"friction_update_tol": 0.0},
    "update_25": {"friction_update_tol": 0.25},
    "update_50": {"friction_update_tol": 0.5},
    "lag_once": {"friction_iterations": 0},
    # friction's lag update inside the solve made at an iterate whose relative gradient is below 0.1 /
    # 0.3 of the step's start instead of 1e-2 (Simulator(friction_lag_below=...), docs/contact.md)
    "lag_below_0.1": {"friction_lag_below": 0.1},
    "lag_below_0.3": {"friction_lag_below": 0.3},
    # the split of a contact frame's cost (docs/contact.md, "What an impact step costs"): friction off
    # (mu = 0 on every collider and surface contact), friction lagged once from the step start, the
    # stick/slip-aware step off
    "after_mu0": {"friction": 0.0},
    "after_lag_once": {"friction_iterations": 0},
    # the friction filter's cut contacts pinned in a second Newton solve (NewtonOptions.friction_pin,
    # docs/contact.md "What an impact step costs"): on (3, the default since it was measured), off
    "after_pin": {"friction_pin": 3.0},
    "after_no_pin": {"friction_pin": 0.0},
    # the pin's second solve from zero, as first built, instead of warm-started from the filtered
    # direction (module constant PIN_WARM_START of warpfem.solvers.forms)
    "pin_cold_start": {"pin_warm_start": False},
    # the collision step bound's fraction of each gap it keeps (the line search's first step, module
    # constants STEP_ETA of warpfem.contact.contact for colliders and warpfem.contact.surface for
    # surface pairs; docs/contact.md "What an impact step costs"): both, colliders only, surface only
    **{f"eta_{e}": {"collider_step_eta": v, "surface_step_eta": v} for e, v in
       (("0.5", 0.5), ("0.3", 0.3), ("0.2", 0.2), ("0.1", 0.1), ("0.05", 0.05), ("0.02", 0.02))},
    **{f"eta_c{e}": {"collider_step_eta": v} for e, v in (("0.1", 0.1), ("0.05", 0.05), ("0.02", 0.02))},
    **{f"eta_s{e}": {"surface_step_eta": v} for e, v in (("0.1", 0.1), ("0.05", 0.05), ("0.02", 0.02))},
    # the same without friction (mu = 0 everywhere): the barrier's approach alone
    **{f"mu0_eta_{e}": {"friction": 0.0, "collider_step_eta": v, "surface_step_eta": v} for e, v in
       (("0.5", 0.5), ("0.2", 0.2), ("0.05", 0.05), ("0.02", 0.02))},
}
#: configuration keys that set a module constant (module, name), restored to its import value before
#: every run so that configurations run one after the other in one process do not leak into each other
MODULE_KEYS = {"pin_warm_start": ("warpfem.solvers.forms", "PIN_WARM_START"),
               "collider_step_eta": ("warpfem.contact.contact", "STEP_ETA"),
               "surface_step_eta": ("warpfem.contact.surface", "STEP_ETA")}
_MODULE_DEFAULTS: dict = {}

#: where the example scenes are read: this tree's, or in a worker the extracted revision's
SCENE_DIR = os.path.join(ROOT, "examples", "scenes")
#: which code runs in this process: "working tree", or in a worker "revision REV (COMMIT)"
TREE = "working tree"
TREE_PATH = None  # the extracted revision's folder in a worker


def portable_path(path):
    """A path as the results record it (no absolute path of a machine): repository-relative for this
    tree, "<revision>/..." inside an extracted revision."""
    p = os.path.realpath(path)
    if TREE_PATH is not None and os.path.commonpath([os.path.realpath(TREE_PATH), p]) == os.path.realpath(TREE_PATH):
        return f"<{TREE}>/" + os.path.relpath(p, os.path.realpath(TREE_PATH))
    root = os.path.realpath(ROOT)
    if os.path.commonpath([root, p]) == root:
        return os.path.relpath(p, root)
    return os.path.basename(p)

SCENES = {name: f"{name}.toml" for name in ("bunny_drop", "stack", "ball_bowl", "twisted_bar", "bunny_octopus")}
#: default frames per case (free fall and impact; a few minutes each on 2 CPU cores)
DEFAULT_FRAMES = {"box_drop": 60, "bunny_drop": 8, "stack": 15, "ball_bowl": 12, "twisted_bar": 90, "bunny_octopus": 8}
CASES = ["box_drop", *SCENES]
#: the cases with surface contact, whose intersections IPC Toolkit judges (the others: collider distances)
NEEDS_IPCTK = ("stack", "ball_bowl", "twisted_bar", "bunny_octopus")

IPCTK_MISSING = ("IPC Toolkit (the Python package 'ipctk', the test extra) is not installed; it judges the "
                 "intersections of the scenes with surface contact: pip install ipctk")


def apply_config(sim, config: dict, skipped: dict | None = None) -> dict:
    """Apply ``config`` to ``sim`` (NewtonOptions fields to ``sim.options``, other keys to existing
    attributes of ``sim``; "revision" is not a setting); returns {key: (where, value)}. Raises
    KeyError on an unknown key, unless ``skipped`` is a dict: then the key is skipped and ``skipped``
    gets {key: note} (a worker on an old revision, whose code lacks a newer key)."""
    fields = {f.name for f in dataclasses.fields(NewtonOptions)}
    applied = {}
    import importlib
    for key, (mod, name) in MODULE_KEYS.items():
        m = importlib.import_module(mod)
        if hasattr(m, name):
            _MODULE_DEFAULTS.setdefault(key, getattr(m, name))
            setattr(m, name, _MODULE_DEFAULTS[key])
    for key, value in config.items():
        if key == "revision":
            continue
        if key in MODULE_KEYS:
            m = importlib.import_module(MODULE_KEYS[key][0])
            if hasattr(m, MODULE_KEYS[key][1]):
                setattr(m, MODULE_KEYS[key][1], value)
                applied[key] = (f"{MODULE_KEYS[key][0]}.{MODULE_KEYS[key][1]}", value)
            elif skipped is not None:
                skipped[key] = f"skipped: {MODULE_KEYS[key][0]} has no {MODULE_KEYS[key][1]} in {TREE}"
            else:
                raise KeyError(f"configuration key {key!r}: {MODULE_KEYS[key][0]} has no {MODULE_KEYS[key][1]}")
            continue
        if key == "friction":  # the Coulomb coefficient of every collider and of surface contact
            cs, sc = getattr(sim, "contact", None), getattr(sim, "surface_contact", None)
            for c in (cs.colliders if cs is not None else []):
                cs.set_friction(c.name, value)
            if sc is not None:
                sc.set_friction(value)
            applied[key] = ("colliders and surface contact", value)
        elif key in fields:
            setattr(sim.options, key, value)
            applied[key] = ("options", value)
        elif hasattr(sim, key) and not callable(getattr(sim, key)):
            setattr(sim, key, value)
            applied[key] = ("sim", value)
        elif skipped is not None:
            skipped[key] = (f"skipped: {key!r} = {value!r} is neither a NewtonOptions field nor an attribute of "
                            f"{type(sim).__name__} in {TREE}")
        else:
            raise KeyError(f"configuration key {key!r} is neither a NewtonOptions field ({', '.join(sorted(fields))}) "
                           f"nor an attribute of {type(sim).__name__}")
    sim.options.validate()
    fi = getattr(sim, "friction_iterations", 0)
    if int(fi) != fi or fi < 0:
        raise ValueError(f"friction_iterations must be an integer >= 0, got {fi!r}")
    return applied


class CaseRun:
    """A built case: ``sim``, ``model``, ``advance()`` (one output frame), what a frame is."""

    def __init__(self, sim, model, advance, steps_per_frame, fps, description):
        self.sim, self.model, self.advance = sim, model, advance
        self.steps_per_frame, self.fps, self.description = steps_per_frame, fps, description


def build_box_drop(precision, device):
    mesh = wf.box_tet_mesh(size=(0.2, 0.2, 0.2), cells=(4, 4, 4))
    mat = wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81))
    sim = wf.Simulator(model, device=device, precision=precision, dt=1.0 / 240.0, integrator="backward_euler",
                       max_iters=100)
    floor_z = float(mesh.vertices[:, 2].min()) - 0.1
    sim.add_collider(wf.Plane(point=(0.0, 0.0, floor_z), normal=(0.0, 0.0, 1.0), friction=0.3, name="floor"))

    def advance():
        for _ in range(4):
            sim.step()

    return CaseRun(sim, model, advance, 4, 60.0, f"box 0.2 m, {mesh.num_tets} tets, dropped 10 cm on a floor (mu 0.3), "
                                                   "backward Euler, dt 1/240 s, 4 steps per frame")


def build_scene(name, precision, device):
    from warpfem.scenes import load_scene

    scene = load_scene(os.path.join(SCENE_DIR, SCENES[name]))
    run = scene.build(device=device, precision=precision)
    integ = scene.spec.integrator
    return CaseRun(run.sim, run.model, run.step_frame, int(integ.get("substeps", 1)), run.fps,
                   f"examples/scenes/{SCENES[name]}")


def build_case(name, precision, device):
    return build_box_drop(precision, device) if name == "box_drop" else build_scene(name, precision, device)


def in_contact(sim) -> bool:
    """A surface vertex within dhat of a collider, or a surface contact pair within dhat."""
    cs = getattr(sim, "contact", None)
    if cs is not None and len(cs) and bool((cs.distances() < np.asarray(cs.dhat)[None, :]).any()):
        return True
    sc = getattr(sim, "surface_contact", None)
    return sc is not None and sc.min_distance() < sc.dhat


class IntersectionCheck:
    """Per frame: IPC Toolkit on the boundary surface (surface contact only) and collider distances <= 0."""

    def __init__(self, run: CaseRun):
        self.sim = run.sim
        self.cm = None
        if getattr(run.sim, "surface_contact", None) is not None:
            try:
                import ipctk
            except ImportError as exc:
                raise RuntimeError(IPCTK_MISSING) from exc
            self.ipctk = ipctk
            faces = np.asarray(run.model.mesh.boundary_faces(), dtype=np.int64)
            edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1),
                              axis=0)
            self.cm = ipctk.CollisionMesh(np.asarray(run.model.rest_positions, dtype=np.float64), edges, faces)
        self.method = " + ".join(m for m, on in (("ipctk.has_intersections", self.cm is not None),
                                                  ("collider distance <= 0", self._colliders())) if on)

    def _colliders(self):
        cs = getattr(self.sim, "contact", None)
        return cs is not None and len(cs) > 0

    def __call__(self) -> dict:
        out = {}
        if self.cm is not None:
            x = np.asarray(self.sim.positions(), dtype=np.float64)
            out["surfaces"] = bool(self.ipctk.has_intersections(self.cm, x))
        if self._colliders():
            d = self.sim.contact.distances()
            out["collider_min_distance"] = float(d.min()) if d.size else math.inf
            out["colliders"] = bool(d.size and d.min() <= 0.0)
        out["intersects"] = bool(out.get("surfaces", False) or out.get("colliders", False))
        return out


def time_hessian(sim, batches=5, repeats=5):
    """(wall, process CPU) seconds of one Hessian assembly (values zeroed + ``assemble_stiffness``) at
    the current positions: best of ``batches`` batches of ``repeats`` after one warm-up call."""
    vals = sim.new_matrix_values()

    def once():
        vals.zero_()
        sim.assemble_stiffness(values=vals)

    once()
    wp.synchronize_device(sim.device)
    wall = cpu = math.inf
    for _ in range(batches):
        t, c = time.perf_counter(), time.process_time()
        for _ in range(repeats):
            once()
        wp.synchronize_device(sim.device)
        wall = min(wall, (time.perf_counter() - t) / repeats)
        cpu = min(cpu, (time.process_time() - c) / repeats)
    return wall, cpu


def run_one(case, config_name, precision, frames, device, log=print, skip_unknown=False):
    """Run one case under one configuration and precision, in this process; the per-frame records
    and the summary. ``skip_unknown``: configuration keys this code lacks are skipped (noted)."""
    gc.collect()  # not in the timed steps
    run = build_case(case, precision, device)
    sim = run.sim
    skipped = {} if skip_unknown else None
    applied = apply_config(sim, CONFIGS[config_name], skipped)
    check = IntersectionCheck(run)
    steps = []
    step = sim.step  # the bound method; the wrapper below shadows it on the instance

    def recorded(*a, **kw):  # the step timed alone; the contact test after it is not timed
        t, c = time.perf_counter(), time.process_time()
        st = step(*a, **kw)
        wall, cpu = time.perf_counter() - t, time.process_time() - c
        steps.append(dict(wall=wall, cpu=cpu, newton=int(st.newton_iterations),
                          linear=int(st.linear_iterations), line_search=int(st.line_search_steps),
                          converged=bool(st.converged), reason=st.reason, friction=int(st.friction_iterations),
                          contact=in_contact(sim)))
        return st

    sim.step = recorded
    records = []
    error = None
    contact_before = in_contact(sim)
    for k in range(1, frames + 1):
        n0 = len(steps)
        try:
            run.advance()
        except Exception as exc:  # a failed solve (NaN/inf): recorded, the run stops there
            error = f"frame {k}: {type(exc).__name__}: {exc}"
            log(f"  {case} {config_name} {precision}: {error}")
            break
        sts = steps[n0:]
        contact = contact_before or any(s["contact"] for s in sts)
        contact_before = bool(sts[-1]["contact"]) if sts else contact_before
        inter = check()
        rec = dict(frame=k, contact=contact, steps=len(sts), contact_steps=sum(s["contact"] for s in sts), newton=sum(s["newton"] for s in sts),
                   linear=sum(s["linear"] for s in sts),
                   wall=sum(s["wall"] for s in sts), cpu=sum(s["cpu"] for s in sts),
                   line_search=sum(s["line_search"] for s in sts), not_converged=sum(not s["converged"] for s in sts),
                   friction_iterations=sum(s["friction"] for s in sts),
                   reasons=sorted({s["reason"] for s in sts if not s["converged"] and s["reason"]}), **inter)
        records.append(rec)
        log(f"  {case} {config_name} {precision} frame {k}: {'contact' if contact else 'free   '} "
            f"{rec['newton']:3d} Newton ({rec['linear']} linear) in {rec['steps']} steps, {rec['wall']:.3f} s, ls {rec['line_search']}, "
            f"friction {rec['friction_iterations']}, not converged {rec['not_converged']}, intersects {rec['intersects']}")
    del sim.step  # the class's step again
    hess_wall, hess_cpu = time_hessian(sim)
    for rec in records:
        rec["wall_over_hessian"] = rec["wall"] / hess_wall
        rec["cpu_over_hessian"] = rec["cpu"] / hess_cpu
    return dict(case=case, config=config_name, config_keys=CONFIGS[config_name],
                applied={k: f"{w}.{k} = {v!r}" for k, (w, v) in applied.items()}, skipped=skipped or {},
                tree=TREE, warpfem_path=portable_path(os.path.dirname(os.path.abspath(wf.__file__))), precision=precision,
                description=run.description, frames_requested=frames, steps_per_frame=run.steps_per_frame,
                fps=run.fps, dt=float(sim.dt), tets=int(getattr(run.model.mesh, "num_tets", 0) or 0),
                vertices=int(sim.num_vertices), newton_options=dataclasses.asdict(sim.options),
                friction_iterations_option=int(getattr(sim, "friction_iterations", 0)),
                intersection_check=check.method, error=error,
                hessian_seconds=dict(wall=hess_wall, cpu=hess_cpu), summary=summarize(records), frames=records)


def run_in_worker(case, config_name, precision, frames, device, tree: dict) -> dict:
    """``run_one`` in a subprocess of this script whose PYTHONPATH starts with the extracted tree
    ``tree["path"]`` (the configuration's revision); its log goes to this process's stdout."""
    with tempfile.TemporaryDirectory(prefix="contact_cost_worker_") as tmp:
        out = os.path.join(tmp, "result.json")
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([tree["path"], *filter(None, [env.get("PYTHONPATH")])])
        cmd = [sys.executable, os.path.abspath(__file__), "--_worker", out, "--_tree", tree["path"],
               "--_tree-label", tree["label"], "--cases", case, "--configs", config_name, "--precision", precision,
               "--frames", str(frames), "--device", device]
        sys.stdout.flush()
        rc = subprocess.run(cmd, env=env, cwd=tree["path"]).returncode
        if rc or not os.path.isfile(out):
            raise SystemExit(f"the worker for {case} {config_name} {precision} ({tree['label']}) failed "
                             f"(exit status {rc}): {' '.join(cmd)}")
        with open(out) as fh:
            return json.load(fh)


def worker(a) -> int:
    """``--_worker OUT``: one case, configuration and precision on the code first on sys.path (an
    extracted revision, ``--_tree``); the result JSON written to OUT."""
    global SCENE_DIR, TREE, TREE_PATH
    tree = os.path.realpath(a._tree)
    TREE_PATH = tree
    here = os.path.realpath(os.path.dirname(wf.__file__))
    if os.path.commonpath([tree, here]) != tree:
        raise SystemExit(f"worker: warpfem was imported from {here}, not from the extracted tree {tree} "
                         "(PYTHONPATH must start with it)")
    SCENE_DIR = os.path.join(a._tree, "examples", "scenes")
    TREE = a._tree_label
    case, config_name, prec = a.cases, a.configs, a.precision
    wp.config.quiet = True
    wp.init()
    import warpfem.contact.kernels  # noqa: F401
    import warpfem.contact.surface_kernels  # noqa: F401
    import warpfem.scenes  # noqa: F401

    wp.force_load(device=a.device)
    w = build_case(case, prec, a.device)  # warm-up (discarded), as in the main process
    w.sim.step()
    del w
    r = run_one(case, config_name, prec, int(a.frames), a.device, log=lambda s: print(s, flush=True), skip_unknown=True)
    for key, note in r["skipped"].items():
        print(f"  {case} {config_name} {prec}: configuration key {key!r} {note}", flush=True)
    with open(a._worker, "w") as fh:
        json.dump(r, fh)
    return 0


def print_summary(r, what=""):
    s = r["summary"]
    print(f"{r['case']} {r['config']} {r['precision']}{' ' + what if what else ''}: free {s['free_frames']} / contact "
          f"{s['contact_frames']} frames; Newton/frame free {_f(s['newton']['free']['mean'])} contact "
          f"{_f(s['newton']['contact']['mean'])} (x{_f(s['newton']['contact_over_free'], '.2f')}); s/frame free "
          f"{_f(s['wall']['free']['mean'], '.3f')} contact {_f(s['wall']['contact']['mean'], '.3f')} "
          f"(x{_f(s['wall']['contact_over_free'], '.2f')}, {_f(s['contact_wall_over_hessian']['mean'], '.0f')} Hessians); "
          f"line-search halvings {s['line_search_total']}; not converged steps {s['not_converged_steps']}; "
          f"intersecting frames {s['intersecting_frames']}; {r.get('tree', 'working tree')}", flush=True)


def merge_repeats(runs):
    """One run from repeats of the same case, configuration and precision: each frame's (and the
    Hessian's) time the smallest over the repeats (the least disturbed by other jobs), the counts
    those of the first repeat (``repeats_identical`` says whether every repeat counted the same)."""
    if len(runs) == 1:
        return dict(runs[0], repeats=1)
    out = dict(runs[0])
    keys = ("contact", "newton", "linear", "line_search", "not_converged", "friction_iterations", "intersects")
    out["repeats_identical"] = all(len(r["frames"]) == len(out["frames"])
                                   and all(all(f[k] == g[k] for k in keys) for f, g in zip(r["frames"], out["frames"]))
                                   for r in runs[1:])
    hw = min(r["hessian_seconds"]["wall"] for r in runs)
    hc = min(r["hessian_seconds"]["cpu"] for r in runs)
    frames = []
    for k, rec in enumerate(out["frames"]):
        same = [r["frames"][k] for r in runs if len(r["frames"]) > k]
        rec = dict(rec, wall=min(f["wall"] for f in same), cpu=min(f["cpu"] for f in same),
                   wall_repeats=[f["wall"] for f in same], cpu_repeats=[f["cpu"] for f in same])
        rec["wall_over_hessian"], rec["cpu_over_hessian"] = rec["wall"] / hw, rec["cpu"] / hc
        frames.append(rec)
    out.update(frames=frames, repeats=len(runs), summary=summarize(frames),
               hessian_seconds=dict(wall=hw, cpu=hc, wall_repeats=[r["hessian_seconds"]["wall"] for r in runs]),
               error="; ".join(r["error"] for r in runs if r["error"]) or None)
    return out


def _stats(values):
    if not values:
        return dict(mean=None, median=None, max=None)
    return dict(mean=float(np.mean(values)), median=float(np.median(values)), max=float(np.max(values)))


def _ratio(a, b):
    return None if a is None or b is None or b == 0 else a / b


def summarize(records):
    free = [r for r in records if not r["contact"]]
    cont = [r for r in records if r["contact"]]
    s = dict(frames=len(records), free_frames=len(free), contact_frames=len(cont),
             first_contact_frame=cont[0]["frame"] if cont else None)
    # times without frame 1 (a new simulator's first step costs up to ~1.5x a later one, even after the
    # warm-up), unless it is the only frame of its kind
    tfree = [r for r in free if r["frame"] > 1] or free
    tcont = [r for r in cont if r["frame"] > 1] or cont
    s["timed_frames"] = dict(free=len(tfree), contact=len(tcont),
                             frame_1_included=bool(records) and any(r["frame"] == 1 for r in tfree + tcont))
    for key in ("newton", "linear", "line_search", "wall", "cpu"):
        f, c = (tfree, tcont) if key in ("wall", "cpu") else (free, cont)
        s[key] = dict(free=_stats([r[key] for r in f]), contact=_stats([r[key] for r in c]))
        s[key]["contact_over_free"] = _ratio(s[key]["contact"]["mean"], s[key]["free"]["mean"])
    s["contact_wall_over_hessian"] = _stats([r["wall_over_hessian"] for r in tcont])
    s["contact_cpu_over_hessian"] = _stats([r["cpu_over_hessian"] for r in tcont])
    s["free_wall_over_hessian"] = _stats([r["wall_over_hessian"] for r in tfree])
    s["line_search_total"] = sum(r["line_search"] for r in records)
    s["not_converged_steps"] = sum(r["not_converged"] for r in records)
    s["not_converged_frames"] = [r["frame"] for r in records if r["not_converged"]]
    s["friction_iterations_total"] = sum(r["friction_iterations"] for r in records)
    s["intersecting_frames"] = [r["frame"] for r in records if r["intersects"]]
    mins = [r["collider_min_distance"] for r in records if "collider_min_distance" in r]
    s["collider_min_distance"] = min(mins) if mins else None
    return s


def cpu_model():
    """The processor as Python's ``platform`` names it."""
    return platform.processor() or platform.machine() or "unknown"


def loadavg():
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def _f(x, fmt=".1f"):
    return "-" if x is None else format(x, fmt)


def markdown(result):
    m = result["meta"]
    L = ["# Contact cost: free vs contact frames", "",
         f"Device `{m['device']}` ({m['cpu']}, {m['cores']} cores), warp {m['warp']}, {m['date']}; load average "
         f"(1, 5, 15 min) before {m['load_before']}, after {m['load_after']}. Times: seconds of the steps only, wall "
         "(process CPU time in brackets: a shared machine inflates it less), frame 1 left out unless it is the only "
         "free (contact) frame; comparable within this "
         f"run only{'; each frame the best of ' + str(m.get('repeats')) + ' repeats' if (m.get('repeats') or 1) > 1 else ''}. "
         "Hessian: one elastic assembly (`assemble_stiffness`) of the same mesh at the run's final state, "
         "best of 5x5.", "",
         "| case | config | precision | frames free/contact | Newton/frame free mean (max) | contact mean (max) | "
         "Newton contact/free | s/frame free | s/frame contact | time contact/free | contact frame / Hessian mean (max) | "
         "Hessian ms | line-search halvings | not converged steps | friction re-solves (lag updates since 5531463) | "
         "linear it. / frame free (contact) | intersecting frames |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["runs"]:
        s = r["summary"]
        n, w, c = s["newton"], s["wall"], s["cpu"]
        hw, hc = s["contact_wall_over_hessian"], s["contact_cpu_over_hessian"]
        L.append(
            f"| {r['case']} | {r['config']} | {r['precision']} | {s['free_frames']}/{s['contact_frames']} | "
            f"{_f(n['free']['mean'])} ({_f(n['free']['max'], '.0f')}) | {_f(n['contact']['mean'])} ({_f(n['contact']['max'], '.0f')}) | "
            f"{_f(n['contact_over_free'], '.2f')} | {_f(w['free']['mean'], '.3f')} ({_f(c['free']['mean'], '.3f')}) | "
            f"{_f(w['contact']['mean'], '.3f')} ({_f(c['contact']['mean'], '.3f')}) | "
            f"{_f(w['contact_over_free'], '.2f')} ({_f(c['contact_over_free'], '.2f')}) | "
            f"{_f(hw['mean'], '.0f')} ({_f(hc['mean'], '.0f')}), max {_f(hw['max'], '.0f')} | "
            f"{r['hessian_seconds']['wall'] * 1e3:.2f} ({r['hessian_seconds']['cpu'] * 1e3:.2f}) | "
            f"{s['line_search_total']} | {s['not_converged_steps']} | {s['friction_iterations_total']} | "
            f"{_f((s.get('linear') or {}).get('free', {}).get('mean'), '.1f')} "
            f"({_f((s.get('linear') or {}).get('contact', {}).get('mean'), '.1f')}) | "
            f"{len(s['intersecting_frames'])}{' ' + str(s['intersecting_frames'][:5]) if s['intersecting_frames'] else ''}"
            f"{' (error: ' + r['error'] + ')' if r['error'] else ''} |")
    cmp_rows = result.get("against_baseline") or []
    if cmp_rows:
        L += ["", f"Against the baseline configuration `{result['baseline']}` of this run (ratio config / baseline):", "",
              "| case | precision | config | Newton/contact frame | line-search halvings | s/contact frame wall (cpu) | "
              "Newton/free frame | s/free frame wall (cpu) |",
              "|---|---|---|---|---|---|---|---|"]
        for c in cmp_rows:
            L.append(f"| {c['case']} | {c['precision']} | {c['config']} | {_f(c['newton_contact'], '.2f')} | "
                     f"{_f(c['line_search'], '.2f')} | "
                     f"{_f(c['wall_contact'], '.2f')} ({_f(c['cpu_contact'], '.2f')}) | {_f(c['newton_free'], '.2f')} | "
                     f"{_f(c['wall_free'], '.2f')} ({_f(c['cpu_free'], '.2f')}) |")
    trees = result.get("trees") or {}
    if trees:
        L += ["", "Configurations: the code each ran and its settings:", "",
              "| config | keys | code | commit | warpfem imported from | keys skipped |", "|---|---|---|---|---|---|"]
        for name, t in trees.items():
            skipped = sorted({k for r in result["runs"] if r["config"] == name for k in r.get("skipped", {})})
            paths = sorted({r["warpfem_path"] for r in result["runs"] if r["config"] == name and r.get("warpfem_path")})
            L.append(f"| {name} | `{json.dumps(result['configs'][name])}` | {t['tree']} | {t.get('commit') or '-'} | "
                     f"{', '.join(f'`{p}`' for p in paths) or '-'} | {', '.join(skipped) or '-'} |")
    return "\n".join(L) + "\n"


def against_baseline(runs, baseline):
    base = {(r["case"], r["precision"]): r for r in runs if r["config"] == baseline}
    out = []
    for r in runs:
        b = base.get((r["case"], r["precision"]))
        if r["config"] == baseline or b is None:
            continue
        s, t = r["summary"], b["summary"]
        out.append(dict(case=r["case"], precision=r["precision"], config=r["config"],
                        newton_contact=_ratio(s["newton"]["contact"]["mean"], t["newton"]["contact"]["mean"]),
                        line_search=_ratio(s["line_search_total"], t["line_search_total"]),
                        not_converged=_ratio(s["not_converged_steps"], t["not_converged_steps"]),
                        wall_contact=_ratio(s["wall"]["contact"]["mean"], t["wall"]["contact"]["mean"]),
                        newton_free=_ratio(s["newton"]["free"]["mean"], t["newton"]["free"]["mean"]),
                        wall_free=_ratio(s["wall"]["free"]["mean"], t["wall"]["free"]["mean"]),
                        cpu_contact=_ratio(s["cpu"]["contact"]["mean"], t["cpu"]["contact"]["mean"]),
                        cpu_free=_ratio(s["cpu"]["free"]["mean"], t["cpu"]["free"]["mean"])))
    return out


def parse_frames(text, cases):
    """``--frames``: one count for every case, or ``case=N,...`` (the others keep their default)."""
    frames = {c: DEFAULT_FRAMES[c] for c in cases}
    if text:
        for part in text.split(","):
            if "=" in part:
                name, n = part.split("=", 1)
                if name not in DEFAULT_FRAMES:
                    raise SystemExit(f"--frames: unknown case {name!r}; known: {', '.join(CASES)}")
                frames[name] = int(n)
            else:
                frames = {c: int(part) for c in cases}
    if any(n < 1 for n in frames.values()):
        raise SystemExit("--frames: counts must be >= 1")
    return frames


def _split(text):
    return [s for s in text.split(",") if s]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, from {', '.join(CASES)}")
    ap.add_argument("--frames", default="", help="frames of every case (N) or per case (box_drop=15,stack=6); "
                    f"defaults {DEFAULT_FRAMES}")
    ap.add_argument("--precision", default="float64,float32", help="comma-separated: float32, float64")
    ap.add_argument("--configs", default="before,after", help=f"comma-separated names from CONFIGS ({', '.join(CONFIGS)}); "
                    "the first is the baseline of the ratios")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each case, configuration and precision (interleaved); "
                    "each frame's time is the smallest over them")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None)
    ap.add_argument("--md", default=None)
    ap.add_argument("--_worker", default=None, help=argparse.SUPPRESS)  # OUT.json: run one case/config/precision
    ap.add_argument("--_tree", default=None, help=argparse.SUPPRESS)  # the extracted tree the worker must import
    ap.add_argument("--_tree-label", default="", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a._worker:
        if not a._tree:
            raise SystemExit("--_worker needs --_tree")
        return worker(a)
    cases, precisions, configs = _split(a.cases), _split(a.precision), _split(a.configs)
    for kind, names, known in (("case", cases, CASES), ("precision", precisions, ("float32", "float64")),
                               ("configuration", configs, list(CONFIGS))):
        bad = [n for n in names if n not in known]
        if bad or not names:
            raise SystemExit(f"unknown {kind}(s) {bad or names}; known: {', '.join(known)}")
    frames = parse_frames(a.frames, cases)
    if a.repeats < 1:
        raise SystemExit("--repeats must be >= 1")
    need = [c for c in cases if c in NEEDS_IPCTK]
    if need:
        try:
            import ipctk  # noqa: F401
        except ImportError:
            cases = [c for c in cases if c not in NEEDS_IPCTK]
            if not cases:
                print(f"SKIP: {IPCTK_MISSING}")
                return 0
            print(f"note: {', '.join(need)} left out: {IPCTK_MISSING}", flush=True)
            frames = {c: frames[c] for c in cases}
    wp.config.quiet = True
    wp.init()
    # every imported Warp module loaded now (compiled on a cold kernel cache), not in the first frame
    # that needs it (e.g. the contact kernels, first launched in the frame before an impact)
    import warpfem.contact.kernels  # noqa: F401
    import warpfem.contact.surface_kernels  # noqa: F401
    import warpfem.scenes  # noqa: F401

    wp.force_load(device=a.device)
    # every in-process configuration's keys checked before any run (a revision's, in its worker:
    # keys its code lacks are skipped there, with a note)
    probe = build_box_drop("float64", a.device).sim
    for name in configs:
        if "revision" in CONFIGS[name]:
            continue
        try:
            apply_config(probe, CONFIGS[name])
        except (KeyError, ValueError, TypeError) as exc:
            raise SystemExit(f"configuration {name!r}: {exc}") from exc
    del probe
    with tempfile.TemporaryDirectory(prefix="contact_cost_trees_") as tmp_trees:
        # the code each configuration runs: a revision extracted once (its runs are workers), or this tree
        trees, extracted = {}, {}
        for name in configs:
            rev = CONFIGS[name].get("revision")
            if rev is None:
                trees[name] = dict(tree="working tree", revision=None, commit=working_tree_commit(), path=None,
                                   warpfem_path=portable_path(os.path.dirname(os.path.abspath(wf.__file__))))
                continue
            if rev not in extracted:
                path = os.path.join(tmp_trees, f"rev{len(extracted)}")
                os.makedirs(path)
                commit = extract_revision(str(rev), path)
                extracted[rev] = dict(path=path, commit=commit, label=f"revision {rev} ({commit[:12]})")
                print(f"revision {rev} ({commit}) extracted into a temporary folder", flush=True)
            e = extracted[rev]
            trees[name] = dict(tree=e["label"], revision=str(rev), commit=e["commit"], path=e["path"], label=e["label"])
        load_before = loadavg()
        t_all = time.perf_counter()
        runs = []
        for case in cases:
            for prec in precisions:
                # warm-up (discarded): Warp's module loading and first-call allocations out of frame 1's time
                # (a worker does its own)
                if any(trees[cfg]["path"] is None for cfg in configs):
                    w = build_case(case, prec, a.device)
                    w.sim.step()
                    del w
                done = {cfg: [] for cfg in configs}
                for rep in range(a.repeats):  # the configurations one after the other, repeats interleaved
                    for cfg in configs:
                        t = trees[cfg]
                        print(f"{case} {cfg} {prec}: {frames[case]} frames, {t['tree']}"
                              + (f" (repeat {rep + 1})" if a.repeats > 1 else ""), flush=True)
                        if t["path"] is None:
                            r = run_one(case, cfg, prec, frames[case], a.device, log=lambda s: print(s, flush=True))
                        else:
                            r = run_in_worker(case, cfg, prec, frames[case], a.device, t)
                        done[cfg].append(r)
                        print_summary(r)
                for cfg in configs:
                    r = merge_repeats(done[cfg])
                    if a.repeats > 1:
                        print_summary(r, "best of repeats")
                    runs.append(r)
    for name, t in trees.items():  # the temporary paths are gone; the paths each run imported stay in the runs
        t.pop("path", None)
        t.pop("label", None)
        t["warpfem_path"] = sorted({r["warpfem_path"] for r in runs if r["config"] == name})
    meta = dict(device=str(a.device), cpu=cpu_model(), platform=platform.platform(), cores=os.cpu_count(),
                warp=wp.__version__, warpfem=getattr(wf, "__version__", None), python=platform.python_version(),
                date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes"),
                load_before=load_before, load_after=loadavg(), seconds=round(time.perf_counter() - t_all, 1),
                clock="wall (perf_counter) per step, process CPU time next to it", repeats=a.repeats,
                argv=sys.argv[1:] if argv is None else list(argv))
    result = dict(meta=meta, configs={c: CONFIGS[c] for c in configs}, trees=trees, baseline=configs[0], frames=frames,
                  runs=runs,
                  against_baseline=against_baseline(runs, configs[0]))
    md = markdown(result)
    print(md)
    if a.json:
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        with open(a.json, "w") as fh:
            json.dump(result, fh, indent=1)
    if a.md:
        os.makedirs(os.path.dirname(os.path.abspath(a.md)), exist_ok=True)
        with open(a.md, "w") as fh:
            fh.write(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
