"""Scenes with a ``[subspace]`` section: training the cache (``warpfem train``) and reduced runs.

This module registers :func:`build_reduced_simulator` in the scene integrator registry for the
``[subspace]`` section (``warpfem.scenes.register_integrator``), so ``Scene.build`` calls it for a
scene with ``[subspace]`` (``Scene.build(full=True)``, the training run, does not); it loads
the cache written by :func:`train_scene` and returns a :class:`~warpfem.reduced.ReducedSimulator`
(reduced backward Euler) that offers what :class:`warpfem.scenes.SceneRun` drives: ``positions()``,
``x``, ``set_targets``, ``sync_model``, ``step`` / ``dt`` / ``time`` and, for the render surface,
``surface_positions_for(run)`` (W U precomputed: O(r) per surface point, no full-mesh rebuild).

Kinematic ``[[handle]]``s: the basis is built with the handle vertices fixed and the handle motion
enters as a prescribed displacement field (``warpfem.reduced.lifting``).
"""

from __future__ import annotations

import logging
import os
import time

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["BudgetNotMet", "check_validation_error", "build_reduced_simulator", "train_scene", "subspace_cache_path", "scene_handles", "describe_subspace",
           "scene_settings"]

def subspace_cache_path(scene) -> str:
    """The cache file: ``[subspace].cache`` relative to the scene file, default ``<name>.subspace.npz``
    next to it."""
    sp = scene.spec
    c = sp.subspace.get("cache") or f"{os.path.splitext(os.path.basename(sp.path or 'scene'))[0]}.subspace.npz"
    return os.path.normpath(c if os.path.isabs(c) else os.path.join(sp.base_dir, c))


def scene_handles(scene) -> list:
    """[(vertex ids, components)] per ``[[handle]]``."""
    sel = scene.selections()["handle"]
    return [(ids, h["components"]) for h, ids in zip(scene.spec.handle, sel)]


def scene_settings(scene) -> dict:
    """The ``[subspace]`` keys as :func:`~warpfem.reduced.train_subspace` settings (for staleness checks)."""
    s = scene.spec.subspace
    return {"modes": int(s["modes"]), "modal_derivatives": bool(s["modal_derivatives"]),
            "cubature_tolerance": float(s["cubature_tolerance"]), "max_cubature_points": int(s["max_cubature_points"]),
            "seed": int(s["seed"]), "pose_source": _POSE_SOURCE[s["training"]],
            "load_response": bool(s.get("load_response", False)), "pod_modes": int(s.get("pod_modes") or 0),
            "rotation_lifting": int(s.get("rotation_lifting") or 0),
            "max_error": float(s.get("max_error") or 0.0), "max_pod_modes": int(s.get("max_pod_modes") or 0)}


_POSE_SOURCE = {"mixed": "random+snapshots", "snapshots": "snapshots", "random": "random"}


def _where(scene):
    return scene.path or "<scene>"


def _scene_error(scene, where, msg):
    from warpfem.scenes import SceneError

    return SceneError(f"{_where(scene)}: {where}: {msg}")


def _check_integrator(scene):
    from warpfem.mesh.element_types import get_element

    el = scene.spec.mesh.get("element", "tet4")
    if not get_element(el).is_linear_tet:
        raise _scene_error(scene, "[subspace]", f"reduced simulation supports [mesh] element = \"tet4\" only, got {el!r}")
    t = scene.integrator_type
    if t not in ("backward_euler", "bdf2", "newmark"):
        raise _scene_error(scene, "[subspace]", f"reduced simulation needs [integrator] type = \"backward_euler\", "
                           f"\"bdf2\" or \"newmark\", got {t!r} (remove [subspace] to run {t!r} on the full mesh)")


