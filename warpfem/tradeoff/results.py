"""What a trade-off study records: one configuration's outcome (:class:`ConfigResult`) and a whole study
(:class:`StudyResult`), with their JSON round trip (:func:`load_study`) and :func:`without_timings`
(the part of a study that does not depend on wall time or on where runs executed).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, fields

import numpy as np

__all__ = ["SCHEMA_VERSION", "ConfigResult", "StudyResult", "TIMING_FIELDS", "without_timings", "load_study"]


SCHEMA_VERSION = "warpfem.tradeoff/1"


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


@dataclass
class StudyResult:
    """Everything a study measured (JSON round trip with :meth:`to_json` / :func:`load_study`)."""

    scene: str  # the scene file, relative to the repository root (warpfem.paths.portable_path)
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
