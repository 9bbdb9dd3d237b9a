"""Speed/accuracy trade-off study: one scene over a grid of solver configurations.

Every configuration is a set of overrides of the scene file (precision, Newton ``tol`` and
``max_iters``, ``cg_tol``, substeps per frame, integrator, ``[mesh] element``, ``[subspace]``).
Variants are built by editing the parsed TOML document and validating it again with
:func:`warpfem.scenes.parse_scene_dict`, so whatever the scene layer supports is available here and
whatever it rejects is skipped with the scene layer's own message. Runs are stepped with
:meth:`warpfem.scenes.SceneRun.step_frame` and compared with a reference converged in space and
time (:class:`TruthSpec`): the box generator's cells refined with a higher-order element, a ladder
of time steps S, S/2, S/4 Richardson-extrapolated (backward Euler is first order), the same element
at half the refinement as a space check; every error is split into a discretisation part (the
time-converged run on the configuration's own mesh vs the reference) and a solver/step part (the
configuration vs that run). Without a truth spec (or for a mesh file, which cannot be refined; the
report says so) the reference is the grid's tight run on the scene's mesh: solver/step error only.

Common ground for comparisons: fixed material points, the **scene mesh's simulation vertices**
(rest positions; without a truth spec, the reference's). A run on that mesh is sampled there
directly; a run with another vertex set (another element type, a refined mesh) is sampled by
embedding those points in its elements (:func:`warpfem.elements.meshes.embed_points_in_elements`,
its own shape functions). Every run is an independent job (:func:`run_job`), executed serially or
on a Dask cluster (:mod:`warpfem.tradeoff.cluster`).

Errors (all over output frames 1..N, the rest state excluded):

* ``rms_error``: sqrt(mean over frames and sample points of |x - x_ref|^2) / L, L the diagonal of
  the rest bounding box ("relative to the object's size").
* ``surface_error``: the same over the render surface (``[surface]`` points skinned on each run's
  own mesh) or, without ``[surface]``, over the reference mesh's boundary vertices.
* ``tip_error``: max over frames of |x_tip - x_tip_ref| / max over frames of |u_tip_ref|; the tip
  is the free (not fixed, not a handle) reference vertex of largest displacement over the reference
  trajectory, or a rest-space point given with ``tip_point`` (embedded in each run's mesh).
* ``energy_error``: max over frames |E - E_ref| / M, E the integrator's total energy (kinetic +
  elastic - x.f_ext, J), M the reference's largest kinetic + elastic energy over the frames (the
  energy of the motion); ``energy_drift``: (E(T) - E(0)) / M (negative: numerical dissipation;
  moving handles also do work, so it is not zero for the reference either).
* ``seconds_per_sim_second``: wall time of the steps (``FrameStats.step_seconds``, build and Warp
  compilation excluded) per simulated second.
"""

from __future__ import annotations

import math
import os
import platform
import tempfile

import numpy as np

__all__ = ["without_timings", "planned_runs", "TruthSpec", "SerialExecutor", "run_job", "work_proxy", "TradeoffConfig", "TradeoffGrid", "GridError", "StudyResult", "ConfigResult", "builtin_grid",
           "load_grid", "pareto_front", "run_study", "load_study", "format_table", "plot_pareto",
           "QUANTITIES", "SCHEMA_VERSION", "scene_document", "set_quantity", "format_markdown"]

# The study is split by concern (grid.py, results.py, metrics.py, runner.py, report.py); this module
# runs it (reference planning, jobs, run_study) and re-exports every name, so imports keep working.
from .grid import (  # noqa: F401, E402 - re-exported
    GridError,
    QUANTITIES,
    SCHEMA_VERSION,
    TradeoffConfig,
    TradeoffGrid,
    TruthSpec,
    _GRID_KEYS,
    _REFERENCE,
    _auto_name,
    _cfg,
    _dedupe,
    _element_names,
    builtin_grid,
    load_grid,
)
from .results import (  # noqa: F401, E402 - re-exported
    ConfigResult,
    StudyResult,
    TIMING_FIELDS,
    _FLOAT_FIELDS,
    _device_description,
    _json_value,
    load_study,
    set_quantity,
    without_timings,
)
from .metrics import (  # noqa: F401, E402 - re-exported
    _QUADRATURE_POINTS,
    _Trajectory,
    _errors,
    _sampler,
    pareto_front,
    work_proxy,
)
from .runner import (  # noqa: F401, E402 - re-exported
    Unavailable,
    _WARMED,
    _build,
    _run_one,
    _warm_up,
    _warm_up_signature,
    scene_document,
    variant_document,
    variant_scene,
)
from .report import (  # noqa: F401, E402 - re-exported
    _fmt,
    _one_line,
    _split_key,
    format_markdown,
    format_table,
    plot_pareto,
    reference_lines,
)


