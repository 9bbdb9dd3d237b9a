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
"""

from __future__ import annotations

import copy
import json
import math
import os
import platform
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from warpfem.scenes.schema import read_toml

__all__ = ["without_timings", "planned_runs", "TruthSpec", "SerialExecutor", "run_job", "work_proxy", "TradeoffConfig", "TradeoffGrid", "GridError", "StudyResult", "ConfigResult", "builtin_grid",
           "load_grid", "pareto_front", "run_study", "load_study", "format_table", "plot_pareto",
           "QUANTITIES", "SCHEMA_VERSION", "scene_document", "set_quantity", "format_markdown"]

SCHEMA_VERSION = "warpfem.tradeoff/1"

# error measure used for the frontier / plot -> result field
QUANTITIES = {"tip": "tip_error", "rms": "rms_error", "surface": "surface_error", "energy": "energy_error"}


class GridError(ValueError):
    """An invalid grid (file or options): the message names the file and the key."""


# ----------------------------------------------------------------------------- configurations
@dataclass(frozen=True)
class TradeoffConfig:
    """Overrides of the scene's settings (None: keep the scene's value).

    precision: "float32" | "float64" (always set; default float64).
    tol, max_iters, cg_tol: ``[integrator]`` Newton keys (ignored by integrators without them).
    substeps: time steps per output frame (dt = 1 / (fps * substeps)).
    integrator: ``[integrator].type``; element: ``[mesh].element``.
    subspace: the ``[subspace]`` table (reduced run), e.g. {"modes": 20, "cubature_tolerance": 0.01}.
    """

    name: str
    precision: str = "float64"
    tol: float | None = None
    max_iters: int | None = None
    cg_tol: float | None = None
    substeps: int | None = None
    integrator: str | None = None
    element: str | None = None
    subspace: tuple | None = None  # sorted (key, value) pairs (hashable); see subspace_dict()
    max_cg_iters: int | None = None
    refine: int | None = None  # box generator: [mesh].cells multiplied by this (spatial refinement)
    linear_solver: str | None = None  # [integrator].linear_solver, for integrators that take one

    def subspace_dict(self) -> dict | None:
        return None if self.subspace is None else dict(self.subspace)

    def as_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["subspace"] = self.subspace_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict, *, where: str = "config") -> "TradeoffConfig":
        d = dict(d)
        known = {f.name for f in fields(cls)}
        bad = sorted(set(d) - known)
        if bad:
            raise GridError(f"{where}: unknown key {bad[0]!r}; known keys: {', '.join(sorted(known))}")
        sub = d.get("subspace")
        if sub is not None:
            if not isinstance(sub, dict):
                raise GridError(f"{where}.subspace: expected a table, got {sub!r}")
            d["subspace"] = tuple(sorted(sub.items()))
        if "name" not in d or not d["name"]:
            d["name"] = _auto_name(d)
        cfg = cls(**d)
        cfg.check(where)
        return cfg

    def check(self, where="config"):
        if self.precision not in ("float32", "float64"):
            raise GridError(f"{where}.precision: must be 'float32' or 'float64', got {self.precision!r}")
        for k in ("tol", "cg_tol"):
            v = getattr(self, k)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1):
                raise GridError(f"{where}.{k}: must be a number in (0, 1), got {v!r}")
        for k in ("max_iters", "substeps", "max_cg_iters", "refine"):
            v = getattr(self, k)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise GridError(f"{where}.{k}: must be an integer >= 1, got {v!r}")
        if self.linear_solver is not None and self.linear_solver not in ("auto", "pcg", "direct", "amg"):
            raise GridError(f"{where}.linear_solver: must be one of auto, pcg, direct, amg, got {self.linear_solver!r}")
        for k in ("integrator", "element", "name", "linear_solver"):
            v = getattr(self, k)
            if v is not None and not isinstance(v, str):
                raise GridError(f"{where}.{k}: expected a string, got {v!r}")


def _auto_name(d: dict) -> str:
    parts = []
    if d.get("precision", "float64") == "float32":
        parts.append("f32")
    for k, short in (("tol", "tol"), ("max_iters", "it"), ("cg_tol", "cg"), ("max_cg_iters", "cgit"), ("substeps", "sub")):
        if d.get(k) is not None:
            parts.append(f"{short}={d[k]:g}")
    if d.get("integrator"):
        parts.append({"stiffness_warping": "warping", "backward_euler": "newton"}.get(d["integrator"], d["integrator"]))
    if d.get("element"):
        parts.append(d["element"])
    if d.get("refine") not in (None, 1):
        parts.append(f"cells x{d['refine']}")
    if d.get("linear_solver"):
        parts.append(d["linear_solver"])
    sub = d.get("subspace")
    if sub is not None:
        s = dict(sub)
        parts.append(f"r={s.get('modes', 'def')}" + (f",cub={s['cubature_tolerance']:g}" if "cubature_tolerance" in s else ""))
    return " ".join(parts) if parts else "scene"


def _cfg(**kw) -> TradeoffConfig:
    if "subspace" in kw and isinstance(kw["subspace"], dict):
        kw["subspace"] = tuple(sorted(kw["subspace"].items()))
    kw.setdefault("name", _auto_name(kw))
    return TradeoffConfig(**kw)


@dataclass(frozen=True)
class TruthSpec:
    """The converged reference ("truth") of a study.

    element: the higher-order element of the reference mesh (None: tet10 for a tet scene, hex27 for
        a hex scene). refine: the box generator's cells multiplied by this (>= 2 also runs the
        same element at half of it, showing the space convergence). substeps: the finest time step
        of the ladder S, S/2, S/4 (None: the grid reference's substeps); the reference trajectory is
        the Richardson extrapolation 2 x(S) - x(S/2). The solver settings are the grid's reference."""

    element: str | None = None
    refine: int = 2
    substeps: int | None = None

    def as_dict(self) -> dict:
        return {"element": self.element, "refine": self.refine, "substeps": self.substeps}

    @classmethod
    def from_dict(cls, d: dict, *, where: str = "truth") -> "TruthSpec":
        from warpfem.scenes import ELEMENTS

        bad = sorted(set(d) - {"element", "refine", "substeps"})
        if bad:
            raise GridError(f"{where}: unknown key {bad[0]!r}; known keys: element, refine, substeps")
        el = d.get("element")
        if el is not None and el not in ELEMENTS:
            raise GridError(f"{where}.element: must be one of {', '.join(ELEMENTS)}, got {el!r}")
        for k in ("refine", "substeps"):
            v = d.get(k)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise GridError(f"{where}.{k}: must be an integer >= 1, got {v!r}")
        return cls(element=el, refine=int(d.get("refine", 2)), substeps=d.get("substeps"))


@dataclass
class TradeoffGrid:
    """Configurations to run, the reference settings, frames and the tip point.

    ``truth``: a :class:`TruthSpec` (converged reference in space and time; the built-in grids and
    grid files use one) or None: the ``reference`` configuration on the scene's mesh is the truth
    (solver / time-step error only)."""

    configs: list
    reference: TradeoffConfig
    frames: int | None = None
    tip_point: tuple | None = None
    name: str = "custom"
    truth: TruthSpec | None = None


_REFERENCE = dict(name="reference", precision="float64", tol=1e-9, max_iters=100, cg_tol=1e-9, max_cg_iters=20000)


def _element_names():
    from warpfem.scenes import ELEMENTS

    return list(ELEMENTS)


def builtin_grid(name: str) -> TradeoffGrid:
    """``quick``: one knob at a time around the scene's own settings (float64), plus a "fast"
    combination, the other time integrators (Newmark, BDF2) and linear solvers (pcg, direct); ``full``: the product precision x tol x cg_tol x substeps plus the one-at-a-time
    integrator / element / reduced / iteration-cap variants. Element and reduced variants are listed
    for every name the scene schema knows; unavailable ones are skipped at run time with a note."""
    if name == "quick":
        cs = [_cfg(name="scene"), _cfg(precision="float32"),
              _cfg(tol=1e-3), _cfg(tol=1e-7), _cfg(max_iters=2),
              _cfg(cg_tol=1e-2), _cfg(cg_tol=1e-6), _cfg(substeps=2),
              _cfg(name="fast: f32 tol=1e-3 cg=1e-2", precision="float32", tol=1e-3, cg_tol=1e-2),
              _cfg(integrator="stiffness_warping"),
              _cfg(integrator="newmark"), _cfg(integrator="bdf2"), _cfg(integrator="newmark", substeps=2),
              _cfg(integrator="newmark", precision="float32", tol=1e-3, cg_tol=1e-2),
              _cfg(linear_solver="pcg"), _cfg(linear_solver="direct")]
        cs += [_cfg(element=e) for e in _element_names()]
        cs += [_cfg(subspace={"modes": 20, "cubature_tolerance": 0.01})]
        ref_sub = 4
    elif name == "full":
        cs = []
        for prec in ("float32", "float64"):
            for tol in (1e-3, 1e-5, 1e-7):
                for cg in (1e-2, 1e-4, 1e-6):
                    for sub in (1, 2, 4):
                        cs.append(_cfg(precision=prec, tol=tol, cg_tol=cg, substeps=sub))
        cs += [_cfg(max_iters=m) for m in (1, 2, 5)]
        for prec in ("float32", "float64"):
            for sub in (1, 2, 4):
                cs.append(_cfg(precision=prec, integrator="stiffness_warping", substeps=sub))
        cs += [_cfg(element=e) for e in _element_names()]
        cs += [_cfg(subspace={"modes": r, "cubature_tolerance": c}) for r in (10, 20, 40) for c in (0.05, 0.01)]
        ref_sub = 8
    else:
        raise GridError(f"unknown built-in grid {name!r}; choose 'quick', 'full' or a .toml file")
    return TradeoffGrid(configs=cs, reference=_cfg(**_REFERENCE, substeps=ref_sub), name=name, truth=TruthSpec())


_GRID_KEYS = {"base", "exclude", "frames", "tip_point", "reference", "axes", "config", "truth"}


def load_grid(path) -> TradeoffGrid:
    """Read a grid TOML file.

    Keys: ``base`` ("quick"/"full": start from a built-in grid), ``exclude`` (config names to drop),
    ``frames``, ``tip_point`` ([x, y, z] rest position, m), ``[reference]`` (overrides of the
    reference config), ``[axes]`` (lists of values; their Cartesian product is added), ``[[config]]``
    (explicit configurations; keys of :class:`TradeoffConfig`).
    """
    path = os.fspath(path)
    data = read_toml(path, GridError, what="grid file")
    bad = sorted(set(data) - _GRID_KEYS)
    if bad:
        raise GridError(f"{path}: {bad[0]}: unknown key; known: {', '.join(sorted(_GRID_KEYS))}")
    grid = builtin_grid(data["base"]) if "base" in data else TradeoffGrid(configs=[], reference=_cfg(**_REFERENCE, substeps=4),
                                                                          truth=TruthSpec())
    grid.name = os.path.basename(path)
    if "truth" in data:  # [truth] table, or truth = false: the reference on the scene's own mesh
        t = data["truth"]
        if t is False:
            grid.truth = None
        elif isinstance(t, dict):
            grid.truth = TruthSpec.from_dict(t, where=f"{path}: [truth]")
        else:
            raise GridError(f"{path}: truth: expected a table or false, got {t!r}")
    if "reference" in data:
        if not isinstance(data["reference"], dict):
            raise GridError(f"{path}: [reference]: expected a table")
        ref = {**grid.reference.as_dict(), **data["reference"], "name": "reference"}
        grid.reference = TradeoffConfig.from_dict(ref, where=f"{path}: [reference]")
    if "axes" in data:
        axes = data["axes"]
        if not isinstance(axes, dict) or not axes:
            raise GridError(f"{path}: [axes]: expected a table of value lists")
        import itertools

        keys = list(axes)
        for k in keys:
            if not isinstance(axes[k], list) or not axes[k]:
                raise GridError(f"{path}: [axes].{k}: expected a non-empty array of values")
        for values in itertools.product(*(axes[k] for k in keys)):
            grid.configs.append(TradeoffConfig.from_dict(dict(zip(keys, values)), where=f"{path}: [axes]"))
    for i, c in enumerate(data.get("config", [])):
        grid.configs.append(TradeoffConfig.from_dict(c, where=f"{path}: [[config]] #{i + 1}"))
    if "frames" in data:
        if isinstance(data["frames"], bool) or not isinstance(data["frames"], int) or data["frames"] < 1:
            raise GridError(f"{path}: frames: must be an integer >= 1, got {data['frames']!r}")
        grid.frames = data["frames"]
    if "tip_point" in data:
        tp = data["tip_point"]
        if not (isinstance(tp, list) and len(tp) == 3 and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in tp)):
            raise GridError(f"{path}: tip_point: expected [x, y, z] (m), got {tp!r}")
        grid.tip_point = tuple(float(c) for c in tp)
    excl = data.get("exclude", [])
    if not isinstance(excl, list):
        raise GridError(f"{path}: exclude: expected an array of configuration names")
    names = {c.name for c in grid.configs}
    unknown = [e for e in excl if e not in names]
    if unknown:
        raise GridError(f"{path}: exclude: no configuration named {unknown[0]!r}; names: {', '.join(sorted(names))}")
    grid.configs = [c for c in grid.configs if c.name not in excl]
    if not grid.configs:
        raise GridError(f"{path}: the grid has no configurations")
    return grid