def _stale(scene, sub) -> list:
    want = scene_settings(scene)
    have = sub.settings
    out = []
    for k, v in want.items():
        got = have.get(k, {"pose_source": "random", "load_response": False, "pod_modes": 0, "rotation_lifting": 0,
                           "max_error": 0.0, "max_pod_modes": 0}.get(k))
        if got != v:
            out.append(f"{k}: cache {got!r} vs scene {v!r}")
    if want["pose_source"] != "random":
        count = _training_snapshot_count(scene)
        if have.get("snapshots") != count + 1:
            out.append(f"training snapshots: cache {(have.get('snapshots') or 1) - 1} vs scene {count} "
                       "(training_frames / training_dt_scale changed)")
    if want["pose_source"] != "snapshots":
        for k, key in (("num_training_poses", "training_poses"), ("num_validation_poses", "validation_poses")):
            if have.get(k) != scene.spec.subspace[key]:
                out.append(f"{key}: cache {have.get(k)!r} vs scene {scene.spec.subspace[key]!r}")
    return out


def _training_snapshot_count(scene) -> int:
    """Snapshots of the full training run (rest excluded): one per frame, or with
    ``training_dt_scale`` = k > 1 one per coarse step (frames x substeps / k steps)."""
    s = scene.spec.subspace
    frames = int(s["training_frames"] or scene.spec.output["frames"])
    k = int(s.get("training_dt_scale") or 1)
    if k == 1:
        return frames
    return max(1, int(round(frames * int(scene.spec.integrator["substeps"]) / k)))


def _load_checked(scene, model):
    from warpfem.reduced.subspace import SubspaceMismatch, load_subspace

    path = subspace_cache_path(scene)
    hint = f"run `warpfem train {_where(scene)}` first"
    if not os.path.exists(path):
        raise _scene_error(scene, "[subspace].cache", f"subspace cache {path} not found; {hint}")
    try:
        sub = load_subspace(path, model, handles=scene_handles(scene))
    except SubspaceMismatch as e:
        raise _scene_error(scene, "[subspace].cache", f"{e}; {hint}") from e
    stale = _stale(scene, sub)
    if stale:
        raise _scene_error(scene, "[subspace].cache", f"subspace cache {path} was trained with other [subspace] "
                           f"settings ({'; '.join(stale)}); {hint}")
    return sub, path


def build_reduced_simulator(scene, model, *, device="cpu", precision="float64"):
    """The reduced simulator of a scene with ``[subspace]`` (cache from ``warpfem train``).

    Raises :class:`~warpfem.scenes.SceneError` when the integrator is not backward Euler, BDF2 or Newmark, or the
    cache is missing, belongs to another mesh / material / fixed set / handle set, or was trained
    with other ``[subspace]`` settings.
    """
    _check_integrator(scene)
    sub, path = _load_checked(scene, model)
    check_validation_error(scene, sub, path)
    return _reduced_simulator(scene, model, sub, device=device, precision=precision)


def _reduced_simulator(scene, model, sub, *, device="cpu", precision="float64"):
    from warpfem.reduced.simulator import ReducedSimulator

    o = scene.spec.integrator
    return ReducedSimulator(model, sub, device=device, precision=precision, dt=o["dt"], damping_mass=o["damping_mass"],
                            damping_stiffness=o["damping_stiffness"], require_convergence=o["require_convergence"],
                            tol=o["tol"], atol=o["atol"], max_iters=30 if o["max_iters"] is None else o["max_iters"], project_hessian=o["project_hessian"],
                            integrator=scene.integrator_type)


def check_validation_error(scene, sub, path=None) -> str | None:
    """Warn loudly (a ``logging`` warning: a ``warning:`` line on stderr from the CLI) when the subspace's cubature
    validation error (force error on poses not used in training) is above the scene's
    ``[subspace] max_validation_error``. Returns the message, or None when within the threshold
    (or no threshold is set)."""
    limit = scene.spec.subspace.get("max_validation_error")
    err = float(sub.cubature.validation_error)
    if limit is None or not (np.isnan(err) or err > limit):
        return None
    msg = (f"{_where(scene)}: reduced run NOT TRUSTED: the subspace's validation error {err:.3g} is above "
           f"[subspace] max_validation_error = {limit:g} (cache {path or subspace_cache_path(scene)}); lower "
           "cubature_tolerance, add modes / pod_modes and retrain, or check the run against a full one")
    logger.warning(msg)  # the CLI prints warnings on stderr as "warning: ..." lines
    return msg