def _truth_element(scene_element: str, spec: TruthSpec) -> str:
    if spec.element:
        return spec.element
    return "hex27" if scene_element.startswith("hex") else "tet10"


def _key(cfg: TradeoffConfig):
    import dataclasses

    return dataclasses.replace(cfg, name="")


def _combine(fine, coarse):
    """Richardson extrapolation of a first-order-in-dt trajectory: 2 x(h) - x(2h), frame by frame."""
    t = _Trajectory()
    for k in ("points", "surface", "tip", "energy", "motion_energy"):
        a, b = getattr(fine, k), getattr(coarse, k)
        setattr(t, k, list(2.0 * np.asarray(a) - np.asarray(b)) if len(a) and len(a) == len(b) else [])
    t.fps, t.fixed, t.boundary = fine.fps, getattr(fine, "fixed", None), getattr(fine, "boundary", None)
    return t


def _as_reference(traj, base: dict) -> dict:
    """A reference dict with ``traj``'s trajectory and ``base``'s normalisation (size, tip, energy scale)."""
    ref = dict(base)
    ref["points"] = np.asarray(traj.points)
    ref["tip"] = np.asarray(traj.tip) if base.get("tip_point") is not None else ref["points"][:, base["tip_vertex"]]
    ref["surface"] = np.asarray(traj.surface) if traj.surface else None
    ref["energy"] = np.asarray(traj.energy) if traj.energy else None
    return ref


def _pair_errors(traj, ref: dict) -> tuple:
    r = ConfigResult(config={"name": ""}, status="ok")
    _errors(r, traj, ref)
    return r.tip_error, r.rms_error