def _dedupe(configs, spec):
    """Drop repeated names and configurations equal to an earlier one once settings equal to the
    scene's own (element, integrator type, substeps) are read as "unchanged"."""
    import dataclasses

    same = {"element": spec.mesh["element"], "integrator": spec.integrator["type"],
            "substeps": spec.integrator.get("substeps")}
    seen_names, seen, out, dropped = set(), {}, [], []
    for c in configs:
        if c.name in seen_names:
            continue
        seen_names.add(c.name)
        norm = dataclasses.replace(c, name="", **{k: None for k, v in same.items() if getattr(c, k) == v})
        if norm in seen:
            dropped.append((c, seen[norm]))
            continue
        seen[norm] = c.name
        out.append(c)
    return out, dropped


# ----------------------------------------------------------------------------- Pareto
def pareto_front(times, errors) -> list:
    """Indices of the non-dominated points (minimise both ``times`` and ``errors``), by time.

    A point is dominated when another is no worse in both and strictly better in one. Points with
    a non-finite time or error are never on the front; exact duplicates are all kept.
    """
    t = np.asarray(times, dtype=np.float64)
    e = np.asarray(errors, dtype=np.float64)
    if t.shape != e.shape or t.ndim != 1:
        raise ValueError(f"times and errors must be 1-d of equal length, got {t.shape} and {e.shape}")
    ok = np.isfinite(t) & np.isfinite(e)
    front = []
    for i in np.flatnonzero(ok):
        dom = ok & (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        if not dom.any():
            front.append(int(i))
    return sorted(front, key=lambda i: (t[i], e[i]))


# ----------------------------------------------------------------------------- scene variants
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
        raise Unavailable(str(e)) from e
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
    if cfg.subspace is not None:
        sub = dict(cfg.subspace_dict())
        if "cache" not in sub and cache_dir is not None:
            key = "_".join(f"{k}{v}" for k, v in sorted(sub.items()))
            sub["cache"] = os.path.join(cache_dir, f"subspace_{key}.npz")
        d["subspace"] = sub
    return d


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


# ----------------------------------------------------------------------------- running one config
@dataclass
class ConfigResult:
    """One configuration's outcome. ``status``: "ok", "failed" (a step raised) or "skipped"."""

    config: dict
    status: str
    note: str = ""
    settings: dict = field(default_factory=dict)  # effective [integrator] / element / subspace
    frames: int = 0
    steps: int = 0
    build_seconds: float = 0.0
    train_seconds: float = 0.0
    step_seconds: float = 0.0
    seconds_per_sim_second: float = math.nan
    newton_iterations: int = 0
    cg_iterations: int = 0
    newton_per_step: float = math.nan
    cg_per_step: float = math.nan
    cg_per_sim_second: float = math.nan  # load-independent cost proxy (full-space runs)
    unconverged_frames: int = 0
    rms_error: float = math.nan
    surface_error: float = math.nan
    tip_error: float = math.nan
    tip_error_m: float = math.nan
    energy_error: float = math.nan
    energy_drift: float = math.nan
    on_frontier: bool = False
    # error split (against the converged reference; NaN when it is not available)
    discretisation_tip_error: float = math.nan  # time-converged run on this mesh/element vs the truth
    discretisation_rms_error: float = math.nan
    solver_tip_error: float = math.nan  # this configuration vs the time-converged run on its own mesh
    solver_rms_error: float = math.nan
    work: float = math.nan  # deterministic cost proxy per simulated second (see work_proxy)
    ran_on: str = ""  # host / process (and Dask worker) that ran and timed it

    @property
    def name(self) -> str:
        return self.config["name"]

    def as_dict(self) -> dict:
        return {k: _json_value(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d):
        names = {f.name for f in fields(cls)}
        return cls(**{k: (math.nan if v is None and k in _FLOAT_FIELDS else v) for k, v in d.items() if k in names})


_FLOAT_FIELDS = {f.name for f in fields(ConfigResult) if f.type in ("float", float)}


def _json_value(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None  # JSON has no NaN/inf
    if isinstance(v, dict):
        return {k: _json_value(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_value(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


class _Trajectory:
    def __init__(self):
        self.points, self.surface, self.tip, self.energy, self.motion_energy = [], [], [], [], []


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


def _run_one(doc, scene_path, cfg, *, device, frames, ref_info, cache_dir, tip_point=None, progress=None):
    """Run ``cfg``; returns (ConfigResult, _Trajectory or None)."""
    from warpfem.solvers.nonlinear import SolveFailed

    res = ConfigResult(config=cfg.as_dict(), status="skipped")
    try:
        scene = variant_scene(doc, scene_path, cfg, cache_dir=cache_dir)
        run, res.build_seconds, res.train_seconds = _build(scene, device=device, precision=cfg.precision)
    except Unavailable as e:
        res.note = f"not available: {e}"
        return res, None
    sp = scene.spec
    res.settings = {"integrator": {k: v for k, v in sp.integrator.items() if not k.startswith("require")},
                    "element": sp.mesh["element"], "subspace": sp.subspace,
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
        res.status, res.note = "failed", f"frame {run.frame}: {e}"
        return res, None
    except (NotImplementedError, ValueError, RuntimeError) as e:  # e.g. a reduced run with handles
        res.status, res.note = "skipped", f"not available: {type(e).__name__}: {e}"
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


def work_proxy(res: ConfigResult, run) -> float:
    """A deterministic, load-independent cost of a run (arbitrary units, comparable across
    configurations): every Newton iteration assembles forces and Hessian over the quadrature points,
    ~E q n^2 (E elements, q quadrature points, n nodes per element), every CG iteration is one
    element-by-element matrix-vector product, ~E n^2. A reduced run assembles over its cubature
    elements and solves an r x r system per Newton iteration (c q n^2 + r^3) and reconstructs the
    full positions once per step (N r, N vertices)."""
    mesh = run.scene.mesh()
    n = int(np.asarray(mesh.elements).shape[1])
    q = mesh.element.points_per_element
    E = mesh.num_elements
    sim = run.sim
    r = getattr(sim, "r", None)
    forces = getattr(sim, "forces", None)
    if r is not None and forces is not None:  # reduced
        c = int(getattr(forces, "c", E))
        return float(res.newton_iterations * (c * q * n * n + r ** 3) + res.steps * mesh.num_vertices * r)
    return float(res.newton_iterations * E * q * n * n + res.cg_iterations * E * n * n)


def _errors(res: ConfigResult, traj: _Trajectory, ref: dict):
    P = np.asarray(traj.points)[1:]
    R = ref["points"][1:]
    L = ref["size"]
    d2 = np.sum((P - R) ** 2, axis=2)  # (frames, points)
    res.rms_error = float(np.sqrt(d2.mean()) / L)
    if ref["surface"] is not None and traj.surface and np.shape(traj.surface[0]) == ref["surface"].shape[1:]:
        S = np.asarray(traj.surface)[1:]
        res.surface_error = float(np.sqrt(np.sum((S - ref["surface"][1:]) ** 2, axis=2).mean()) / L)
    elif ref["boundary"] is not None:
        res.surface_error = float(np.sqrt(d2[:, ref["boundary"]].mean()) / L)
    if ref.get("tip_point") is not None:
        tip = np.asarray(traj.tip)[1:]
    else:
        tip = P[:, ref["tip_vertex"]]
    err = np.linalg.norm(tip - ref["tip"][1:], axis=1).max()
    res.tip_error_m = float(err)
    res.tip_error = float(err / ref["tip_peak"]) if ref["tip_peak"] > 0 else math.nan
    if traj.energy and ref["energy"] is not None and len(traj.energy) == len(ref["energy"]):
        E = np.asarray(traj.energy)
        Er = ref["energy"]
        scale = ref["energy_scale"]
        if scale > 0:
            res.energy_error = float(np.max(np.abs(E[1:] - Er[1:])) / scale)
            res.energy_drift = float((E[-1] - E[0]) / scale)


# ----------------------------------------------------------------------------- the study
@dataclass
class StudyResult:
    """Everything a study measured (JSON round trip with :meth:`to_json` / :func:`load_study`)."""

    scene: str
    scene_name: str
    grid: str
    device: str
    device_description: str
    precision_note: str
    frames: int
    fps: float
    simulated_seconds: float
    quantity: str
    object_size: float
    tip: dict
    reference: ConfigResult
    results: list
    frontier: list
    comparison: str
    load_note: str = ""
    energy_scale: float = math.nan
    schema: str = SCHEMA_VERSION
    truth: dict = field(default_factory=dict)  # what the reference is and its own convergence
    executor: str = "serial (this process)"

    def to_dict(self) -> dict:
        d = {k: _json_value(getattr(self, k)) for k in ("schema", "scene", "scene_name", "grid", "device",
                                                       "device_description", "precision_note", "frames", "fps",
                                                       "simulated_seconds", "quantity", "object_size", "tip",
                                                       "frontier", "comparison", "load_note", "energy_scale",
                                                       "truth", "executor")}
        d["reference"] = self.reference.as_dict()
        d["results"] = [r.as_dict() for r in self.results]
        return d

    def to_json(self, path) -> str:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        with open(path, "w") as f:
            json.dump(self.to_dict(), f, indent=1, allow_nan=False)
        return path

    @classmethod
    def from_dict(cls, d: dict) -> "StudyResult":
        if d.get("schema") != SCHEMA_VERSION:
            raise ValueError(f"not a {SCHEMA_VERSION} document (schema = {d.get('schema')!r})")
        kw = dict(d)
        kw["reference"] = ConfigResult.from_dict(d["reference"])
        kw["results"] = [ConfigResult.from_dict(r) for r in d["results"]]
        for r in [kw["reference"]] + kw["results"]:  # documents written before the field existed
            if r.status == "ok" and not math.isfinite(r.cg_per_sim_second) and r.frames:
                r.cg_per_sim_second = r.cg_iterations / (r.frames / float(d["fps"]))
        kw["object_size"] = float(kw["object_size"])
        names = {f.name for f in fields(cls)}
        missing = sorted(names - set(kw) - {"load_note", "schema", "energy_scale", "truth", "executor"})
        if kw.get("energy_scale") is None:
            kw["energy_scale"] = math.nan
        if missing:
            raise ValueError(f"tradeoff JSON is missing {missing}")
        return cls(**{k: v for k, v in kw.items() if k in names})

    def ok_results(self):
        return [r for r in self.results if r.status == "ok"]


def set_quantity(study: StudyResult, quantity: str) -> StudyResult:
    """Recompute the frontier of a (loaded) study for another error measure, in place."""
    if quantity not in QUANTITIES:
        raise GridError(f"unknown quantity {quantity!r}; choose one of {', '.join(QUANTITIES)}")
    ok = study.ok_results()
    idx = pareto_front([r.seconds_per_sim_second for r in ok], [getattr(r, QUANTITIES[quantity]) for r in ok])
    for r in study.results:
        r.on_frontier = False
    for i in idx:
        ok[i].on_frontier = True
    study.quantity, study.frontier = quantity, [ok[i].name for i in idx]
    return study


TIMING_FIELDS = ("build_seconds", "train_seconds", "step_seconds", "seconds_per_sim_second", "ran_on", "on_frontier")


def without_timings(d):
    """A study's JSON document without what depends on wall time or on where runs executed
    (timings, the frontier on time, the load note, the executor): what a serial run and a
    cluster run of the same study must agree on exactly."""
    if isinstance(d, StudyResult):
        d = d.to_dict()
    if isinstance(d, dict):
        return {k: without_timings(v) for k, v in d.items()
                if k not in TIMING_FIELDS + ("frontier", "load_note", "executor")}
    if isinstance(d, list):
        return [without_timings(v) for v in d]
    return d


def load_study(path) -> StudyResult:
    with open(path) as f:
        return StudyResult.from_dict(json.load(f))


def _device_description(device) -> str:
    import warp as wp

    d = wp.get_device(device)
    if d.is_cuda:
        return f"{d.alias}: {d.name}"
    cpu = platform.processor() or platform.machine()
    return f"cpu ({cpu}, {os.cpu_count()} logical cores; Warp's CPU backend runs kernels on one thread)"


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
def _fmt(v, spec=".2e"):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


def _one_line(r: ConfigResult) -> str:
    if r.status != "ok":
        return f"{r.name}: {r.status}: {r.note}"
    return (f"{r.name}: {r.seconds_per_sim_second:.3g} s/sim-s, newton {r.newton_per_step:.2f}/step, "
            f"cg {r.cg_per_step:.1f}/step, rms {_fmt(r.rms_error)}, tip {_fmt(r.tip_error)}, "
            f"energy {_fmt(r.energy_error)}" + (f"  ({r.note})" if r.note else ""))


def format_table(study: StudyResult) -> str:
    """The terminal table: one row per configuration, frontier rows marked '*', skipped ones last."""
    key = QUANTITIES[study.quantity]
    split = _split_key(study)
    head = ["", "configuration", "s/sim-s", "newton/step", "cg/step", "cg/sim-s", "rms err", "surf err", "tip err", "energy err",
            "drift", "unconv"] + ([f"{split} disc", f"{split} solver"] if split else [])
    rows = []
    ok = sorted(study.ok_results(), key=lambda r: r.seconds_per_sim_second)
    for r in [study.reference] + ok:
        rows.append(["*" if r.on_frontier else ("R" if r is study.reference else ""), r.name,
                     _fmt(r.seconds_per_sim_second, ".3g"), _fmt(r.newton_per_step, ".2f"), _fmt(r.cg_per_step, ".1f"),
                     _fmt(r.cg_per_sim_second, ".4g"), _fmt(r.rms_error), _fmt(r.surface_error), _fmt(r.tip_error), _fmt(r.energy_error),
                     _fmt(r.energy_drift, "+.2e"), str(r.unconverged_frames)]
                    + ([_fmt(getattr(r, f"discretisation_{split}_error")), _fmt(getattr(r, f"solver_{split}_error"))]
                       if split else []))
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    lines = [f"{study.scene_name}: {study.frames} frames ({study.simulated_seconds:g} s simulated) on {study.device_description}",
             f"frontier (*) on {study.quantity} error ({key}) vs wall time; R = reference ({study.precision_note})",
             "  ".join(h.ljust(w) for h, w in zip(head, widths))]
    lines += ["  ".join(str(x).ljust(w) for x, w in zip(row, widths)) for row in rows]
    for r in study.results:
        if r.status != "ok":
            lines.append(f"  {r.status}: {r.name}: {r.note}")
    lines += reference_lines(study)
    tip = study.tip
    lines.append(f"tip: {tip['how']} at {np.round(tip['point'], 4).tolist()} m, peak displacement "
                 f"{tip['peak_displacement_m']:.4g} m; object size (bbox diagonal) {study.object_size:.4g} m")
    return "\n".join(lines)


def _split_key(study: StudyResult) -> str | None:
    """The error whose split is shown: the frontier's quantity when it is tip or rms, else tip."""
    if not any(math.isfinite(r.discretisation_tip_error) for r in study.ok_results()):
        return None
    return study.quantity if study.quantity in ("tip", "rms") else "tip"


def reference_lines(study: StudyResult) -> list:
    """What the reference is and how converged it is (lines of text)."""
    t = study.truth or {}
    if not t:
        return []
    out = [f"reference: {t.get('kind', '')}" + (f" -- {t['flag']}" if t.get("flag") else "")]
    tm = t.get("time")
    if tm:
        d = ", ".join(_fmt(x) for x in tm.get("difference_tip", []))
        out.append(f"  time: substeps {tm.get('substeps')}, successive tip differences {d}"
                   + (f", observed order {tm['observed_order_tip']:.2f}" if tm.get("observed_order_tip") is not None else "")
                   + f"; estimated reference error: tip {_fmt(tm.get('estimated_error_tip'))}, rms {_fmt(tm.get('estimated_error_rms'))}"
                   + (f" ({tm['method']})" if tm.get("method") else ""))
    sp = t.get("space")
    if sp:
        out.append(f"  space: {t['space_run']['config']['name']}: tip difference {_fmt(sp['difference_tip'])}, "
                   f"rms {_fmt(sp['difference_rms'])} ({sp['note']})")
    for name, m in (t.get("meshes") or {}).items():
        out.append(f"  discretisation error of {name} (time-converged run on that mesh vs the reference): tip "
                   f"{_fmt(m.get('discretisation_tip_error'))}, rms {_fmt(m.get('discretisation_rms_error'))}")
    return out


def format_markdown(study: StudyResult, *, frontier_only=False) -> str:
    """A markdown table (for docs)."""
    rows = sorted(study.ok_results(), key=lambda r: r.seconds_per_sim_second)
    if frontier_only:
        rows = [r for r in rows if r.on_frontier]
    split = _split_key(study)
    extra = f" {split} discretisation | {split} solver/step |" if split else ""
    out = ["| configuration | s / simulated s | Newton / step | CG / step | CG / simulated s | RMS err / size | tip err / peak | energy err | frontier |" + extra,
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- |" + (" --- | --- |" if split else "")]
    for r in [study.reference] + rows:
        name = "reference" if r is study.reference else r.name
        out.append(f"| {name} | {_fmt(r.seconds_per_sim_second, '.3g')} | {_fmt(r.newton_per_step, '.2f')} | "
                   f"{_fmt(r.cg_per_step, '.1f')} | {_fmt(r.cg_per_sim_second, '.4g')} | {_fmt(r.rms_error)} | {_fmt(r.tip_error)} | {_fmt(r.energy_error)} | "
                   f"{'yes' if r.on_frontier else ''} |"
                   + (f" {_fmt(getattr(r, f'discretisation_{split}_error'))} | {_fmt(getattr(r, f'solver_{split}_error'))} |"
                      if split else ""))
    return "\n".join(out)


def plot_pareto(study: StudyResult, path) -> str:
    """Error vs wall time (log-log) with the frontier drawn; needs matplotlib (``pip install warpfem[plot]``)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:
        raise ImportError("the Pareto plot needs matplotlib: pip install 'warpfem[plot]' (or pip install matplotlib)") from e
    key = QUANTITIES[study.quantity]
    ok = study.ok_results()
    t = np.array([r.seconds_per_sim_second for r in ok])
    e = np.array([getattr(r, key) for r in ok], dtype=np.float64)
    finite = np.isfinite(e) & np.isfinite(t)
    floor = np.nanmin(e[finite & (e > 0)]) / 10 if np.any(finite & (e > 0)) else 1e-12
    e_plot = np.where(e > 0, e, floor)
    fig, ax = plt.subplots(figsize=(8, 5.5))
    on = np.array([r.on_frontier for r in ok])
    ax.scatter(t[finite & ~on], e_plot[finite & ~on], c="0.6", label="configuration")
    ax.scatter(t[finite & on], e_plot[finite & on], c="C3", label="Pareto frontier", zorder=3)
    order = np.argsort(t[on])
    ax.plot(t[on][order], e_plot[on][order], c="C3", drawstyle="steps-post", lw=1)
    for r, ti, ei in zip(ok, t, e_plot):  # names on the frontier only (the table / JSON has them all)
        if r.on_frontier and np.isfinite(ti) and np.isfinite(ei):
            ax.annotate(r.name, (ti, ei), fontsize=7, xytext=(4, 4), textcoords="offset points")
    ax.axvline(study.reference.seconds_per_sim_second, c="C0", ls="--", lw=1, label="reference time")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall seconds per simulated second")
    ax.set_ylabel({"tip_error": "tip error / peak tip displacement", "rms_error": "RMS vertex error / object size",
                   "surface_error": "RMS surface error / object size", "energy_error": "energy error / energy swing"}[key])
    ax.set_title(f"{study.scene_name}: {study.frames} frames, {study.device_description}", fontsize=8)
    ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