class BudgetNotMet(ValueError):
    """``warpfem train`` could not bring the replay of the training run within ``[subspace] max_error``
    without going past the size caps (``max_pod_modes``); the cache is not written."""


def _pod_schedule(first: int, cap: int, snapshots: int) -> list:
    """POD column counts ``train`` tries for the error budget: the scene's own count first, then
    doubling (4, 8, 16, ...) up to ``cap`` (``[subspace] max_pod_modes``) and the number of
    training snapshots (POD cannot have more directions than snapshots)."""
    top = min(int(cap), int(snapshots))
    out, k = [int(first)], max(4, 2 * int(first))
    while k < top:
        out.append(k)
        k *= 2
    if top > out[-1]:
        out.append(top)
    return out


def train_scene(scene, *, device="cpu", precision="float64", retrain=True, progress=None, log=None):
    """Train (or, with ``retrain=False`` and an up-to-date cache, load) the scene's subspace.

    ``[subspace].training = "snapshots"`` (or ``"mixed"``, the default: snapshots + random poses): the full scene is simulated for ``training_frames``
    frames (handles and loads as in ``warpfem run``) and the per-frame positions, projected on the
    basis, are the cubature training poses (every 4th held out for validation). ``"random"``:
    random poses (amplitude ~ 1/frequency), handles at random ramp fractions.

    Error budget (``[subspace] max_error``, default 0.02; 0 = off): after training, the reduced
    run replays the training run; while its RMS trajectory error (max over frames of the RMS vertex
    error over the bounding-box diagonal) is above the budget, POD columns of the training run are
    added (the scene's ``pod_modes``, then 4, 8, 16, ... up to ``max_pod_modes``) and the basis and
    cubature are trained again (the full training run is not repeated). Raises
    :class:`BudgetNotMet` (the cache is not written) when even ``max_pod_modes`` columns miss it.
    ``training = "random"`` has no training run to replay: the budget is not checked (the report
    says so).

    ``progress(frame, total)`` is called after each training frame; ``log(line)`` (optional) gets a
    line per budget attempt. Writes the cache and returns the :class:`~warpfem.reduced.Subspace`
    (its ``report`` includes the itemised training times, ``training_seconds`` = their sum, and
    the budget attempts).
    """
    from warpfem.reduced.subspace import train_subspace
    from warpfem.scenes import handle_targets

    _check_integrator(scene)
    sp = scene.spec
    s = sp.subspace
    path = subspace_cache_path(scene)
    t_start = time.perf_counter()
    run = scene.build(device=device, precision=precision, full=True)  # the full-space training run
    model = run.model
    why = "--retrain requested" if retrain else "no cache yet"
    if not retrain and os.path.exists(path):
        try:
            sub, _ = _load_checked(scene, model)
            sub.report["cache"] = f"up to date: {path} (use --retrain to train again)"
            return sub
        except ValueError as e:  # SceneError / SubspaceMismatch: stale or mismatched, train below
            import re

            m = re.search(r"settings \((.*)\); run `warpfem train", str(e))
            why = "the cache was stale: " + (m.group(1) if m else str(e).split("; run `warpfem train")[0])
    t_setup = time.perf_counter() - t_start
    sel = scene_handles(scene)
    rest = [model.rest_positions[ids].copy() for ids, _ in sel]

    def targets_at(frac):
        return [handle_targets(r0, h, frac) for r0, h in zip(rest, sp.handle)]

    snapshots, t_snap, full_steps, frame_times = None, None, 0, []
    if s["training"] in ("snapshots", "mixed"):
        frames = int(s["training_frames"] or sp.output["frames"])
        if frames < 4:
            raise _scene_error(scene, "[subspace].training_frames", f"snapshot training needs >= 4 frames, got {frames}")
        t0 = time.perf_counter()
        snapshots, full_steps, _ = _drive(scene, run, frames, progress, per_frame=frame_times)
        t_snap = time.perf_counter() - t0
    else:  # no training run: time two full frames of the scene for the predicted speed-up
        t0 = time.perf_counter()
        for _ in range(2):
            fs = run.step_frame()
            frame_times.append((fs.steps, fs.step_seconds))
            full_steps += fs.steps
        t_snap = time.perf_counter() - t0
    full_step, full_load = _steady_step_seconds(frame_times)
    t_extra = 0.0
    if snapshots is not None and int(s.get("training_dt_scale") or 1) > 1:
        t0 = time.perf_counter()
        full_step = _time_scene_steps(scene, run.sim)
        t_extra = time.perf_counter() - t0
    timed_dt = float(sp.integrator["dt"])
    budget = float(s.get("max_error") or 0.0)
    if snapshots is None:
        schedule = [int(s.get("pod_modes") or 0)]
    else:
        schedule = _pod_schedule(int(s.get("pod_modes") or 0), int(s.get("max_pod_modes") or 0), len(snapshots) - 1)
        if not budget:
            schedule = schedule[:1]
    attempts, earlier, sub, last_r = [], 0.0, None, None
    for pod in schedule:
        t_try = time.perf_counter()
        sub = train_subspace(model, modes=s["modes"], modal_derivatives=s["modal_derivatives"],
                             cubature_tolerance=s["cubature_tolerance"], max_cubature_points=s["max_cubature_points"],
                             seed=s["seed"], cache=None, retrain=True, num_training_poses=s["training_poses"],
                             num_validation_poses=s["validation_poses"], snapshots=snapshots,
                             pose_source=_POSE_SOURCE[s["training"]],
                             handles=sel, handle_targets_at=targets_at if sel else None,
                             load_response=bool(s.get("load_response", False)), pod_modes=pod,
                             rotation_lifting=int(s.get("rotation_lifting") or 0))
        rep = sub.report
        _replay(scene, run, sub, snapshots, device=device, precision=precision)
        r = int(sub.U.shape[1])
        att = {"pod_modes": int(rep.get("pod_modes", 0)), "r": r, "cubature_points": int(rep["cubature_points"]),
               "rms_error": rep.get("replay_rms_error"), "tip_error": rep.get("replay_tip_error"),
               "seconds": time.perf_counter() - t_try}
        attempts.append(att)
        if log is not None and budget and snapshots is not None:
            log(f"budget: r = {r} ({att['pod_modes']} POD), {att['cubature_points']} cubature points: replay RMS "
                f"error {att['rms_error']:.3g} ({'within' if att['rms_error'] <= budget else 'above'} {budget:g})")
        if not budget or snapshots is None or att["rms_error"] <= budget:
            break
        if last_r is not None and r <= last_r:  # more POD columns asked for, none came (no energy left)
            break
        last_r = r
        earlier += att["seconds"]
    rep = sub.report
    s_pod = int(s.get("pod_modes") or 0)
    # the cache records the scene's settings (pod_modes as the scene asks; the count chosen is in the report)
    sub.settings["pod_modes"] = s_pod
    if not s_pod:
        sub.settings.pop("pod_modes", None)
    sub.settings.update(max_error=budget, max_pod_modes=int(s.get("max_pod_modes") or 0))
    rep["budget"] = {"max_error": budget, "checked": bool(budget and snapshots is not None),
                     "met": (None if not (budget and snapshots is not None) else bool(attempts[-1]["rms_error"] <= budget)),
                     "attempts": attempts, "max_pod_modes": int(s.get("max_pod_modes") or 0)}
    if rep["budget"]["met"] is False:
        best = min(attempts, key=lambda a: (not np.isfinite(a["rms_error"]), a["rms_error"]))  # a diverged replay: NaN
        raise BudgetNotMet(
            f"{_where(scene)}: [subspace] max_error = {budget:g} not met: the reduced replay of the training run is "
            f"{best['rms_error']:.3g} RMS error at best (r = {best['r']}: {s['modes']} modes + {best['pod_modes']} POD "
            f"columns, {best['cubature_points']} cubature points; tried POD columns "
            f"{', '.join(str(a['pod_modes']) for a in attempts)}, up to [subspace] max_pod_modes = "
            f"{int(s.get('max_pod_modes') or 0)}). Raise max_pod_modes or modes, lower cubature_tolerance, train "
            f"over more frames, or set max_error = 0 to accept this subspace; the cache was not written")
    if snapshots is not None:
        rep["snapshot_seconds"] = t_snap
        rep["snapshot_frames"] = len(snapshots) - 1
    rep["full_steps"] = full_steps
    rep["full_run_seconds"] = t_snap
    rep["full_step_seconds"] = full_step
    rep["timed_step_dt"] = timed_dt  # the step the full step time is of (the scene's dt)
    rep["budget_search_seconds"] = earlier
    rep["cache"] = f"trained ({why}), saved to {path}"
    total = time.perf_counter() - t_start
    items = {"setup (model, simulators)": t_setup, "full training run" if snapshots is not None else "two full frames (timing)": t_snap,
             "basis": rep.get("basis_seconds", 0.0), "cubature": rep.get("cubature_seconds", 0.0),
             "reduced replay": rep.get("replay_seconds", 0.0)}
    if t_extra:
        items["timing full steps at the scene's dt"] = t_extra
    if earlier:
        items[f"{len(attempts) - 1} earlier budget attempt(s)"] = earlier
    items["other (stiffness for the basis, lifting)"] = max(0.0, total - sum(items.values()))
    rep["training_items"] = items
    rep["training_seconds"] = float(sum(items.values()))
    rep["kernel_load_seconds"] = full_load + rep.get("replay_load_seconds", 0.0)
    red = rep["reduced_step_seconds"]
    rep["predicted_speedup"] = full_step / max(red, 1e-12)
    per_frame = (full_step - red) * int(sp.integrator["substeps"])
    # what training costs beyond what a full run pays as well (building the scene, loading kernels)
    recurring = max(rep["training_seconds"] - t_setup - rep["kernel_load_seconds"], 0.0)
    rep["break_even_seconds"] = recurring
    rep["break_even_frames"] = (int(np.ceil(recurring / per_frame)) if per_frame > 0 else None)
    sub.save(path)
    return sub