def run_study(scene_path, grid: TradeoffGrid, *, device="cpu", frames=None, quantity="tip", tip_point=None,
              progress=None, log=None, executor=None, truth="grid") -> StudyResult:
    """Run ``grid`` on the scene file and compare every configuration with the reference.

    ``frames``: output frames per run (default: the grid's, else the scene's ``[output].frames``).
    ``quantity``: the error measure of the frontier ("tip", "rms", "surface", "energy").
    ``tip_point``: rest-space point (m) whose displacement is the named quantity (default: the free
    reference vertex of largest displacement). ``progress(cfg, FrameStats)`` after each frame (serial
    runs), ``log(str)`` after each run. ``executor``: where runs execute (default: this process,
    one after the other; :class:`warpfem.tradeoff.cluster.DaskExecutor` for a Dask cluster).
    ``truth``: "grid" (the grid's ``truth``), None (the grid's reference on the scene's mesh: solver
    and time-step error only) or a :class:`TruthSpec` (converged reference: refined higher-order mesh,
    time-step ladder). Raises SceneError for an invalid scene, :class:`warpfem.SolveFailed` when the
    reference itself fails.
    """
    from warpfem.scenes import load_scene

    if quantity not in QUANTITIES:
        raise GridError(f"unknown quantity {quantity!r}; choose one of {', '.join(QUANTITIES)}")
    scene_path = os.fspath(scene_path)
    base = load_scene(scene_path)  # validates the scene file (SceneError)
    doc = scene_document(scene_path)
    frames = int(frames or grid.frames or base.spec.output["frames"])
    if frames < 1:
        raise GridError(f"frames must be >= 1, got {frames}")
    tip_point = tip_point if tip_point is not None else grid.tip_point
    log = log or (lambda s: None)
    executor = executor or SerialExecutor()
    tspec = grid.truth if truth == "grid" else truth
    configs, dropped = _dedupe(grid.configs, base.spec)
    plan = plan_reference(doc, scene_path, base, grid.reference, tspec, configs)
    internal = plan["jobs"]
    jobs = internal + list(configs)  # configurations always run (and are timed) on their own, in grid order
    n_internal = len(internal)
    payload = [make_job(doc, scene_path, c, device=device, frames=frames, plan=plan, tip_point=tip_point) for c in jobs]

    def on_done(i, out):
        res = _job_outcome(out, jobs[i], None)[0]
        log(_one_line(res) if i >= n_internal else "reference run: " + _one_line(res))

    outs = executor.map(run_job, payload, on_done=on_done, progress=progress)
    outs = [_job_outcome(out, jobs[i], getattr(executor, "retried", {}).get(i)) for i, out in enumerate(outs)]
    reference = finish_reference(plan, outs[:n_internal], tip_point=tip_point, frames=frames)
    results = []
    for res, traj in outs[n_internal:]:
        if traj is not None:
            reference.errors(res, traj)
        results.append(res)
    for cfg, same_as in dropped:
        res = ConfigResult(config=cfg.as_dict(), status="skipped", note=f"same settings as {same_as!r} for this scene")
        results.append(res)
        log(_one_line(res))
    key = QUANTITIES[quantity]
    ok = [r for r in results if r.status == "ok"]
    idx = pareto_front([r.seconds_per_sim_second for r in ok], [getattr(r, key) for r in ok])
    for i in idx:
        ok[i].on_frontier = True
    fps = float(base.spec.output["fps"])
    ref = reference.ref
    comparison = ("errors at the " + ("scene mesh's" if plan["split"] else "reference's") + " simulation vertices "
                  "(rest positions); runs with another vertex set (element type, refined mesh) are sampled there "
                  "through their own shape functions (embedding); 'surface' is the "
                  + ("[surface] render points skinned on each run's mesh" if ref["surface"] is not None
                     else "reference mesh's boundary vertices"))
    return StudyResult(scene=os.path.abspath(scene_path), scene_name=base.name, grid=grid.name, device=str(device),
                       device_description=_device_description(device),
                       precision_note="reference: " + ", ".join(f"{k}={v}" for k, v in plan["ladder"][0].as_dict().items()
                                                               if v is not None and k != "name"),
                       frames=frames, fps=fps, simulated_seconds=frames / fps, quantity=quantity, object_size=ref["size"],
                       tip=reference.tip_info, reference=reference.result, results=results,
                       frontier=[ok[i].name for i in idx], comparison=comparison, load_note=_load_note(),
                       energy_scale=ref["energy_scale"], truth=reference.info, executor=executor.description)


def make_job(doc, scene_path, cfg: TradeoffConfig, *, device, frames, plan, tip_point=None, cache_dir=None) -> dict:
    """The picklable description of one run (see :func:`run_job`)."""
    return dict(doc=doc, scene_path=scene_path, config=cfg.as_dict(), device=str(device), frames=int(frames),
                sample_rest=plan["sample_rest"], tip_point=tip_point, cache_dir=cache_dir)


class Reference:
    """A scene's reference trajectory at the sample points (the converged one, or the grid's
    reference on the scene's mesh), the time-converged run on each mesh, and what is known about
    its own convergence. :meth:`errors` fills a run's error fields (total and split)."""

    def __init__(self, plan, ref, result, mesh_truth, info, tip_info, frames):
        self.plan, self.ref, self.result, self.mesh_truth = plan, ref, result, mesh_truth
        self.info, self.tip_info, self.frames = info, tip_info, frames

    @property
    def sample_rest(self):
        return self.plan["sample_rest"]

    def _prefix(self, n):
        if n is None or n >= self.frames:
            return self.ref
        ref = dict(self.ref)
        for k in ("points", "tip", "surface", "energy"):
            if ref.get(k) is not None:
                ref[k] = ref[k][:n + 1]
        return ref

    def errors(self, res: ConfigResult, traj, *, frames: int | None = None) -> ConfigResult:
        """Errors of ``traj`` (a run of ``res``'s configuration over its first ``frames`` frames,
        default all) against the reference, split into discretisation and solver/step parts."""
        n = len(traj.points) - 1 if frames is None else frames
        ref = self._prefix(n)
        _errors(res, traj, ref)
        cfg = TradeoffConfig.from_dict(res.config)
        mt = self.mesh_truth.get(self.plan["mesh_of"](cfg))
        if mt is not None and self.plan["split"]:
            mt = _slice(mt, n)
            res.discretisation_tip_error, res.discretisation_rms_error = _pair_errors(mt, ref)
            res.solver_tip_error, res.solver_rms_error = _pair_errors(traj, _as_reference(mt, ref))
        return res

    def discretisation_error(self, element: str, refine: int = 1, quantity: str = "tip") -> float:
        """The time-converged run on that mesh vs the reference (NaN: not measured)."""
        mt = self.mesh_truth.get((element, refine))
        if mt is None or not self.plan["split"]:
            return math.nan
        tip, rms = _pair_errors(mt, self.ref)
        return tip if quantity == "tip" else rms


