"""``warpfem tune SCENE --max-error E``: the cheapest configuration of a scene whose error against
the converged reference stays below E.

The search space is data-driven. The default one (``space="default"``, minutes on the shipped
scenes): the registered dynamic integrator types (:data:`warpfem.scenes.INTEGRATORS`) on the
scene's element and its higher-order partner (tet4 -> tet10, hex8 -> hex27), 1, 2 or 4 substeps per
frame, one Newton and one CG tolerance (1e-4), float64, the scene's linear solver
(:data:`DEFAULT_AXES`). ``space="full"`` (``warpfem tune --space full``) grows it to every element
type (:data:`warpfem.scenes.ELEMENTS`), 1-8 substeps, two Newton and two CG tolerances, both
precisions and the ``[integrator] linear_solver`` choices when the scene schema has that key
(:data:`FULL_AXES`; 1,600 candidates on the cantilever). Reduced runs of given subspace sizes are
added on request. Candidates the scene layer rejects are dropped, and candidates whose effective
settings coincide (a tolerance an integrator does not take) are run once.

Search (no full grid): candidates whose mesh alone already misses the budget (the discretisation
error of the time-converged run on that mesh, measured with the reference) are dropped before any
run; then successive halving on prefixes of the run (frames/8, frames/4, frames/2): every survivor
runs the prefix, those over the budget are dropped (the tip error, normalised by the reference's
peak over the whole run, can only grow with the prefix), and the cheapest third (at least ``keep``)
go on. The ``keep`` cheapest survivors of the last prefix then run the whole scene: the cheapest
within budget is the winner (the others are the runners-up); if none is, the next ones are tried.

Cost: ``time`` (wall seconds per simulated second, measured on the machine / worker that ran it;
noisy on a shared machine) or ``work`` (:func:`warpfem.tradeoff.metrics.work_proxy`: Newton and CG
iterations times element work, deterministic).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass, field

from warpfem.paths import portable_path, repository_root

from .grid import _REFERENCE, GridError, TradeoffConfig, TruthSpec, _cfg
from .reference import finish_reference, plan_reference
from .report import _fmt
from .results import _json_value
from .runner import (SerialExecutor, Unavailable, _job_outcome, make_job, run_job, scene_document, variant_document,
                     variant_scene)

__all__ = ["tune", "format_tune", "search_space", "TuneResult", "DEFAULT_AXES", "FULL_AXES", "SPACES", "space_axes",
           "plan_runs", "format_plan", "write_scene", "toml_dumps", "load_space",
           "rerun_error"]

# axes besides integrator / element / linear_solver (filled from the registries).
# DEFAULT_AXES: the search space of a plain `warpfem tune` (minutes on the shipped scenes: the registered
# dynamic integrators on the scene's element and its higher-order partner, 1-4 substeps, one Newton and
# one CG tolerance, float64, the scene's linear solver); FULL_AXES (`--space full`): every element,
# 1-8 substeps, two tolerances each, both precisions and every linear solver (1,600 candidates on the
# cantilever: hours).
DEFAULT_AXES = {"substeps": [1, 2, 4], "tol": [1e-4], "cg_tol": [1e-4], "precision": ["float64"]}
FULL_AXES = {"substeps": [1, 2, 4, 8], "tol": [1e-3, 1e-5], "cg_tol": [1e-2, 1e-4], "precision": ["float32", "float64"]}
SPACES = ("default", "full")
_AXES = ("integrator", "element", "substeps", "tol", "cg_tol", "precision", "linear_solver", "subspace", "target_tets")
#: A scene whose mesh is a surface file: the default and full spaces also search its physics mesh
#: size, these fractions of the scene's ``target_tets`` (candidates below the scene's value; the
#: reference is a finer mesh of the same surface), and both precisions.
TARGET_TETS_FRACTIONS = (0.25, 0.5, 1.0)
QUANTITY_FIELDS = {"tip": "tip_error", "rms": "rms_error"}


def _registered_axes(full: bool = True, doc=None) -> dict:
    """Integrator, element and linear-solver axes from the registries: every registered value
    (``full``), or the default space's: every dynamic integrator, the scene's element (``doc``) and
    its higher-order partner (:func:`_element_partners`), and no linear-solver axis (the scene's own)."""
    from warpfem.scenes import ELEMENTS, INTEGRATORS
    from warpfem.scenes.schema import INTEGRATOR_KEYS

    axes = {"integrator": sorted(n for n, e in INTEGRATORS.items() if e.dynamic), "element": list(ELEMENTS)}
    if not full:
        el = str(((doc or {}).get("mesh") or {}).get("element", "tet4"))
        axes["element"] = _element_partners(el)
        return axes
    key = INTEGRATOR_KEYS.get("linear_solver")
    if key is not None:  # optional axis: only once the schema has the key
        axes["linear_solver"] = list(getattr(key, "choices", None) or [])
    return axes


def _element_partners(name: str) -> list:
    """The element ``name`` and the registered element of the same reference shape (same corner
    nodes and reference volume) with the fewest nodes above its own (tet4 -> tet10, hex8 -> hex27)."""
    from warpfem.mesh.element_types import ELEMENTS

    if name not in ELEMENTS:
        return [name]
    e = ELEMENTS[name]
    same = [(o.nodes_per_element, n) for n, o in ELEMENTS.items()
            if len(o.corner_nodes) == len(e.corner_nodes) and o.reference_volume == e.reference_volume
            and o.nodes_per_element > e.nodes_per_element]
    return [name] + ([min(same)[1]] if same else [])


def space_axes(space, doc=None) -> dict:
    """The axes of a named search space (``"default"`` or ``"full"``, :data:`SPACES`) for a scene document."""
    if space not in SPACES:
        raise GridError(f"search space must be one of {', '.join(SPACES)} or a .toml file, got {space!r}")
    full = space == "full"
    axes = {**_registered_axes(full, doc), **(FULL_AXES if full else DEFAULT_AXES)}
    from .runner import surface_target_tets

    tets = surface_target_tets(doc)
    if tets is not None:  # a surface file: its physics mesh size and float32 too
        axes["target_tets"] = sorted({max(int(tets * f), 10) for f in TARGET_TETS_FRACTIONS})
        axes["precision"] = ["float32", "float64"]
    return axes


def load_space(path) -> dict:
    """A search-space TOML file: any of ``integrator``, ``element``, ``substeps``, ``tol``, ``cg_tol``,
    ``precision``, ``linear_solver``, ``target_tets`` (arrays of values) and ``subspace`` (array of mode counts)."""
    from warpfem.scenes.schema import read_toml

    data = read_toml(os.fspath(path), GridError, what="search-space file")
    bad = sorted(set(data) - set(_AXES))
    if bad:
        raise GridError(f"{path}: {bad[0]}: unknown axis; known: {', '.join(_AXES)}")
    for k, v in data.items():
        if not isinstance(v, list) or (k != "subspace" and not v):
            raise GridError(f"{path}: {k}: expected a non-empty array of values")
    return data


def search_space(doc, scene_path, axes: dict | None = None, space: str = "default") -> tuple:
    """(candidates, dropped): every combination of the axes that the scene layer accepts, one per
    distinct effective setting. ``axes`` overrides the axes of ``space`` (:func:`space_axes`:
    ``"default"``, the registered dynamic integrators on the scene's element and its higher-order
    partner with :data:`DEFAULT_AXES`; ``"full"``, every registered integrator, element and linear
    solver with :data:`FULL_AXES`); ``subspace``: a list of mode counts for reduced candidates
    (default none: training takes minutes per size)."""
    ax = {**space_axes(space, doc), "subspace": []}
    ax.update(axes or {})
    from warpfem.scenes import INTEGRATORS

    out, seen, dropped = [], {}, []
    solvers = ax.get("linear_solver") or [None]
    for integ, el, sub, tol, cg, prec, tets in itertools.product(ax["integrator"], ax["element"], ax["substeps"], ax["tol"],
                                                                ax["cg_tol"], ax["precision"], ax.get("target_tets") or [None]):
        entry = INTEGRATORS.get(integ)
        for ls in (solvers if entry is not None and "linear_solver" in entry.keys else [None]):
            _add(out, seen, dropped, doc, scene_path, dict(integrator=integ, element=el, substeps=sub, tol=tol, cg_tol=cg,
                                                           precision=prec, linear_solver=ls, target_tets=tets))
    for modes, sub, tol, prec in itertools.product(ax.get("subspace") or [], ax["substeps"], ax["tol"], ax["precision"]):
        _add(out, seen, dropped, doc, scene_path, dict(subspace={"modes": int(modes)}, substeps=sub, tol=tol, precision=prec))
    return out, dropped


def _add(out, seen, dropped, doc, scene_path, kw):
    from warpfem.scenes import INTEGRATORS

    kw = {k: v for k, v in kw.items() if v is not None}
    entry = INTEGRATORS.get(kw.get("integrator"))
    if entry is not None:  # knobs this integrator does not take: not in its name (same run once)
        for k in ("tol", "cg_tol", "linear_solver"):
            if k not in entry.keys:
                kw.pop(k, None)
    try:
        cfg = _cfg(**kw)
        cfg.check("search space")
    except (GridError, TypeError) as e:
        raise GridError(f"search space: {e}") from e
    try:
        spec = variant_scene(doc, scene_path, cfg).spec
    except Unavailable as e:
        dropped.append((cfg.name, str(e).splitlines()[0][:200]))
        return
    eff = json.dumps([cfg.precision, {k: v for k, v in spec.integrator.items() if not k.startswith("require")},
                      spec.mesh.get("element"), spec.subspace and {k: v for k, v in spec.subspace.items() if k != "cache"},
                      spec.mesh.get("target_tets")],
                     sort_keys=True, default=str)
    if eff in seen:
        return
    seen[eff] = cfg.name
    out.append(cfg)


@dataclass
class TuneResult:
    """What ``tune`` found (JSON with :meth:`to_json`)."""

    scene: str  # the scene file, relative to the repository root (warpfem.paths.portable_path); see scene_file()
    max_error: float
    quantity: str
    cost: str
    frames: int
    winner: dict | None
    runners_up: list
    rungs: list
    pruned: list
    candidates: int
    dropped: list
    reference: dict
    search: dict
    scene_out: str | None = None
    device: str = "cpu"
    executor: str = ""
    notes: list = field(default_factory=list)
    schema: str = "warpfem.tune/1"
    #: the scene file on this machine as the search read it (absolute): kept out of the JSON, which
    #: records ``scene`` relative to the repository root
    local_scene_file: str | None = field(default=None, repr=False, compare=False)
    #: the tuned scene file as the caller gave it to write_scene (relative to the current folder, or
    #: absolute): what the terminal report prints; kept out of the JSON (``scene_out`` there)
    local_scene_out: str | None = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("local_scene_file")
        d.pop("local_scene_out")
        return _json_value(d)

    def to_json(self, path) -> str:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        with open(path, "w") as f:
            json.dump(self.to_dict(), f, indent=1, allow_nan=False)
        return path

    def scene_file(self) -> str:
        """The scene file on this machine: the one the search read, else ``scene`` (recorded
        relative to the repository root) resolved there."""
        if self.local_scene_file:
            return self.local_scene_file
        root = repository_root()
        return os.path.join(root, self.scene) if root and not os.path.isabs(self.scene) else self.scene

    def winner_config(self) -> TradeoffConfig | None:
        return None if self.winner is None else TradeoffConfig.from_dict(self.winner["config"])


def _cost(res, cost):
    return res.work if cost == "work" else res.seconds_per_sim_second


def _error(res, quantity):
    return getattr(res, QUANTITY_FIELDS[quantity])


def _row(res, quantity, cost) -> dict:
    return {"name": res.name, "config": res.config, "status": res.status, "note": res.note,
            "error": _error(res, quantity), "cost": _cost(res, cost), "seconds_per_sim_second": res.seconds_per_sim_second,
            "work": res.work, "newton_per_step": res.newton_per_step, "cg_per_step": res.cg_per_step,
            "tip_error": res.tip_error, "rms_error": res.rms_error,
            "discretisation_error": getattr(res, f"discretisation_{quantity}_error"),
            "solver_error": getattr(res, f"solver_{quantity}_error"), "ran_on": res.ran_on}


def tune(scene_path, max_error: float, *, quantity="tip", frames=None, device="cpu", axes=None, candidates=None,
         truth: TruthSpec | None = TruthSpec(), reference_config: TradeoffConfig | None = None, reference=None,
         cost="time", eta: int = 3, keep: int = 3, executor=None, log=None, tip_point=None,
         space: str = "default") -> TuneResult:
    """Search the cheapest configuration of the scene whose ``quantity`` error ("tip" or "rms")
    against the reference is at most ``max_error`` (see the module docstring).

    ``space``: ``"default"`` (minutes on the shipped scenes) or ``"full"`` (every registered value:
    hours), see :func:`search_space`; ``axes``: overrides of its axes, or ``candidates``: an explicit
    list of :class:`TradeoffConfig`. ``truth``: the converged reference (None: the tight run on the
    scene's own mesh, solver/step error only). ``reference``: a :class:`warpfem.tradeoff.reference.Reference`
    computed before (for these frames), reused instead of running it again. ``cost``: "time" or
    "work". ``executor``: serial (default) or :class:`warpfem.tradeoff.cluster.DaskExecutor`.
    ``log(line)`` gets, before any run, the number of runs of each stage (:func:`plan_runs`), then a
    line per finished run with the stage's elapsed time and ETA. Every run reads the scene's mesh:
    a surface mesh's "tetrahedralisation cache hit" line is logged once, after the search, with
    the number of hits (:class:`_CacheHitLine`)."""
    with _CacheHitLine():
        return _tune(scene_path, max_error, quantity=quantity, frames=frames, device=device, axes=axes,
                     candidates=candidates, truth=truth, reference_config=reference_config, reference=reference,
                     cost=cost, eta=eta, keep=keep, executor=executor, log=log, tip_point=tip_point, space=space)


class _CacheHitLine:
    """Inside it, the tetrahedralisation cache's "cache hit" INFO lines (one per run of a search:
    every run loads the scene) are counted, not logged; on leaving, one line per cache entry says
    how many times it was read: ``PATH: tetrahedralisation cache hit ENTRY (N times)``."""

    _MESSAGE = "%s: tetrahedralisation cache hit %s"

    def __init__(self):
        import logging

        self.logger = logging.getLogger("warpfem.mesh.tetrahedralization")
        self.hits = {}  # (surface path, cache entry) -> count, in order of the first hit

    def filter(self, record) -> bool:
        if record.msg == self._MESSAGE and len(record.args or ()) == 2:
            key = tuple(str(a) for a in record.args)
            self.hits[key] = self.hits.get(key, 0) + 1
            return False
        return True

    def __enter__(self):
        self.logger.addFilter(self)
        return self

    def __exit__(self, *exc):
        self.logger.removeFilter(self)
        for (path, entry), n in self.hits.items():
            self.logger.info(self._MESSAGE + " (%d time%s)", path, entry, n, "" if n == 1 else "s")
        return False


def _tune(scene_path, max_error, *, quantity, frames, device, axes, candidates, truth, reference_config, reference,
          cost, eta, keep, executor, log, tip_point, space) -> TuneResult:
    """:func:`tune`'s search (its arguments, all given)."""
    from warpfem.scenes import load_scene

    if quantity not in QUANTITY_FIELDS:
        raise GridError(f"quantity must be one of {', '.join(QUANTITY_FIELDS)}, got {quantity!r}")
    if cost not in ("time", "work"):
        raise GridError(f"cost must be 'time' or 'work', got {cost!r}")
    if isinstance(max_error, bool) or not isinstance(max_error, (int, float)) or not max_error > 0 or not math.isfinite(max_error):
        raise GridError(f"max error must be a number > 0, got {max_error!r}")
    if eta < 2 or keep < 1:
        raise GridError(f"eta must be >= 2 and keep >= 1, got {eta}, {keep}")
    scene_path = os.fspath(scene_path)
    base = load_scene(scene_path)
    doc = scene_document(scene_path)
    frames = int(frames or base.spec.output["frames"])
    if frames < 1:
        raise GridError(f"frames must be >= 1, got {frames}")
    log = log or (lambda s: None)
    executor = executor or SerialExecutor()
    t_start = time.perf_counter()
    dropped = []
    if candidates is None:
        candidates, dropped = search_space(doc, scene_path, axes, space)
    if not candidates:
        raise GridError("the search space has no configuration this scene accepts"
                        + (f" (e.g. {dropped[0][0]}: {dropped[0][1]})" if dropped else ""))
    log(f"{len(candidates)} candidate configurations ({len(dropped)} combinations the scene rejects or that repeat)")
    notes = []
    runs = {"reference": 0, "prefix": 0, "full": 0}
    frame_runs = 0
    with tempfile.TemporaryDirectory(prefix="warpfem_tune_") as cache_dir:
        # the reference (and the time-converged run on every candidate mesh)
        if reference is None:
            ref_cfg = reference_config or _cfg(**_REFERENCE, substeps=4)
            plan = plan_reference(doc, scene_path, base, ref_cfg, truth, candidates)
            planned = plan_runs(len(candidates), frames, eta=eta, keep=keep, reference_runs=len(plan["jobs"]))
            log(format_plan(planned))
            stage = _Stage(log, f"reference ({frames} frames)", [_run_weight(c, doc) for c in plan["jobs"]])
            outs = executor.map(run_job, [make_job(doc, scene_path, c, device=device, frames=frames, plan=plan,
                                                   tip_point=tip_point) for c in plan["jobs"]],
                                on_done=lambda i, o: stage.done(i, _job_outcome(o, plan["jobs"][i], None)[0].name))
            outs = [_job_outcome(o, plan["jobs"][i], getattr(executor, "retried", {}).get(i)) for i, o in enumerate(outs)]
            reference = finish_reference(plan, outs, tip_point=tip_point, frames=frames)
            runs["reference"] = len(plan["jobs"])
        elif reference.frames != frames:
            raise GridError(f"the given reference covers {reference.frames} frames, the search {frames}")
        else:
            planned = plan_runs(len(candidates), frames, eta=eta, keep=keep, reference_runs=0)
            log(format_plan(planned))
        est = (reference.info.get("time") or {}).get(f"estimated_error_{quantity}")
        if est is not None and est > max_error / 3:
            notes.append(f"the reference's own estimated {quantity} error ({est:.2e}) is not small against the budget "
                         f"({max_error:.2e}): tighten it (truth substeps) or loosen the budget")
        if reference.info.get("flag"):
            notes.append(reference.info["flag"])
        rc = reference.info.get("cost") or {}
        if reference.plan.get("scene_mesh", (None, 1, None))[2] is not None and rc.get("elements"):
            notes.append(f"the reference run cost {_fmt(rc.get('seconds_per_sim_second'), '.3g')} s per simulated second "
                         f"on {rc['elements']} elements, {rc.get('vertices')} vertices (work {_fmt(rc.get('work'), '.3g')})")
        # a mesh that alone misses the budget cannot be in the answer
        pruned, alive = [], []
        for c in candidates:
            el, rf, tt = reference.plan["mesh_of"](c)
            d = reference.discretisation_error(el, rf, quantity, target_tets=tt)
            if math.isfinite(d) and d > max_error:
                what = f"{el} mesh" + (f" of target_tets = {tt}" if tt else "")
                pruned.append({"name": c.name, "stage": "discretisation",
                               "reason": f"{what}: discretisation {quantity} error {d:.3g} > {max_error:g}"})
            else:
                alive.append(c)
        log(f"{len(alive)} candidates after the discretisation check ({len(pruned)} dropped)")

        def run_all(cfgs, n, label):
            jobs = [make_job(doc, scene_path, c, device=device, frames=n, plan=reference.plan, tip_point=tip_point,
                             cache_dir=cache_dir) for c in cfgs]
            stage = _Stage(log, label, [_run_weight(c, doc) for c in cfgs])
            outs = executor.map(run_job, jobs, on_done=lambda i, o: stage.done(i, cfgs[i].name))
            res = []
            for i, o in enumerate(outs):
                r, traj = _job_outcome(o, cfgs[i], getattr(executor, "retried", {}).get(i))
                if traj is not None:
                    reference.errors(r, traj, frames=n)
                res.append(r)
            return res

        _pretrain(doc, scene_path, alive, cache_dir, device, log)
        prefixes = prefix_lengths(frames)
        rungs = []
        ranked, fallback = alive, []
        for n in prefixes:
            if len(ranked) <= keep:
                break
            res = run_all(ranked, n, f"prefix of {n} frame(s)")
            runs["prefix"] += len(res)
            frame_runs += n * len(res)
            feasible = sorted([r for r in res if r.status == "ok" and _error(r, quantity) <= max_error],
                              key=lambda r: (_cost(r, cost), _error(r, quantity)))
            for r in res:
                if r not in feasible:
                    why = (f"{quantity} error {_error(r, quantity):.3g} > {max_error:g}" if r.status == "ok"
                           else f"{r.status}: {r.note}")
                    pruned.append({"name": r.name, "stage": f"prefix {n} frames", "reason": why})
            n_keep = max(keep, math.ceil(len(feasible) / eta))
            for r in feasible[n_keep:]:
                pruned.append({"name": r.name, "stage": f"prefix {n} frames",
                               "reason": f"not among the {n_keep} cheapest within budget (kept as a fallback)"})
            rungs.append({"frames": n, "evaluated": [_row(r, quantity, cost) for r in res],
                          "kept": [r.name for r in feasible[:n_keep]]})
            log(f"prefix of {n} frame(s): {len(res)} run, {len(feasible)} within budget, {min(n_keep, len(feasible))} kept")
            by_name = {c.name: c for c in ranked}
            ranked = [by_name[r.name] for r in feasible[:n_keep]]
            fallback = [by_name[r.name] for r in feasible[n_keep:]] + fallback  # tried if the kept ones fail
            if not ranked:
                break
        ranked = ranked + fallback
        # full runs of the cheapest survivors: the winner and its runners-up
        full, winner, start = [], None, 0
        while start < len(ranked) and winner is None:
            batch = ranked[start:start + keep]
            start += keep
            res = run_all(batch, frames, f"full runs ({frames} frames)")
            runs["full"] += len(res)
            frame_runs += frames * len(res)
            full += res
            ok = sorted([r for r in full if r.status == "ok" and _error(r, quantity) <= max_error],
                        key=lambda r: (_cost(r, cost), _error(r, quantity)))
            winner = ok[0] if ok else None
            log(f"full runs: {len(res)}, " + (f"winner {winner.name}" if winner else "none within budget yet"))
        full_sorted = sorted(full, key=lambda r: (not (r.status == "ok" and _error(r, quantity) <= max_error),
                                                  _cost(r, cost) if r.status == "ok" else math.inf))
    if winner is None:
        notes.append(f"no candidate meets {quantity} error <= {max_error:g}")
    search = {"candidates_run": runs, "planned": planned, "frame_runs": frame_runs, "whole_grid_frame_runs": len(candidates) * frames,
              "prefixes": prefixes, "eta": eta, "keep": keep, "seconds": time.perf_counter() - t_start}
    result = TuneResult(scene=portable_path(scene_path), max_error=float(max_error), quantity=quantity, cost=cost,
                      frames=frames, winner=None if winner is None else _row(winner, quantity, cost),
                      runners_up=[_row(r, quantity, cost) for r in full_sorted if r is not winner],
                      rungs=rungs, pruned=pruned, candidates=len(candidates), dropped=[list(d) for d in dropped],
                      reference=reference.info, search=search, device=str(device), executor=executor.description,
                      notes=notes)
    result.local_scene_file = os.path.abspath(scene_path)
    return result


def prefix_lengths(frames: int) -> list:
    """The prefixes (frames) of successive halving: frames/8, frames/4, frames/2 (distinct, shorter than the run)."""
    return sorted({max(1, frames // 2 ** k) for k in (3, 2, 1)} - {frames})


def plan_runs(candidates: int, frames: int, *, eta: int = 3, keep: int = 3, reference_runs: int = 0) -> dict:
    """How many runs a search of ``candidates`` configurations does, at most, stage by stage (before
    any run): the reference runs, every prefix rung with all its candidates surviving (a rung keeps
    at most max(keep, ceil(n / eta)) of its n), and ``keep`` full runs (more only when none of them
    is within budget). The discretisation check and the budget only lower these counts."""
    stages = [("reference", frames, int(reference_runs))] if reference_runs else []
    n = int(candidates)
    for p in prefix_lengths(frames):
        if n <= keep:
            break
        stages.append(("prefix", p, n))
        n = max(keep, math.ceil(n / eta))
    stages.append(("full", frames, min(keep, n)))
    return {"candidates": int(candidates), "stages": stages, "runs": sum(s[2] for s in stages),
            "run_frames": sum(s[1] * s[2] for s in stages)}


def format_plan(plan: dict) -> str:
    """The up-front line: ``N candidates: at most R runs (...)``."""
    parts = []
    for kind, n_frames, count in plan["stages"]:
        what = {"reference": "reference", "prefix": "prefix", "full": "full"}[kind]
        parts.append(f"{count} {what} run(s) of {n_frames} frame(s)")
    return (f"search plan: {plan['candidates']} candidates; at most {plan['runs']} runs "
            f"({plan['run_frames']} run-frames): " + ", then ".join(parts)
            + " (fewer when candidates are pruned; more full runs only if none is within budget)")


class _Stage:
    """Progress of one search stage: a line per finished run with elapsed time and ETA. The ETA
    weighs the runs left by a relative cost estimate (:func:`_run_weight`: steps x element nodes
    x refinement cubed), so a stage that starts with its most expensive run (the reference on the
    refined mesh at the finest step) does not predict every run to cost as much."""

    def __init__(self, log, label, weights):
        self.log, self.label = log, label
        self.weights = [float(w) for w in weights]
        self.total, self.count, self.done_weight = len(self.weights), 0, 0.0
        self.t0 = time.perf_counter()
        log(f"{label}: {self.total} run(s)")

    def done(self, i, name):
        self.count += 1
        self.done_weight += self.weights[i]
        el = time.perf_counter() - self.t0
        left = sum(self.weights) - self.done_weight
        eta = el / max(self.done_weight, 1e-300) * left
        self.log(f"  {self.label} {self.count}/{self.total}: {name}  elapsed {_clock(el)}  ETA {_clock(eta)}")


def _run_weight(cfg, doc) -> float:
    """Relative cost of a run (for ETAs only): substeps x nodes per element x refine^3."""
    from warpfem.mesh.element_types import ELEMENTS

    from .runner import surface_target_tets

    mesh = (doc or {}).get("mesh") or {}
    el = cfg.element or mesh.get("element", "tet4")
    k = ELEMENTS[el].nodes_per_element if el in ELEMENTS else 4
    sub = cfg.substeps or ((doc or {}).get("integrator") or {}).get("substeps") or 1
    tets = surface_target_tets(doc)
    size = float(cfg.target_tets) / tets if cfg.target_tets and tets else 1.0
    return float(sub) * k * float(cfg.refine or 1) ** 3 * size


def _clock(seconds) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def _pretrain(doc, scene_path, cfgs, cache_dir, device, log):
    """Train every reduced candidate's subspace once, into the shared cache (offline cost, not in
    the candidates' cost). Candidates on a cluster without this filesystem train their own."""
    from .runner import Unavailable, _build

    done = set()
    for c in cfgs:
        if c.subspace is None or c.subspace in done:
            continue
        done.add(c.subspace)
        try:
            _build(variant_scene(doc, scene_path, dataclasses.replace(c, substeps=None, tol=None), cache_dir=cache_dir),
                   device=device, precision="float64")
            log(f"trained subspace {c.subspace_dict()}")
        except Unavailable as e:
            log(f"subspace {c.subspace_dict()}: {e}")


# ----------------------------------------------------------------------------- writing the scene
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write {v!r} to TOML")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _toml_table(lines, prefix, table, header):
    """Append ``table``'s lines: its ``header`` (none at the top level), its values, then its
    tables ``[prefix.key]`` and arrays of tables ``[[prefix.key]]`` (a [[body]]'s [body.mesh])."""
    if header:
        lines += ["", header]
    for k, v in table.items():
        if v is not None and not isinstance(v, dict) and not _is_table_array(v):
            lines.append(f"{k} = {_toml_value(v)}")
    for k, v in table.items():
        name = f"{prefix}.{k}" if prefix else k
        if isinstance(v, dict):
            _toml_table(lines, name, v, f"[{name}]")
        elif _is_table_array(v):
            for item in v:
                _toml_table(lines, name, item, f"[[{name}]]")


def toml_dumps(doc: dict) -> str:
    """TOML text of a scene document (scalars, arrays, tables, arrays of tables, and tables within
    them)."""
    lines = []
    _toml_table(lines, "", doc, None)
    return "\n".join(lines) + "\n"


def write_scene(result: TuneResult, path) -> str:
    """Write the winner as a scene file: its input paths (mesh, surface, index files: relative to
    the scene file) re-anchored to its new location; its ``[output]`` paths kept as the scene has
    them (they are relative to the folder a scene is run from, so the tuned scene run from the
    folder ``tune`` was run in writes the files the original would); a reduced winner's cache is
    left to ``warpfem train``. ``path`` is printed by :func:`format_tune` as given."""
    from warpfem.scenes.schema import rebase_scene_paths

    cfg = result.winner_config()
    if cfg is None:
        raise ValueError("no winner to write")
    scene_file = result.scene_file()
    src_dir = os.path.dirname(scene_file)
    out_dir = os.path.dirname(os.path.abspath(path))
    d = variant_document(scene_document(scene_file), dataclasses.replace(cfg, name=""), for_study=False)
    if d.get("subspace") is not None:
        d["subspace"].pop("cache", None)
    d["integrator"] = {"type": d["integrator"]["type"], **d["integrator"]}  # type first
    output = dict(d.get("output") or {})
    rebase_scene_paths(d, src_dir, out_dir)
    if output:  # outputs: relative to the current folder when run, not to the scene file
        d["output"] = output
    w = result.winner
    head = [f"# Tuned by `warpfem tune` from {os.path.relpath(scene_file, out_dir)}: the cheapest configuration found",
            f"# with {result.quantity} error <= {result.max_error:g} against the converged reference "
            f"({result.frames} frames).",
            f"# Measured: {result.quantity} error {w['error']:.3g} (discretisation {_fmt(w['discretisation_error'], '.3g')}, "
            f"solver/step {_fmt(w['solver_error'], '.3g')}), {w['seconds_per_sim_second']:.3g} s per simulated second "
            f"({result.device}), work {w['work']:.3g}.",
            f"# Run it with: warpfem run {os.fspath(path)} --precision {cfg.precision}",
            "# from the folder `warpfem tune` ran in: like the original's, its [output] paths are relative to the",
            "# folder it is run from, so it then writes the files the original would."]
    os.makedirs(out_dir, exist_ok=True)
    with open(path, "w") as f:
        f.write("\n".join(head) + "\n" + toml_dumps(d))
    result.scene_out = portable_path(path)
    result.local_scene_out = os.fspath(path)
    return path


def format_tune(result: TuneResult) -> str:
    """The terminal report."""
    q = result.quantity
    s = result.search
    lines = [f"{os.path.basename(result.scene)}: cheapest configuration with {q} error <= {result.max_error:g} "
             f"({result.frames} frames, cost = {result.cost}, {result.executor})",
             f"searched {result.candidates} candidates: {s['candidates_run']['prefix']} prefix runs "
             f"({'/'.join(map(str, s['prefixes'])) or '-'} frames), {s['candidates_run']['full']} full runs, "
             f"{s['candidates_run']['reference']} reference runs; search: {s['frame_runs']} run-frames vs "
             f"{s['whole_grid_frame_runs']} for the whole grid; {s['seconds']:.0f} s in all"]
    rows = ([("winner", result.winner)] if result.winner else []) + [("", r) for r in result.runners_up]
    if rows:
        wid = max([len("configuration")] + [len(r["name"]) for _, r in rows])  # whole names (element last)
        lines.append(f"  {'':7}{'configuration':{wid}} {q + ' err':>9} {'disc':>9} {'solver':>9} {'s/sim-s':>9} {'work/sim-s':>11}"
                     f"  budget: {q} err <= {result.max_error:g}")
        for tag, r in rows:
            ok = r["status"] == "ok"
            err = _fmt(r["error"], ".3g") if ok else r["status"]
            within = ok and r["error"] is not None and r["error"] <= result.max_error
            mark = "within" if within else "over budget" if ok else "failed"
            lines.append(f"  {tag:7}{r['name']:{wid}} {err:>9} {_fmt(r['discretisation_error'], '.3g'):>9} "
                         f"{_fmt(r['solver_error'], '.3g'):>9} {_fmt(r['seconds_per_sim_second'], '.3g'):>9} "
                         f"{_fmt(r['work'], '.3g'):>11}  {mark}")
    lines += [f"note: {n}" for n in result.notes]
    if result.scene_out:  # as the caller gave it (relative to the current folder, or absolute)
        lines.append(f"wrote {result.local_scene_out or result.scene_out}")
    return "\n".join(lines)


def rerun_error(scene_file, reference, *, device="cpu", precision="float64", quantity="tip") -> float:
    """Run a scene file as it is (e.g. the one ``tune`` wrote) and return its error against
    ``reference`` (over the reference's frames)."""
    job = make_job(scene_document(scene_file), os.fspath(scene_file), TradeoffConfig(name="rerun", precision=precision),
                   device=device, frames=reference.frames, plan=reference.plan)
    res, traj = run_job(job)
    if traj is None:
        raise RuntimeError(f"{scene_file}: {res.status}: {res.note}")
    reference.errors(res, traj)
    return _error(res, quantity)
