"""Running one configuration of a trade-off study: the scene variant (:func:`variant_document`,
:func:`variant_scene`), its build (training a reduced basis when needed), warm-up so that no timing
includes Warp compilation, the timed frames, and the picklable job around it (:func:`make_job`,
:func:`run_job`) that runs in this process (:class:`SerialExecutor`) or on a Dask worker.
"""

from __future__ import annotations

import copy
import os
import platform
import tempfile
import time
import warnings

import numpy as np

from warpfem.paths import portable_message, portable_path
from warpfem.scenes.schema import read_toml

from .grid import TradeoffConfig
from .metrics import _Trajectory, work_proxy
from .results import ConfigResult

__all__ = ["scene_document", "Unavailable", "variant_scene", "variant_document", "make_job", "run_job", "SerialExecutor",
           "surface_target_tets"]


def scene_document(scene_path) -> dict:
    """The scene file's TOML document (raises SceneError like load_scene)."""
    from warpfem.scenes import SceneError

    return read_toml(os.fspath(scene_path), SceneError, what="scene file")


class Unavailable(Exception):
    """A configuration the scene layer cannot build (reported as skipped, with the reason)."""


def variant_scene(doc: dict, scene_path: str, cfg: TradeoffConfig, *, cache_dir: str | None = None):
    """A :class:`warpfem.scenes.Scene` for ``cfg``: the scene document with the overrides applied,
    validated again by :func:`parse_scene_dict`. Raises :class:`Unavailable` when rejected."""
    from warpfem.scenes import Scene, SceneError, parse_scene_dict

    d = variant_document(doc, cfg, cache_dir=cache_dir)
    try:
        spec = parse_scene_dict(d, path=os.path.abspath(scene_path))
    except SceneError as e:
        raise Unavailable(portable_message(str(e))) from e
    return Scene(spec)


def variant_document(doc: dict, cfg: TradeoffConfig, *, cache_dir: str | None = None, for_study: bool = True) -> dict:
    """The scene's TOML document with ``cfg``'s overrides written in (not validated).
    ``for_study``: drop the scene's outputs and make non-convergence non-fatal (a study counts it);
    False keeps the document as a user would run it (``warpfem tune`` writes it)."""
    from warpfem.scenes import INTEGRATORS, SCHEMA

    d = copy.deepcopy(doc)
    out = d.setdefault("output", {})
    if for_study:
        for k in ("usd", "states", "stats", "vtu"):
            out.pop(k, None)  # a study writes no scene outputs
    integ = d.setdefault("integrator", {})
    itype = cfg.integrator or integ.get("type", SCHEMA["integrator"]["type"].default)
    if itype not in INTEGRATORS:
        raise Unavailable(f"integrator {itype!r} is not registered (available: {', '.join(sorted(INTEGRATORS))})")
    entry = INTEGRATORS[itype]
    if cfg.integrator and cfg.integrator != integ.get("type", "backward_euler"):
        integ = {k: v for k, v in integ.items() if k in entry.keys}  # keys the new type does not take are dropped
        d["integrator"] = integ
    integ["type"] = itype
    if for_study:
        integ["require_convergence"] = False  # non-convergence is counted, not fatal
    for k in ("tol", "max_iters", "cg_tol", "max_cg_iters"):
        v = getattr(cfg, k)
        if v is not None and k in entry.keys:
            integ[k] = v
    if cfg.linear_solver is not None:
        if "linear_solver" not in entry.keys:
            raise Unavailable(f"integrator {itype!r} has no linear_solver option")
        integ["linear_solver"] = cfg.linear_solver
    if cfg.substeps is not None:
        if not entry.dynamic:
            raise Unavailable(f"integrator {itype!r} is quasi-static: no time step to vary")
        fps = float(out.get("fps", SCHEMA["output"]["fps"].default))
        integ["dt"] = 1.0 / (fps * cfg.substeps)
    if cfg.element is not None:
        d.setdefault("mesh", {})["element"] = cfg.element
    if cfg.refine not in (None, 1):
        mesh = d.setdefault("mesh", {})
        if mesh.get("generator") != "box" or "cells" not in mesh:
            raise Unavailable("spatial refinement needs [mesh] generator = \"box\" with cells (a mesh file cannot be "
                              "refined here)")
        mesh["cells"] = [int(c) * cfg.refine for c in mesh["cells"]]
    if cfg.target_tets is not None:
        mesh = d.setdefault("mesh", {})
        if surface_target_tets(doc) is None:
            raise Unavailable("target_tets needs [mesh] path = a surface file (.obj, .off, .ply, .stl) without "
                              "max_edge_length")
        mesh["target_tets"] = int(cfg.target_tets)
    if cfg.subspace is not None:
        sub = dict(cfg.subspace_dict())
        if "cache" not in sub and cache_dir is not None:
            key = "_".join(f"{k}{v}" for k, v in sorted(sub.items()))
            sub["cache"] = os.path.join(cache_dir, f"subspace_{key}.npz")
        d["subspace"] = sub
    return d