def _slice(traj, n):
    t = _Trajectory()
    for k in ("points", "surface", "tip", "energy", "motion_energy"):
        setattr(t, k, list(getattr(traj, k))[:n + 1])
    t.fps, t.fixed, t.boundary = getattr(traj, "fps", None), getattr(traj, "fixed", None), getattr(traj, "boundary", None)
    return t


def finish_reference(plan, outs, *, tip_point=None, frames) -> Reference:
    """Combine the reference runs (``outs``, in the order of ``plan["jobs"]``) into a :class:`Reference`."""
    ids = plan["ids"]
    ladder = [outs[i] for i in ids["ladder"]]
    ref_res, ref_traj = ladder[0]
    if ref_res.status != "ok":
        from warpfem.solvers.nonlinear import SolveFailed

        raise SolveFailed(f"the reference run ({plan['ladder'][0].as_dict()}) did not complete: {ref_res.note}")
    # the reference trajectory: Richardson extrapolation of the two finest steps when both ran
    truth_traj = ref_traj
    if len(ladder) >= 2 and all(r.status == "ok" for r, _ in ladder[:2]):
        truth_traj = _combine(ladder[0][1], ladder[1][1])
    mesh_ids = ids["mesh_refs"]
    mask_traj = outs[mesh_ids[plan["scene_mesh"]][0]][1] if plan["scene_mesh"] in mesh_ids else ref_traj
    if mask_traj is None:
        mask_traj = ref_traj
    rest = plan["sample_rest"]
    pts = np.asarray(truth_traj.points)
    size = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    if tip_point is not None:
        tip = np.asarray(truth_traj.tip)
        tip_info = {"vertex": None, "point": list(map(float, tip_point)), "how": "given point (rest position)"}
    else:
        disp = np.linalg.norm(pts - pts[0][None], axis=2).max(axis=0)
        disp[mask_traj.fixed] = -1.0
        v = int(np.argmax(disp))
        tip = pts[:, v]
        tip_info = {"vertex": v, "point": rest[v].tolist(),
                    "how": "free reference vertex of largest displacement over the trajectory"}
    tip_peak = float(np.linalg.norm(tip - tip[0], axis=1).max())
    tip_info["peak_displacement_m"] = tip_peak
    ref = {"rest": rest, "points": pts, "size": size, "tip": tip, "tip_peak": tip_peak,
           "tip_vertex": tip_info["vertex"], "tip_point": tip_point,
           "surface": np.asarray(truth_traj.surface) if truth_traj.surface else None,
           "boundary": mask_traj.boundary,
           "energy": np.asarray(truth_traj.energy) if truth_traj.energy else None,
           "energy_scale": float(np.max(ref_traj.motion_energy)) if ref_traj.motion_energy else 0.0}
    _errors(ref_res, ref_traj, ref)
    mesh_truth = {}
    for mk, jj in mesh_ids.items():
        runs = [outs[i] for i in jj]
        if all(r.status == "ok" for r, _ in runs):
            mesh_truth[mk] = _combine(runs[0][1], runs[1][1]) if len(runs) == 2 else runs[0][1]
    space = outs[ids["space"]] if ids["space"] is not None else None
    info = describe_reference(plan, ladder, space, ref, mesh_truth, {mk: [outs[i][0] for i in jj] for mk, jj in mesh_ids.items()})
    return Reference(plan, ref, ref_res, mesh_truth, info, tip_info, frames)