def _steady_step_seconds(frame_times) -> tuple:
    """(seconds per step leaving the first frame out, the first frame's excess over that): the first
    frame of a run loads (or compiles) its Warp kernels, once per process and module."""
    if not frame_times:
        return float("nan"), 0.0
    if len(frame_times) == 1:
        n, t = frame_times[0]
        return t / max(n, 1), 0.0
    n = sum(f[0] for f in frame_times[1:])
    t = sum(f[1] for f in frame_times[1:])
    each = t / max(n, 1)
    return each, max(0.0, frame_times[0][1] - frame_times[0][0] * each)


def _drive(scene, run, frames, progress=None, per_frame=None):
    """Run ``run.sim`` over ``frames`` frames of the scene, handles ramped over those frames.
    Positions after every frame, or with ``[subspace] training_dt_scale`` = k > 1 after every step
    of k x dt (the same simulated time in fewer steps). Returns (positions list with the rest pose
    first, steps, seconds spent stepping); ``per_frame`` (a list), when given, gets (steps, seconds)
    per frame (per coarse step)."""
    sp = scene.spec
    sim = run.sim
    xs = [run.model.rest_positions.copy()]
    steps, seconds = 0, 0.0
    scale = int(sp.subspace.get("training_dt_scale") or 1)
    if scale == 1:
        for k in range(frames):
            fs = run.step_frame(total_frames=frames)
            steps += fs.steps
            seconds += fs.step_seconds
            if per_frame is not None:
                per_frame.append((fs.steps, fs.step_seconds))
            xs.append(sim.positions())
            if progress is not None:
                progress(k + 1, frames)
        return xs, steps, seconds
    dt = float(sp.integrator["dt"]) * scale  # the coarse step, an argument of each step (the simulator's dt is kept)
    count = _training_snapshot_count(scene)
    duration = frames / float(sp.output["fps"])
    for k in range(count):
        t_next = sim.time + dt
        run.set_handles(lambda h, t=t_next: t / (h["ramp_time"] or duration))
        t0 = time.perf_counter()
        sim.step(dt=dt)
        dt_wall = time.perf_counter() - t0
        seconds += dt_wall
        steps += 1
        if per_frame is not None:
            per_frame.append((1, dt_wall))
        xs.append(sim.positions())
        if progress is not None:
            progress(k + 1, count)
    return xs, steps, seconds