def surface_target_tets(doc) -> int | None:
    """The ``target_tets`` a scene document's mesh is made with when it is a surface file (its own
    value or the default for surface files), None for a box, a volume file or ``max_edge_length``."""
    from warpfem.mesh.tetrahedralization import SURFACE_EXTENSIONS
    from warpfem.scenes.schema import TARGET_TETS_DEFAULT

    mesh = (doc or {}).get("mesh") or {}
    path = mesh.get("path")
    if not isinstance(path, str) or not path.lower().endswith(SURFACE_EXTENSIONS) or mesh.get("max_edge_length") is not None:
        return None
    t = mesh.get("target_tets")
    return int(t) if isinstance(t, int) and not isinstance(t, bool) else TARGET_TETS_DEFAULT


def _build(scene, *, device, precision):
    """Build a run; a reduced variant whose cache is missing is trained first (offline cost,
    reported separately as ``train_seconds``)."""
    from warpfem.scenes import SceneError

    t0 = time.perf_counter()
    train = 0.0
    try:
        run = scene.build(device=device, precision=precision)
    except (SceneError, NotImplementedError, ImportError, ModuleNotFoundError) as e:
        sub = scene.spec.subspace
        if sub is None:
            raise Unavailable(str(e)) from e
        try:  # train the basis + cubature into the (temporary) cache, then build again
            from warpfem.reduced.scene import train_scene
        except ImportError as e2:
            raise Unavailable(f"reduced simulation not available: {e2}") from e2
        try:
            t1 = time.perf_counter()
            train_scene(scene, device=device, precision="float64", retrain=True)
            train = time.perf_counter() - t1
            run = scene.build(device=device, precision=precision)
        except Exception as e3:  # noqa: BLE001 - any failure of an optional feature is a skip
            raise Unavailable(f"reduced variant: {type(e3).__name__}: {e3}") from e3
    except (ValueError, RuntimeError) as e:
        raise Unavailable(str(e)) from e
    return run, time.perf_counter() - t0 - train, train


def _warm_up(device):
    """Compile / load every imported Warp module now so that no step timing includes compilation."""
    import warp as wp

    try:
        wp.force_load(device=device)
    except Exception:  # noqa: BLE001 - timing hygiene only
        pass


_WARMED: set = set()


def _warm_up_signature(doc, scene_path, cfg, *, device, frames, cache_dir):
    """One untimed frame per (device, precision, integrator, element, subspace) at the scene's own
    tolerances, so that kernels Warp builds on first use (sparse-matrix helpers, overloads) are
    not timed in whichever configuration happens to run first."""
    import dataclasses

    sig = (str(device), cfg.precision, cfg.integrator, cfg.element, cfg.subspace)
    if sig in _WARMED:
        return
    _WARMED.add(sig)
    light = dataclasses.replace(cfg, name="warm-up", tol=None, max_iters=None, cg_tol=None, max_cg_iters=None,
                                substeps=None, refine=None)
    try:
        run, _, _ = _build(variant_scene(doc, scene_path, light, cache_dir=cache_dir), device=device,
                           precision=cfg.precision)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            run.step_frame(total_frames=frames)
    except Exception:  # noqa: BLE001 - the timed run reports any problem itself
        pass