def planned_runs(scene_path, grid: TradeoffGrid, *, truth="grid") -> int:
    """How many runs :func:`run_study` will do (reference runs included)."""
    from warpfem.scenes import load_scene

    base = load_scene(os.fspath(scene_path))
    configs, dropped = _dedupe(grid.configs, base.spec)
    plan = plan_reference(scene_document(scene_path), os.fspath(scene_path), base, grid.reference,
                          grid.truth if truth == "grid" else truth, configs)
    return len(plan["jobs"]) + len(configs) + len(dropped)


def plan_reference(doc, scene_path, base, reference: TradeoffConfig, tspec, configs, *, meshes=()) -> dict:
    """Which reference runs a study needs (``plan["jobs"]``, distinct; see :func:`_plan`).
    ``meshes``: more (element, refine) keys whose time-converged run is wanted."""
    plan = _plan(doc, scene_path, base, reference, tspec, configs, meshes)
    jobs, index = [], {}

    def add(cfg):
        k = _key(cfg)
        if k not in index:
            index[k] = len(jobs)
            jobs.append(cfg)
        return index[k]

    plan["ids"] = {"ladder": [add(c) for c in plan["ladder"]],
                   "space": add(plan["space"]) if plan["space"] is not None else None,
                   "mesh_refs": {mk: [add(c) for c in cs] for mk, cs in plan["mesh_refs"].items()}}
    plan["jobs"] = jobs
    return plan


