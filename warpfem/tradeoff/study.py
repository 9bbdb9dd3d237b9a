"""Speed/accuracy trade-off study: one scene over a grid of solver configurations.

Every configuration is a set of overrides of the scene file (precision, Newton ``tol`` and
``max_iters``, ``cg_tol``, substeps per frame, integrator, ``[mesh] element``, ``[subspace]``).
Variants are built by editing the parsed TOML document and validating it again with
:func:`warpfem.scenes.parse_scene_dict`, so whatever the scene layer supports is available here and
whatever it rejects is skipped with the scene layer's own message. Runs are stepped with
:meth:`warpfem.scenes.SceneRun.step_frame` and compared with a converged reference run of the same
scene (float64, tight tolerances, small time step).

Common ground for comparisons: the **reference's simulation vertices** (rest positions). A variant
on the same mesh is sampled at those vertices directly; a variant with another vertex set (another
element type) is sampled by embedding the reference's rest vertices in the variant's elements
(:func:`warpfem.elements.meshes.embed_points_in_elements`, the variant's own shape functions).

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

__all__ = ["TradeoffConfig", "TradeoffGrid", "GridError", "StudyResult", "ConfigResult", "builtin_grid",
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
    linear_solver: str | None = None  # [integrator].linear_solver: "auto" | "pcg" | "direct" | "amg"

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
        for k in ("max_iters", "substeps", "max_cg_iters"):
            v = getattr(self, k)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise GridError(f"{where}.{k}: must be an integer >= 1, got {v!r}")
        if self.linear_solver is not None and self.linear_solver not in ("auto", "pcg", "direct", "amg"):
            raise GridError(f"{where}.linear_solver: must be one of auto, pcg, direct, amg, got {self.linear_solver!r}")
        for k in ("integrator", "element", "name"):
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


@dataclass
class TradeoffGrid:
    """Configurations to run, the reference settings, frames and the tip point."""

    configs: list
    reference: TradeoffConfig
    frames: int | None = None
    tip_point: tuple | None = None
    name: str = "custom"


_REFERENCE = dict(name="reference", precision="float64", tol=1e-9, max_iters=100, cg_tol=1e-9, max_cg_iters=20000)


def _element_names():
    from warpfem.scenes import ELEMENTS

    return list(ELEMENTS)


def builtin_grid(name: str) -> TradeoffGrid:
    """``quick``: one knob at a time around the scene's own settings (float64), plus a "fast"
    combination; ``full``: the product precision x tol x cg_tol x substeps plus the one-at-a-time
    integrator / element / reduced / iteration-cap variants. Element and reduced variants are listed
    for every name the scene schema knows; unavailable ones are skipped at run time with a note."""
    if name == "quick":
        cs = [_cfg(name="scene"), _cfg(precision="float32"),
              _cfg(tol=1e-3), _cfg(tol=1e-7), _cfg(max_iters=2),
              _cfg(cg_tol=1e-2), _cfg(cg_tol=1e-6), _cfg(substeps=2),
              _cfg(name="fast: f32 tol=1e-3 cg=1e-2", precision="float32", tol=1e-3, cg_tol=1e-2),
              _cfg(integrator="stiffness_warping")]
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
    return TradeoffGrid(configs=cs, reference=_cfg(**_REFERENCE, substeps=ref_sub), name=name)


_GRID_KEYS = {"base", "exclude", "frames", "tip_point", "reference", "axes", "config"}


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
    grid = builtin_grid(data["base"]) if "base" in data else TradeoffGrid(configs=[], reference=_cfg(**_REFERENCE, substeps=4))
    grid.name = os.path.basename(path)
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
    from warpfem.scenes import INTEGRATORS, SCHEMA, Scene, SceneError, parse_scene_dict

    d = copy.deepcopy(doc)
    out = d.setdefault("output", {})
    for k in ("usd", "states", "stats"):
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
    integ["require_convergence"] = False  # non-convergence is counted, not fatal
    for k in ("tol", "max_iters", "cg_tol", "max_cg_iters", "linear_solver"):
        v = getattr(cfg, k)
        if v is not None and k in entry.keys:
            integ[k] = v
    if cfg.substeps is not None:
        if not entry.dynamic:
            raise Unavailable(f"integrator {itype!r} is quasi-static: no time step to vary")
        fps = float(out.get("fps", SCHEMA["output"]["fps"].default))
        integ["dt"] = 1.0 / (fps * cfg.substeps)
    if cfg.element is not None:
        d.setdefault("mesh", {})["element"] = cfg.element
    if cfg.subspace is not None:
        sub = dict(cfg.subspace_dict())
        if "cache" not in sub and cache_dir is not None:
            key = "_".join(f"{k}{v}" for k, v in sorted(sub.items()))
            sub["cache"] = os.path.join(cache_dir, f"subspace_{key}.npz")
        d["subspace"] = sub
    try:
        spec = parse_scene_dict(d, path=os.path.abspath(scene_path))
    except SceneError as e:
        raise Unavailable(str(e)) from e
    return Scene(spec)


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
                                substeps=None)
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
    from warpfem.elements.meshes import embed_points_in_elements

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
    if res.unconverged_frames:
        res.note = f"{res.unconverged_frames} frame(s) with a non-converged step"
    traj.fps = run.fps
    traj.fixed = run.model.fixed.any(axis=1).copy()
    traj.boundary = np.unique(np.asarray(scene.mesh().boundary_faces()).ravel()) if run.skinner is None else None
    return res, traj


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

    def to_dict(self) -> dict:
        d = {k: _json_value(getattr(self, k)) for k in ("schema", "scene", "scene_name", "grid", "device",
                                                       "device_description", "precision_note", "frames", "fps",
                                                       "simulated_seconds", "quantity", "object_size", "tip",
                                                       "frontier", "comparison", "load_note", "energy_scale")}
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
        missing = sorted(names - set(kw) - {"load_note", "schema", "energy_scale"})
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


def run_study(scene_path, grid: TradeoffGrid, *, device="cpu", frames=None, quantity="tip", tip_point=None,
              progress=None, log=None) -> StudyResult:
    """Run ``grid`` on the scene file and compare every configuration with the reference.

    ``frames``: output frames per run (default: the grid's, else the scene's ``[output].frames``).
    ``quantity``: the error measure of the frontier ("tip", "rms", "surface", "energy").
    ``tip_point``: rest-space point (m) whose displacement is the named quantity (default: the free
    reference vertex of largest displacement). ``progress(cfg, FrameStats)`` after each frame,
    ``log(str)`` after each configuration. Raises SceneError for an invalid scene,
    :class:`warpfem.SolveFailed` when the reference itself fails.
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
    configs, dropped = _dedupe(grid.configs, base.spec)

    with tempfile.TemporaryDirectory(prefix="warpfem_tradeoff_") as cache_dir:
        ref_res, ref_traj = _run_one(doc, scene_path, grid.reference, device=device, frames=frames, ref_info=None,
                                     cache_dir=cache_dir, tip_point=tip_point, progress=progress)
        if ref_res.status != "ok":
            from warpfem.solvers.nonlinear import SolveFailed

            raise SolveFailed(f"the reference run ({grid.reference.as_dict()}) did not complete: {ref_res.note}")
        ref_scene = variant_scene(doc, scene_path, grid.reference)
        rest = np.asarray(ref_scene.mesh().vertices, dtype=np.float64)
        pts = np.asarray(ref_traj.points)
        size = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
        if tip_point is not None:
            tip = np.asarray(ref_traj.tip)
            tip_info = {"vertex": None, "point": list(map(float, tip_point)), "how": "given point (rest position)"}
        else:
            disp = np.linalg.norm(pts - pts[0][None], axis=2).max(axis=0)
            disp[ref_traj.fixed] = -1.0
            v = int(np.argmax(disp))
            tip = pts[:, v]
            tip_info = {"vertex": v, "point": rest[v].tolist(),
                        "how": "free reference vertex of largest displacement over the trajectory"}
        tip_peak = float(np.linalg.norm(tip - tip[0], axis=1).max())
        tip_info["peak_displacement_m"] = tip_peak
        ref = {"rest": rest, "points": pts, "size": size, "tip": tip, "tip_peak": tip_peak,
               "tip_vertex": tip_info["vertex"], "tip_point": tip_point,
               "surface": np.asarray(ref_traj.surface) if ref_traj.surface else None,
               "boundary": ref_traj.boundary,
               "energy": np.asarray(ref_traj.energy) if ref_traj.energy else None,
               "energy_scale": float(np.max(ref_traj.motion_energy)) if ref_traj.motion_energy else 0.0}
        _errors(ref_res, ref_traj, ref)
        log(_one_line(ref_res))
        results = []
        for cfg in configs:
            res, traj = _run_one(doc, scene_path, cfg, device=device, frames=frames, ref_info=ref, cache_dir=cache_dir,
                                 tip_point=tip_point, progress=progress)
            if traj is not None:
                _errors(res, traj, ref)
            results.append(res)
            log(_one_line(res))
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
    comparison = ("errors at the reference's simulation vertices (rest positions); variants with another vertex set "
                  "(element type) are sampled there through their own shape functions (embedding); 'surface' is the "
                  + ("[surface] render points skinned on each run's mesh" if ref["surface"] is not None
                     else "reference mesh's boundary vertices"))
    return StudyResult(scene=os.path.abspath(scene_path), scene_name=base.name, grid=grid.name, device=str(device),
                       device_description=_device_description(device),
                       precision_note="reference: " + ", ".join(f"{k}={v}" for k, v in grid.reference.as_dict().items()
                                                               if v is not None and k != "name"),
                       frames=frames, fps=fps, simulated_seconds=frames / fps, quantity=quantity, object_size=size,
                       tip=tip_info, reference=ref_res, results=results, frontier=[ok[i].name for i in idx],
                       comparison=comparison, load_note=_load_note(), energy_scale=ref["energy_scale"])


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
    head = ["", "configuration", "s/sim-s", "newton/step", "cg/step", "cg/sim-s", "rms err", "surf err", "tip err", "energy err",
            "drift", "unconv"]
    rows = []
    ok = sorted(study.ok_results(), key=lambda r: r.seconds_per_sim_second)
    for r in [study.reference] + ok:
        rows.append(["*" if r.on_frontier else ("R" if r is study.reference else ""), r.name,
                     _fmt(r.seconds_per_sim_second, ".3g"), _fmt(r.newton_per_step, ".2f"), _fmt(r.cg_per_step, ".1f"),
                     _fmt(r.cg_per_sim_second, ".4g"), _fmt(r.rms_error), _fmt(r.surface_error), _fmt(r.tip_error), _fmt(r.energy_error),
                     _fmt(r.energy_drift, "+.2e"), str(r.unconverged_frames)])
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    lines = [f"{study.scene_name}: {study.frames} frames ({study.simulated_seconds:g} s simulated) on {study.device_description}",
             f"frontier (*) on {study.quantity} error ({key}) vs wall time; R = reference ({study.precision_note})",
             "  ".join(h.ljust(w) for h, w in zip(head, widths))]
    lines += ["  ".join(str(x).ljust(w) for x, w in zip(row, widths)) for row in rows]
    for r in study.results:
        if r.status != "ok":
            lines.append(f"  {r.status}: {r.name}: {r.note}")
    tip = study.tip
    lines.append(f"tip: {tip['how']} at {np.round(tip['point'], 4).tolist()} m, peak displacement "
                 f"{tip['peak_displacement_m']:.4g} m; object size (bbox diagonal) {study.object_size:.4g} m")
    return "\n".join(lines)


def format_markdown(study: StudyResult, *, frontier_only=False) -> str:
    """A markdown table (for docs)."""
    rows = sorted(study.ok_results(), key=lambda r: r.seconds_per_sim_second)
    if frontier_only:
        rows = [r for r in rows if r.on_frontier]
    out = ["| configuration | s / simulated s | Newton / step | CG / step | CG / simulated s | RMS err / size | tip err / peak | energy err | frontier |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in [study.reference] + rows:
        name = "reference" if r is study.reference else r.name
        out.append(f"| {name} | {_fmt(r.seconds_per_sim_second, '.3g')} | {_fmt(r.newton_per_step, '.2f')} | "
                   f"{_fmt(r.cg_per_step, '.1f')} | {_fmt(r.cg_per_sim_second, '.4g')} | {_fmt(r.rms_error)} | {_fmt(r.tip_error)} | {_fmt(r.energy_error)} | "
                   f"{'yes' if r.on_frontier else ''} |")
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