def _sampler(run, ref_rest, points_rest=None):
    """f(positions (n, 3)) -> positions at ``points_rest`` (default: the reference vertices
    ``ref_rest``): the identity on the reference's own mesh, else an embedding in this run's elements."""
    mesh = run.scene.mesh()
    X = np.asarray(mesh.vertices, dtype=np.float64)
    if points_rest is None and X.shape == ref_rest.shape and np.array_equal(X, ref_rest):
        return lambda x: x
    from warpfem.mesh.locate import embed_points_in_elements

    pts = ref_rest if points_rest is None else points_rest
    ids, w, _ = embed_points_in_elements(pts, mesh)
    return lambda x: np.einsum("pk,pki->pi", w, x[ids])


def _recorded_subspace(sub):
    """The [subspace] settings as a result records them (the cache file written portably)."""
    if sub is None:
        return None
    return {k: (portable_path(v) if k == "cache" and isinstance(v, str) else v) for k, v in sub.items()}


def _run_one(doc, scene_path, cfg, *, device, frames, ref_info, cache_dir, tip_point=None, progress=None):
    """Run ``cfg``; returns (ConfigResult, _Trajectory or None)."""
    from warpfem.solvers.nonlinear import SolveFailed

    res = ConfigResult(config=cfg.as_dict(), status="skipped")
    try:
        scene = variant_scene(doc, scene_path, cfg, cache_dir=cache_dir)
        run, res.build_seconds, res.train_seconds = _build(scene, device=device, precision=cfg.precision)
    except Unavailable as e:
        res.note = f"not available: {portable_message(str(e))}"
        return res, None
    sp = scene.spec
    res.settings = {"integrator": {k: v for k, v in sp.integrator.items() if not k.startswith("require")},
                    "element": sp.mesh["element"], "subspace": _recorded_subspace(sp.subspace),
                    "vertices": scene.mesh().num_vertices, "elements": scene.mesh().num_elements}
    _warm_up(device)
    _warm_up_signature(doc, scene_path, cfg, device=device, frames=frames, cache_dir=cache_dir)
    if ref_info is None:  # this is the reference: sample its own vertices
        sample = lambda x: x  # noqa: E731
    else:
        sample = _sampler(run, ref_info["rest"])
    tip_sample = None
    if tip_point is not None:  # embedded in this run's own mesh
        tip_sample = _sampler(run, None, np.asarray([tip_point], dtype=np.float64))
    traj = _Trajectory()
    energy_fns = [getattr(run.sim, k, None) for k in ("total_energy", "kinetic_energy", "elastic_energy")]
    energy_fn_fail = [any(f is None for f in energy_fns)]

    def record():
        x = run.sim.positions().astype(np.float64)
        traj.points.append(sample(x))
        if run.skinner is not None:
            traj.surface.append(run.surface_points())
        if tip_sample is not None:
            traj.tip.append(tip_sample(x)[0])
        if not energy_fn_fail[0]:
            try:
                traj.energy.append(float(energy_fns[0]()))
                traj.motion_energy.append(float(energy_fns[1]() + energy_fns[2]()))
            except Exception:  # noqa: BLE001 - an integrator without a usable energy
                energy_fn_fail[0] = True

    record()
    try:
        for _ in range(frames):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # non-convergence is counted instead
                fs = run.step_frame(total_frames=frames)
            res.frames += 1
            res.steps += fs.steps
            res.step_seconds += fs.step_seconds
            res.newton_iterations += fs.newton_iterations
            res.cg_iterations += fs.cg_iterations
            res.unconverged_frames += 0 if fs.converged else 1
            record()
            if progress is not None:
                progress(cfg, fs)
    except SolveFailed as e:
        res.status, res.note = "failed", f"frame {run.frame}: {portable_message(str(e))}"
        return res, None
    except (NotImplementedError, ValueError, RuntimeError) as e:  # e.g. a reduced run with handles
        res.status, res.note = "skipped", f"not available: {type(e).__name__}: {portable_message(str(e))}"
        return res, None
    if energy_fn_fail[0]:
        traj.energy = traj.motion_energy = []
    res.status = "ok"
    sim_seconds = res.frames / run.fps
    res.seconds_per_sim_second = res.step_seconds / sim_seconds
    res.newton_per_step = res.newton_iterations / max(res.steps, 1)
    res.cg_per_step = res.cg_iterations / max(res.steps, 1)
    res.cg_per_sim_second = res.cg_iterations / sim_seconds
    res.work = work_proxy(res, run) / sim_seconds
    if res.unconverged_frames:
        res.note = f"{res.unconverged_frames} frame(s) with a non-converged step"
    traj.fps = run.fps
    traj.fixed = run.model.fixed.any(axis=1).copy()
    traj.boundary = np.unique(np.asarray(scene.mesh().boundary_faces()).ravel()) if run.skinner is None else None
    return res, traj


