"""The reference of a trade-off study: which runs it needs (:func:`plan_reference`: time-step ladder on
a refined higher-order mesh, space check, time-converged run on every mesh the configurations use),
and how their outcomes combine (:func:`finish_reference`) into a :class:`Reference` that measures a
run's errors, split into discretisation and solver/step parts.
"""

from __future__ import annotations

import math

import numpy as np

from .grid import TradeoffConfig, TruthSpec
from .metrics import _as_reference, _combine, _errors, _pair_errors, _slice
from .results import ConfigResult, _json_value
from .runner import variant_scene

__all__ = ["Reference", "finish_reference", "plan_reference", "describe_reference"]


def _truth_element(scene_element: str, spec: TruthSpec) -> str:
    if spec.element:
        return spec.element
    return "hex27" if scene_element.startswith("hex") else "tet10"


def _key(cfg: TradeoffConfig):
    import dataclasses

    return dataclasses.replace(cfg, name="")


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

    def discretisation_error(self, element: str, refine: int = 1, quantity: str = "tip", target_tets=None) -> float:
        """The time-converged run on that mesh vs the reference (NaN: not measured). ``target_tets``:
        the physics mesh size of a scene whose mesh is a surface file (None: the scene's own)."""
        if target_tets is None:
            target_tets = self.plan["scene_mesh"][2]
        mt = self.mesh_truth.get((element, refine, target_tets))
        if mt is None or not self.plan["split"]:
            return math.nan
        tip, rms = _pair_errors(mt, self.ref)
        return tip if quantity == "tip" else rms


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

    from .runner import surface_target_tets

    scene_el = base.spec.mesh["element"]
    scene_tets = surface_target_tets(doc)  # a surface file's physics mesh size (None: a box or a volume file)
    sample_cfg = dataclasses.replace(reference, element=None, refine=None, subspace=None, target_tets=None)
    # a mesh is (element, box refinement, target_tets of a surface file)
    plan = {"spec": tspec, "split": False, "space": None, "mesh_refs": {}, "flag": "", "scene_mesh": (scene_el, 1, scene_tets)}
    plan["mesh_of"] = lambda c: (c.element or scene_el, c.refine or 1, c.target_tets or scene_tets)
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
    box = doc.get("mesh", {}).get("generator") == "box"
    can_refine = box or scene_tets is not None
    ref_tets = None
    if scene_tets is not None:  # a surface file: a finer mesh of the same surface, refine^3 times the tets
        finest = max([scene_tets] + [c.target_tets for c in configs if c.target_tets])
        ref_tets = int(finest * refine ** 3)
        plan["flag"] = (f"the scene's mesh is made from a surface file: the reference is a finer mesh of the same surface "
                        f"(target_tets = {ref_tets}, {refine}^3 x {finest}; {el}), so the discretisation error of "
                        "target_tets and of the element is measured")
    elif not can_refine:
        plan["flag"] = ("the scene reads a mesh file, which cannot be refined here: the reference is the time-step "
                        "ladder on the scene's own mesh and element (solver and time-step error only; no "
                        "discretisation error)")
        el, refine = scene_el, 1
    box_refine = refine if box else 1
    base_ref = dataclasses.replace(reference, name="reference", element=el, refine=box_refine if box_refine != 1 else None,
                                   subspace=None, target_tets=ref_tets)
    label = f" cells x{box_refine}" if box_refine != 1 else f" tets={ref_tets}" if ref_tets else ""
    plan["ladder"] = [dataclasses.replace(base_ref, name=f"reference {el}{label} {s} substeps", substeps=s) for s in steps]
    plan["ladder"][0] = dataclasses.replace(plan["ladder"][0], name="reference")
    if box and refine >= 2:
        plan["space"] = dataclasses.replace(base_ref, name=f"space check: {el} cells x{refine // 2} {S} substeps",
                                            refine=(refine // 2) if refine // 2 != 1 else None, substeps=S)
    elif ref_tets is not None and refine >= 2:
        half = max(int(ref_tets // 8), 10)
        plan["space"] = dataclasses.replace(base_ref, name=f"space check: {el} tets={half} {S} substeps",
                                            target_tets=half, substeps=S)
    if not can_refine:
        return plan
    plan["split"] = True
    meshes = {plan["scene_mesh"]} | {plan["mesh_of"](c) for c in configs} | set(extra_meshes)
    for mk in sorted(meshes, key=lambda k: (k[0], k[1], k[2] or 0)):
        e, r, tt = mk
        what = (f" cells x{r}" if r != 1 else "") + (f" tets={tt}" if tt else "")
        cs = [dataclasses.replace(base_ref, name=f"mesh reference {e}{what} {s} substeps",
                                  element=e, refine=r if r != 1 else None, target_tets=tt, substeps=s) for s in steps[:2]]
        plan["mesh_refs"][mk] = cs
    return plan


def describe_reference(plan, ladder, space, ref, mesh_truth, mesh_runs) -> dict:
    """The report's account of the reference: what it is, its own convergence in time and space."""
    info = {"kind": "converged" if plan["split"] else "solver/time-step only", "flag": plan["flag"],
            "runs": [r.as_dict() for r, _ in ladder]}
    r0 = ladder[0][0]  # what the reference costs (its finest run), against the scene's own mesh
    info["cost"] = {"elements": (r0.settings or {}).get("elements"), "vertices": (r0.settings or {}).get("vertices"),
                    "seconds_per_sim_second": r0.seconds_per_sim_second, "work": r0.work,
                    "config": r0.config.get("name") if isinstance(r0.config, dict) else None}
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
    info["meshes"] = {f"{mk[0]}" + (f" cells x{mk[1]}" if mk[1] != 1 else "") + (f" tets={mk[2]}" if mk[2] else ""):
                      {"discretisation_tip_error": (_pair_errors(mesh_truth[mk], L)[0] if mk in mesh_truth else None),
                       "discretisation_rms_error": (_pair_errors(mesh_truth[mk], L)[1] if mk in mesh_truth else None),
                       "notes": [r.note for r in runs if r.note]}
                      for mk, runs in mesh_runs.items()}
    return _json_value(info)
