"""Configurations of a trade-off study and the grids that list them: :class:`TradeoffConfig` (overrides
of a scene's settings), :class:`TruthSpec` (the converged reference), :class:`TradeoffGrid`, the
built-in grids (:func:`builtin_grid`) and grid files (:func:`load_grid`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields

from warpfem.scenes.schema import read_toml

__all__ = ["QUANTITIES", "GridError", "TradeoffConfig", "TruthSpec", "TradeoffGrid", "builtin_grid", "load_grid"]


# error measure used for the frontier / plot -> result field
QUANTITIES = {"tip": "tip_error", "rms": "rms_error", "surface": "surface_error", "energy": "energy_error"}


def _suggest(key, known) -> str:
    """`` (did you mean 'x'?)`` for the known key closest to a misspelt one (as scene files do)."""
    import difflib

    close = difflib.get_close_matches(str(key), sorted(known), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


class GridError(ValueError):
    """An invalid grid (file or options): the message names the file and the key."""


@dataclass(frozen=True)
class TradeoffConfig:
    """Overrides of the scene's settings (None: keep the scene's value).

    precision: "float32" | "float64" (always set; default float64).
    tol, max_iters, cg_tol: ``[integrator]`` Newton keys (ignored by integrators without them).
    substeps: time steps per output frame (dt = 1 / (fps * substeps)).
    integrator: ``[integrator].type``; element: ``[mesh].element``.
    target_tets: ``[mesh].target_tets`` (a scene whose mesh is a surface file: the physics mesh size).
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
    target_tets: int | None = None  # [mesh].target_tets of a scene whose mesh is a surface file

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
            raise GridError(f"{where}: unknown key {bad[0]!r}{_suggest(bad[0], known)}; known keys: {', '.join(sorted(known))}")
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
        v = self.target_tets
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 10):
            raise GridError(f"{where}.target_tets: must be an integer >= 10, got {v!r}")
        if self.linear_solver is not None and self.linear_solver not in ("auto", "pcg", "direct", "amg", "multigrid"):
            raise GridError(f"{where}.linear_solver: must be one of auto, pcg, direct, amg, multigrid, got {self.linear_solver!r}")
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
        # the integrator as its scene key names it (backward_euler, not the Newton solver it uses);
        # stiffness warping shortened
        parts.append({"stiffness_warping": "warping"}.get(d["integrator"], d["integrator"]))
    if d.get("element"):
        parts.append(d["element"])
    if d.get("refine") not in (None, 1):
        parts.append(f"cells x{d['refine']}")
    if d.get("target_tets") is not None:
        parts.append(f"tets={d['target_tets']}")
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
            raise GridError(f"{where}: unknown key {bad[0]!r}{_suggest(bad[0], ('element', 'refine', 'substeps'))}; "
                            "known keys: element, refine, substeps")
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
        raise GridError(f"{path}: {bad[0]}: unknown key{_suggest(bad[0], _GRID_KEYS)}; known: {', '.join(sorted(_GRID_KEYS))}")
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
