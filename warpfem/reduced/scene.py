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

__all__ = ["check_validation_error", "build_reduced_simulator", "train_scene", "subspace_cache_path", "scene_handles", "describe_subspace",
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
            "rotation_lifting": int(s.get("rotation_lifting") or 0)}


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
        got = have.get(k, {"pose_source": "random", "load_response": False, "pod_modes": 0, "rotation_lifting": 0}.get(k))
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
                            tol=o["tol"], atol=o["atol"], max_iters=o["max_iters"], project_hessian=o["project_hessian"],
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


def train_scene(scene, *, device="cpu", precision="float64", retrain=True, progress=None):
    """Train (or, with ``retrain=False`` and an up-to-date cache, load) the scene's subspace.

    ``[subspace].training = "snapshots"`` (or ``"mixed"``, the default: snapshots + random poses): the full scene is simulated for ``training_frames``
    frames (handles and loads as in ``warpfem run``) and the per-frame positions, projected on the
    basis, are the cubature training poses (every 4th held out for validation). ``"random"``:
    random poses (amplitude ~ 1/frequency), handles at random ramp fractions.
    ``progress(frame, total)`` is called after each training frame. Writes the cache and returns
    the :class:`~warpfem.reduced.Subspace` (its ``report`` includes ``snapshot_seconds``).
    """
    from warpfem.reduced.subspace import train_subspace
    from warpfem.scenes import handle_targets

    _check_integrator(scene)
    sp = scene.spec
    s = sp.subspace
    path = subspace_cache_path(scene)
    run = scene.build(device=device, precision=precision, full=True)  # the full-space training run
    model = run.model
    if not retrain and os.path.exists(path):
        try:
            sub, _ = _load_checked(scene, model)
            sub.report["cache"] = f"up to date: {path} (use --retrain to train again)"
            return sub
        except ValueError:  # SceneError / SubspaceMismatch: stale or mismatched, train below
            pass
    sel = scene_handles(scene)
    rest = [model.rest_positions[ids].copy() for ids, _ in sel]

    def targets_at(frac):
        return [handle_targets(r0, h, frac) for r0, h in zip(rest, sp.handle)]

    snapshots, t_snap, full_steps = None, None, 0
    if s["training"] in ("snapshots", "mixed"):
        frames = int(s["training_frames"] or sp.output["frames"])
        if frames < 4:
            raise _scene_error(scene, "[subspace].training_frames", f"snapshot training needs >= 4 frames, got {frames}")
        t0 = time.perf_counter()
        snapshots, full_steps, _ = _drive(scene, run, frames, progress)
        t_snap = time.perf_counter() - t0
    else:  # no training run: time one full frame of the scene for the predicted speed-up
        t0 = time.perf_counter()
        full_steps = run.step_frame().steps
        t_snap = time.perf_counter() - t0
    sub = train_subspace(model, modes=s["modes"], modal_derivatives=s["modal_derivatives"],
                         cubature_tolerance=s["cubature_tolerance"], max_cubature_points=s["max_cubature_points"],
                         seed=s["seed"], cache=path, retrain=True, num_training_poses=s["training_poses"],
                         num_validation_poses=s["validation_poses"], snapshots=snapshots,
                         pose_source=_POSE_SOURCE[s["training"]],
                         handles=sel, handle_targets_at=targets_at if sel else None,
                         load_response=bool(s.get("load_response", False)), pod_modes=int(s.get("pod_modes") or 0),
                         rotation_lifting=int(s.get("rotation_lifting") or 0))
    rep = sub.report
    if snapshots is not None:
        rep["snapshot_seconds"] = t_snap
        rep["snapshot_frames"] = len(snapshots) - 1
    rep["full_steps"] = full_steps
    rep["full_step_seconds"] = t_snap / max(full_steps, 1)
    if snapshots is not None and int(s.get("training_dt_scale") or 1) > 1:
        rep["full_step_seconds"] = _time_scene_steps(scene, run.sim)
    rep["timed_step_dt"] = float(run.sim.dt)  # the step the full step time is of (the scene's dt)
    _replay(scene, run, sub, snapshots, device=device, precision=precision)
    rep["training_seconds"] = (t_snap + rep.get("basis_seconds", 0.0) + rep.get("cubature_seconds", 0.0)
                               + rep.get("replay_seconds", 0.0))
    red, full = rep["reduced_step_seconds"], rep["full_step_seconds"]
    rep["predicted_speedup"] = full / max(red, 1e-12)
    per_frame = (full - red) * int(sp.integrator["substeps"])
    rep["break_even_frames"] = (int(np.ceil(rep["training_seconds"] / per_frame)) if per_frame > 0 else None)
    sub.save(path)
    return sub


def _drive(scene, run, frames, progress=None):
    """Run ``run.sim`` over ``frames`` frames of the scene, handles ramped over those frames.
    Positions after every frame, or with ``[subspace] training_dt_scale`` = k > 1 after every step
    of k x dt (the same simulated time in fewer steps). Returns (positions list with the rest pose
    first, steps, seconds spent stepping)."""
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
            xs.append(sim.positions())
            if progress is not None:
                progress(k + 1, frames)
        return xs, steps, seconds
    sim.dt = float(sp.integrator["dt"]) * scale
    count = _training_snapshot_count(scene)
    duration = frames / float(sp.output["fps"])
    for k in range(count):
        t_next = sim.time + sim.dt
        run.set_handles(lambda h, t=t_next: t / (h["ramp_time"] or duration))
        t0 = time.perf_counter()
        sim.step()
        seconds += time.perf_counter() - t0
        steps += 1
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
    sim.dt = float(scene.spec.integrator["dt"])
    t0 = time.perf_counter()
    for _ in range(_TIMED_SCENE_STEPS):
        sim.step()
    return (time.perf_counter() - t0) / _TIMED_SCENE_STEPS


def _replay(scene, run, sub, snapshots, *, device, precision):
    """Run the reduced simulator over the training run (same frames and step; or a few frames
    without one) on the same SceneRun driver: the reduced step time (for the predicted speed-up)
    and, with snapshots, the in-sample trajectory error against the full training run (tip: the
    free vertex that moved most; relative to its peak displacement; RMS relative to the
    bounding-box diagonal)."""
    import warnings

    model = run.model
    rsim = _reduced_simulator(scene, model, sub, device=device, precision=precision)
    s = scene.spec.subspace
    frames = int(s["training_frames"] or scene.spec.output["frames"]) if snapshots is not None \
        else min(int(scene.spec.output["frames"]), 4)
    run.sim, run.frame = rsim, 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # non-converged reduced steps show in the error
        if snapshots is None:
            xs, steps, t = [], 0, 0.0
            for _ in range(frames):
                fs = run.step_frame(total_frames=frames)
                steps += fs.steps
                t += fs.step_seconds
        else:
            xs, steps, t = _drive(scene, run, frames)
    rep = sub.report
    rep["replay_seconds"] = t
    rep["reduced_step_seconds"] = t / max(steps, 1)
    if snapshots is not None and int(s.get("training_dt_scale") or 1) > 1:
        rep["reduced_step_seconds"] = _time_scene_steps(scene, rsim)
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
             + (f", rotation-aware handle lifting (order {s['rotation_lifting']})" if s.get("rotation_lifting") else "")]
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