def _plan(doc, scene_path, base, reference: TradeoffConfig, tspec, configs, extra_meshes=()) -> dict:
    """Which reference runs a study needs.

    Without a truth spec: the grid's reference alone (on the scene's mesh unless it names another
    element), errors at its vertices. With one: the time-step ladder S, S/2, S/4 on the refined
    higher-order mesh (Richardson extrapolation of the two finest is the reference; the third shows
    the time convergence), the same element at half the refinement at step S (the space
    convergence), and for every mesh the configurations use, the tight run at S and S/2 (the
    time-converged solution on that mesh: splits each error into discretisation and solver/step
    parts). A scene read from a mesh file cannot be refined: the ladder then runs on the scene's
    own mesh and the report says so (``flag``)."""
    import dataclasses

    scene_el = base.spec.mesh["element"]
    sample_cfg = dataclasses.replace(reference, element=None, refine=None, subspace=None)
    plan = {"spec": tspec, "split": False, "space": None, "mesh_refs": {}, "flag": "", "scene_mesh": (scene_el, 1)}
    plan["mesh_of"] = lambda c: (c.element or scene_el, c.refine or 1)
    if tspec is None:
        plan["ladder"] = [reference]
        plan["sample_rest"] = np.asarray(variant_scene(doc, scene_path, reference).mesh().vertices, dtype=np.float64)
        plan["flag"] = ("reference = the grid's reference on its own mesh: errors are solver, precision and time-step "
                        "errors only (no spatial convergence)")
        return plan
    plan["sample_rest"] = np.asarray(variant_scene(doc, scene_path, sample_cfg).mesh().vertices, dtype=np.float64)
    S = int(tspec.substeps or max(8, reference.substeps or 1))
    steps = [S]
    while len(steps) < 3 and steps[-1] % 2 == 0:
        steps.append(steps[-1] // 2)
    el = _truth_element(scene_el, tspec)
    refine = int(tspec.refine)
    can_refine = doc.get("mesh", {}).get("generator") == "box"
    if not can_refine:
        plan["flag"] = ("the scene reads a mesh file, which cannot be refined here: the reference is the time-step "
                        "ladder on the scene's own mesh and element (solver and time-step error only; no "
                        "discretisation error)")
        el, refine = scene_el, 1
    base_ref = dataclasses.replace(reference, name="reference", element=el, refine=refine if refine != 1 else None,
                                   subspace=None)
    plan["ladder"] = [dataclasses.replace(base_ref, name=f"reference {el}" + (f" cells x{refine}" if refine != 1 else "")
                                          + f" {s} substeps", substeps=s) for s in steps]
    plan["ladder"][0] = dataclasses.replace(plan["ladder"][0], name="reference")
    if can_refine and refine >= 2:
        plan["space"] = dataclasses.replace(base_ref, name=f"space check: {el} cells x{refine // 2} {S} substeps",
                                            refine=(refine // 2) if refine // 2 != 1 else None, substeps=S)
    if not can_refine:
        return plan
    plan["split"] = True
    meshes = {plan["scene_mesh"]} | {plan["mesh_of"](c) for c in configs} | set(extra_meshes)
    for mk in sorted(meshes):
        e, r = mk
        cs = [dataclasses.replace(base_ref, name=f"mesh reference {e}" + (f" cells x{r}" if r != 1 else "") + f" {s} substeps",
                                  element=e, refine=r if r != 1 else None, substeps=s) for s in steps[:2]]
        plan["mesh_refs"][mk] = cs
    return plan


def describe_reference(plan, ladder, space, ref, mesh_truth, mesh_runs) -> dict:
    """The report's account of the reference: what it is, its own convergence in time and space."""
    info = {"kind": "converged" if plan["split"] else "solver/time-step only", "flag": plan["flag"],
            "runs": [r.as_dict() for r, _ in ladder]}
    if plan["spec"] is not None:
        info["spec"] = plan["spec"].as_dict()
    L = ref
    if len(ladder) >= 2 and all(r.status == "ok" for r, _ in ladder):
        trajs = [t for _, t in ladder]
        steps = [r.config["substeps"] for r, _ in ladder]
        diffs = [_pair_errors(trajs[k], _as_reference(trajs[k + 1], L)) for k in range(len(trajs) - 1)]
        t = {"substeps": steps, "method": "Richardson extrapolation 2 x(h) - x(2h) of the two finest steps "
                                          "(backward Euler is first order in dt)" if plan["spec"] is not None else "",
             "difference_tip": [d[0] for d in diffs], "difference_rms": [d[1] for d in diffs]}
        if len(diffs) >= 2 and diffs[0][0] > 0 and diffs[1][0] > 0:
            t["observed_order_tip"] = float(math.log2(diffs[1][0] / diffs[0][0]))
        if len(trajs) >= 3:  # the extrapolation's own error ~ |R(h) - R(2h)| / 3 (second order)
            R1, R2 = _combine(trajs[0], trajs[1]), _combine(trajs[1], trajs[2])
            e = _pair_errors(R1, _as_reference(R2, L))
            t["estimated_error_tip"], t["estimated_error_rms"] = e[0] / 3.0, e[1] / 3.0
        elif diffs:
            t["estimated_error_tip"], t["estimated_error_rms"] = diffs[0]
        info["time"] = t
    if space is not None:
        sres, straj = space
        info["space_run"] = sres.as_dict()
        if straj is not None and ladder[0][1] is not None:
            d = _pair_errors(straj, _as_reference(ladder[0][1], L))
            info["space"] = {"difference_tip": d[0], "difference_rms": d[1],
                             "note": "vs the reference mesh at the same dt: the error of the coarser level; the "
                                     "reference's own is smaller (about 1/8 of it for a quadratic element, error ~ h^3)"}
    info["meshes"] = {f"{mk[0]}" + (f" cells x{mk[1]}" if mk[1] != 1 else ""):
                      {"discretisation_tip_error": (_pair_errors(mesh_truth[mk], L)[0] if mk in mesh_truth else None),
                       "discretisation_rms_error": (_pair_errors(mesh_truth[mk], L)[1] if mk in mesh_truth else None),
                       "notes": [r.note for r in runs if r.note]}
                      for mk, runs in mesh_runs.items()}
    return _json_value(info)


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


def _load_note() -> str:
    try:
        la = os.getloadavg()
        return f"load average {la[0]:.2f} {la[1]:.2f} {la[2]:.2f} at the end, {os.cpu_count()} cores"
    except OSError:  # pragma: no cover
        return ""


# ----------------------------------------------------------------------------- reporting