_TIMED_SCENE_STEPS = 2


def _time_scene_steps(scene, sim) -> float:
    """Seconds per step of ``sim`` at the scene's own dt, from where a coarse (``training_dt_scale``)
    run left it: a coarse step takes more Newton iterations than a scene step, so timing the coarse
    steps would overstate the speed-up (measured 1.5-2x on the octopus). The state goes on from
    there; the snapshots are already taken."""
    dt = float(scene.spec.integrator["dt"])
    t0 = time.perf_counter()
    for _ in range(_TIMED_SCENE_STEPS):
        sim.step(dt=dt)
    return (time.perf_counter() - t0) / _TIMED_SCENE_STEPS


def _replay(scene, run, sub, snapshots, *, device, precision):
    """Run the reduced simulator over the training run (same frames and step; or a few frames
    without one) on the same SceneRun driver: the reduced step time (for the predicted speed-up;
    the first frame, which loads the reduced kernels, left out) and, with snapshots, the in-sample
    trajectory error against the full training run (tip: the free vertex that moved most;
    relative to its peak displacement; RMS relative to the bounding-box diagonal)."""
    import warnings

    model = run.model
    t_start = time.perf_counter()
    rsim = _reduced_simulator(scene, model, sub, device=device, precision=precision)
    s = scene.spec.subspace
    frames = int(s["training_frames"] or scene.spec.output["frames"]) if snapshots is not None \
        else min(int(scene.spec.output["frames"]), 4)
    run.sim, run.frame = rsim, 0
    per_frame = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # non-converged reduced steps show in the error
        if snapshots is None:
            xs = []
            for _ in range(frames):
                fs = run.step_frame(total_frames=frames)
                per_frame.append((fs.steps, fs.step_seconds))
        else:
            xs, _, _ = _drive(scene, run, frames, per_frame=per_frame)
        step, load = _steady_step_seconds(per_frame)
        if snapshots is not None and int(s.get("training_dt_scale") or 1) > 1:
            step = _time_scene_steps(scene, rsim)
    rep = sub.report
    rep["replay_seconds"] = time.perf_counter() - t_start
    rep["replay_load_seconds"] = load
    rep["reduced_step_seconds"] = step
    if snapshots is not None:
        rep.update(trajectory_errors(model, np.array(snapshots), np.array(xs)))


