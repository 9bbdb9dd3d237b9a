"""Error and cost measures of a trade-off study: trajectories sampled at the common points, their
errors against a reference (see :mod:`warpfem.tradeoff.study` for the definitions), Richardson
extrapolation of a time-step pair, the deterministic cost proxy :func:`work_proxy` and the Pareto
front (:func:`pareto_front`, :func:`set_quantity`).
"""

from __future__ import annotations

import math

import numpy as np

from .grid import GridError, QUANTITIES
from .results import ConfigResult, StudyResult

__all__ = ["pareto_front", "work_proxy", "set_quantity"]


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


class _Trajectory:
    def __init__(self):
        self.points, self.surface, self.tip, self.energy, self.motion_energy = [], [], [], [], []


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


def _slice(traj, n):
    t = _Trajectory()
    for k in ("points", "surface", "tip", "energy", "motion_energy"):
        setattr(t, k, list(getattr(traj, k))[:n + 1])
    t.fps, t.fixed, t.boundary = getattr(traj, "fps", None), getattr(traj, "fixed", None), getattr(traj, "boundary", None)
    return t
