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
embedding those points in its elements (:func:`warpfem.mesh.locate.embed_points_in_elements`,
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

The code is split by concern: :mod:`.grid` (configurations, grids, truth spec), :mod:`.runner` (one
run: scene variant, build, timed frames, the job around it), :mod:`.metrics` (errors, cost proxy,
Pareto front), :mod:`.reference` (the reference runs and the error split), :mod:`.results`
(:class:`ConfigResult`, :class:`StudyResult`, JSON) and :mod:`.report` (tables, plot). This module runs a
whole study (:func:`run_study`) and re-exports the names of all of them.
"""

from __future__ import annotations

import os
import platform

from warpfem.paths import portable_path

from .grid import builtin_grid, _dedupe, GridError, load_grid, QUANTITIES, TradeoffConfig, TradeoffGrid, TruthSpec
from .metrics import pareto_front, set_quantity, work_proxy
from .reference import describe_reference, finish_reference, plan_reference, Reference
from .report import format_markdown, format_table, _one_line, plot_pareto, reference_lines
from .results import ConfigResult, load_study, SCHEMA_VERSION, StudyResult, TIMING_FIELDS, without_timings
from .runner import (_job_outcome, make_job, run_job, scene_document, SerialExecutor, Unavailable, variant_document,
                     variant_scene)

__all__ = ["without_timings", "planned_runs", "TruthSpec", "SerialExecutor", "run_job", "work_proxy", "TradeoffConfig",
           "TradeoffGrid", "GridError", "StudyResult", "ConfigResult", "builtin_grid", "load_grid", "pareto_front",
           "run_study", "load_study", "format_table", "plot_pareto", "QUANTITIES", "SCHEMA_VERSION", "scene_document",
           "set_quantity", "format_markdown",
           # re-exported from the modules of the split (where they are defined)
           "Unavailable", "variant_scene", "variant_document", "make_job", "Reference", "plan_reference",
           "finish_reference", "describe_reference", "reference_lines", "TIMING_FIELDS"]


def _device_description(device) -> str:
    import warp as wp

    d = wp.get_device(device)
    if d.is_cuda:
        return f"{d.alias}: {d.name}"
    cpu = platform.processor() or platform.machine()
    return f"cpu ({cpu}, {os.cpu_count()} logical cores; Warp's CPU backend runs kernels on one thread)"


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
    return StudyResult(scene=portable_path(scene_path), scene_name=base.name, grid=grid.name, device=str(device),
                       device_description=_device_description(device),
                       precision_note="reference: " + ", ".join(f"{k}={v}" for k, v in plan["ladder"][0].as_dict().items()
                                                               if v is not None and k != "name"),
                       frames=frames, fps=fps, simulated_seconds=frames / fps, quantity=quantity, object_size=ref["size"],
                       tip=reference.tip_info, reference=reference.result, results=results,
                       frontier=[ok[i].name for i in idx], comparison=comparison, load_note=_load_note(),
                       energy_scale=ref["energy_scale"], truth=reference.info, executor=executor.description)


def planned_runs(scene_path, grid: TradeoffGrid, *, truth="grid") -> int:
    """How many runs :func:`run_study` will do (reference runs included)."""
    from warpfem.scenes import load_scene

    base = load_scene(os.fspath(scene_path))
    configs, dropped = _dedupe(grid.configs, base.spec)
    plan = plan_reference(scene_document(scene_path), os.fspath(scene_path), base, grid.reference,
                          grid.truth if truth == "grid" else truth, configs)
    return len(plan["jobs"]) + len(configs) + len(dropped)


def _load_note() -> str:
    try:
        la = os.getloadavg()
        return f"load average {la[0]:.2f} {la[1]:.2f} {la[2]:.2f} at the end, {os.cpu_count()} cores"
    except OSError:  # pragma: no cover
        return ""