def trajectory_errors(model, x_full, x_red) -> dict:
    """Trajectory errors of x_red against x_full ((T, n, 3) each): ``tip_error`` = max over frames
    of |x_red - x_full| at the free vertex that moved most in x_full, over its peak displacement;
    ``rms_error`` = max over frames of the RMS vertex error over the bounding-box diagonal."""
    X = model.rest_positions
    size = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    disp = np.linalg.norm(x_full - X, axis=2)
    free = ~np.asarray(model.fixed).all(axis=1)
    tip = int(np.argmax(disp.max(axis=0) * free))
    peak = max(float(disp[:, tip].max()), 1e-300)
    e = np.linalg.norm(x_red - x_full, axis=2)
    return {"replay_tip_error": float(e[:, tip].max() / peak),
            "replay_rms_error": float(np.sqrt((e ** 2).mean(axis=1)).max() / size)}


def describe_subspace(scene) -> str:
    """Lines for ``warpfem describe``: reduced settings and, when cached, r and cubature points."""
    s = scene.spec.subspace
    path = subspace_cache_path(scene)
    pod = int(s.get("pod_modes") or 0)
    lines = [f"reduced: [subspace] r = {s['modes']}{f' + {pod} POD' if pod else ''} "
             f"(modal derivatives {'on' if s['modal_derivatives'] else 'off'}), "
             f"cubature tolerance {s['cubature_tolerance']:g}, at most {s['max_cubature_points']} points, "
             f"training {s['training']}"
             + (f", rotation-aware handle lifting (order {s['rotation_lifting']})" if s.get("rotation_lifting") else "")
             + (f"; error budget: train adds POD columns (up to {s.get('max_pod_modes')}) until its replay of the "
                f"training run is within {float(s['max_error']):g} RMS" if s.get("max_error") and s["training"] != "random"
                else "; error budget: none (training \"random\" has no run to replay)" if s.get("max_error")
                else "; error budget: off (max_error = 0)")]
    if scene.integrator_type not in ("backward_euler", "bdf2", "newmark"):
        lines.append(f"  error: [subspace] needs [integrator] type = \"backward_euler\", \"bdf2\" or \"newmark\", "
                     f"got {scene.integrator_type!r}")
    if not os.path.exists(path):
        lines.append(f"  cache {path}: not trained yet (run `warpfem train {_where(scene)}`)")
        return "\n".join(lines)
    try:
        import json

        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            r = int(z["U"].shape[1])
            pts = int(z["cubature_elements"].shape[0])
        rep = meta.get("report", {})
        lines.append(f"  cache {path}: r = {r}, {pts} cubature points of {rep.get('num_elements', '?')} elements, "
                     f"training error {rep.get('training_error', float('nan')):.3g}, validation error "
                     f"{rep.get('validation_error', float('nan')):.3g}"
                     + (f", {rep['handles']} handle(s)" if rep.get("handles") else "")
                     + (f", replay RMS error {rep['replay_rms_error']:.3g}" if "replay_rms_error" in rep else "")
                     + (f" with {rep['pod_modes']} POD columns chosen by the budget"
                        if len((rep.get("budget") or {}).get("attempts") or []) > 1 else "")
                     + (f"; predicted {rep['predicted_speedup']:.0f}x faster per step, cheaper than a full run "
                        f"beyond {rep['break_even_frames']} frames" if rep.get("break_even_frames") else ""))
        limit = s.get("max_validation_error")
        if limit is not None and not rep.get("validation_error", 0.0) <= limit:
            lines.append(f"  WARNING: validation error above [subspace] max_validation_error = {limit:g}: "
                         "the reduced run is not trusted")
        lines.append("  the run is reduced (x = X + U q, cubature forces); `warpfem run` checks the cache against "
                     "the mesh, material, fixed set and handles")
    except Exception as e:  # noqa: BLE001 - describe must not fail on a bad cache
        lines.append(f"  cache {path}: unreadable ({e}); retrain with `warpfem train {_where(scene)}`")
    return "\n".join(lines)


def _register():
    from warpfem.scenes import IntegratorType, register_integrator

    register_integrator(IntegratorType(
        "subspace", build_reduced_simulator, section="subspace", dynamic=True, describe=describe_subspace,
        builds=("reduced basis U and cubature points (from the cache)", "reduced Hessian (dense r x r)")),
        replace=True)


_register()