def make_job(doc, scene_path, cfg: TradeoffConfig, *, device, frames, plan, tip_point=None, cache_dir=None) -> dict:
    """The picklable description of one run (see :func:`run_job`)."""
    return dict(doc=doc, scene_path=scene_path, config=cfg.as_dict(), device=str(device), frames=int(frames),
                sample_rest=plan["sample_rest"], tip_point=tip_point, cache_dir=cache_dir)


def _job_outcome(out, cfg: TradeoffConfig, retried) -> tuple:
    """(ConfigResult, trajectory) of a job: a job the executor gave up on is a failed row; retries
    are written into the note."""
    if not isinstance(out, tuple):  # cluster.JobFailed
        return ConfigResult(config=cfg.as_dict(), status="failed", note=out.message), None
    res, traj = out
    if retried:
        res.note = (res.note + "; " if res.note else "") + "retried on the cluster: " + "; ".join(retried)
    return res, traj


def run_job(job: dict, progress=None) -> tuple:
    """One run as a self-contained, picklable job (in this process or on a Dask worker): builds the
    variant, warms this process's kernels for its signature, then runs and times it here.
    Returns (ConfigResult, _Trajectory or None)."""
    if job.get("job_id"):  # on a Dask worker: record the start (restarts are reported), keep Warp quiet
        from .cluster import log_job_start

        log_job_start(job)
        import warp as wp

        wp.config.quiet = True  # the banner and module-load lines (Warp 1.19 reads log_level)
        if hasattr(wp, "LOG_WARNING"):
            wp.config.log_level = wp.LOG_WARNING
    cfg = TradeoffConfig.from_dict(job["config"])
    rest = job.get("sample_rest")
    shared = job.get("cache_dir")
    with tempfile.TemporaryDirectory(prefix="warpfem_tradeoff_") as own:  # reduced training cache
        cache_dir = shared if shared and os.path.isdir(shared) else own
        res, traj = _run_one(job["doc"], job["scene_path"], cfg, device=job["device"], frames=job["frames"],
                             ref_info=None if rest is None else {"rest": np.asarray(rest)}, cache_dir=cache_dir,
                             tip_point=job.get("tip_point"), progress=progress)
    res.ran_on = f"{platform.node()} pid {os.getpid()}"
    try:
        from distributed import get_worker

        res.ran_on += f" dask worker {get_worker().address}"
    except (ImportError, ValueError):
        pass
    return res, traj


class SerialExecutor:
    """Runs jobs one after the other in this process (the default)."""

    description = "serial (this process)"

    def map(self, fn, jobs, *, on_done=None, progress=None):
        out = []
        for i, job in enumerate(jobs):
            r = fn(job, progress=progress) if progress is not None else fn(job)
            out.append(r)
            if on_done is not None:
                on_done(i, r)
        return out
