"""What a run is measured with: sampling a run at the common material points, the error measures
against the reference, the work proxy and the Pareto front.

Part of :mod:`warpfem.tradeoff.study` (which re-exports every name here)."""

from __future__ import annotations

import math

import numpy as np

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only
    from .results import ConfigResult


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


_QUADRATURE_POINTS = {"tet4": 1, "tet10": 4, "hex8": 8, "hex27": 27}


def work_proxy(res: ConfigResult, run) -> float:
    """A deterministic, load-independent cost of a run (arbitrary units, comparable across
    configurations): every Newton iteration assembles forces and Hessian over the quadrature points,
    ~E q n^2 (E elements, q quadrature points, n nodes per element), every CG iteration is one
    element-by-element matrix-vector product, ~E n^2. A reduced run assembles over its cubature
    elements and solves an r x r system per Newton iteration (c q n^2 + r^3) and reconstructs the
    full positions once per step (N r, N vertices)."""
    mesh = run.scene.mesh()
    etype = getattr(mesh, "element_type", "tet4")
    n = int(np.asarray(mesh.elements).shape[1])
    q = _QUADRATURE_POINTS.get(etype, 1)
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
