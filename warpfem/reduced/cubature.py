"""Optimized cubature for subspace forces (An, Kim & James 2008, "Optimizing cubature for efficient
integration of subspace deformations").

The reduced internal force f_r(q) = U^T f(X + U q) = sum_e g_e(q) (sum over all elements, g_e the
element's reduced force, N*sqrt(kg)... i.e. U^T applied to the element's node forces) is
approximated by sum_{c in S} w_c g_c(q) over a few cubature elements S with non-negative weights
w_c (dimensionless multipliers of the element's own contribution: every element with w = 1 is
the exact sum).

Training: poses q_t (random, per-column amplitude ~ 1/frequency, seeded; optionally projected
simulation snapshots), targets b_t = U^T f(X + U q_t), each pose normalised by 1/||b_t||. Greedy
selection: sample candidate elements, pick the one whose (normalised) force column has the
largest cosine with the current residual, re-solve NNLS for all weights (scipy.optimize.nnls),
drop zero weights, repeat until ||A w - b|| / ||b|| <= tolerance or the point cap.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.optimize


@dataclass
class Cubature:
    """Cubature elements and weights plus how they were trained.

    Attributes:
        elements: (c,) int64 element indices.
        weights: (c,) float64 non-negative, dimensionless (multiply the element's own force).
        training_error / validation_error: relative force error ||A w - b|| / ||b|| on the
            training / validation poses (each pose normalised).
        training_seconds: wall-clock training time (s), including the full-force evaluations.
        training_poses: (T, r) the training poses (saved so the error can be re-evaluated).
        tolerance, max_points, seed: the settings used.
        reached_tolerance: False when the point cap (or the candidate pool) stopped training first.
    """

    elements: np.ndarray
    weights: np.ndarray
    training_error: float
    validation_error: float
    training_seconds: float
    training_poses: np.ndarray
    tolerance: float
    max_points: int
    seed: int
    reached_tolerance: bool
    num_validation_poses: int = 0

    @property
    def num_points(self) -> int:
        return int(len(self.elements))

    @classmethod
    def full(cls, num_elements: int):
        """Every element at weight 1 (the exact reduced force)."""
        return cls(np.arange(num_elements), np.ones(num_elements), 0.0, 0.0, 0.0, np.zeros((0, 0)), 0.0,
                   num_elements, 0, True)


def training_poses(U, model, num_poses: int, *, seed: int, amplitude: float = 0.1, K=None) -> np.ndarray:
    """Random poses q (num_poses, r): column j ~ N(0, a_j^2) with
    a_j = amplitude * size / max|U_j| * omega_min / omega_j  (size = bounding-box diagonal, m).

    So the softest column moves some vertex by about ``amplitude`` of the object size and stiffer
    columns proportionally less (1/frequency). Columns with zero stiffness (rigid translations) get
    amplitude 0: they produce no elastic force.
    """
    from warpfem.reduced.basis import _full_simulator

    X = model.rest_positions
    size = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    if K is None:
        K = _full_simulator(model).stiffness_matrix(X, project=False)
    omega = np.sqrt(np.clip(np.einsum("ij,ij->j", U, K @ U), 0.0, None))
    positive = omega > 1e-8 * max(omega.max(), 1e-300)
    if not positive.any():
        raise ValueError("the basis has no elastic column (all columns have zero stiffness)")
    wmin = omega[positive].min()
    amp = np.zeros(U.shape[1])
    amp[positive] = amplitude * size / np.abs(U[:, positive]).max(axis=0) * wmin / omega[positive]
    rng = np.random.default_rng(seed)
    return rng.standard_normal((int(num_poses), U.shape[1])) * amp


class _ForceTable:
    """Per-element reduced forces g_e(q_t) for the training poses, evaluated on demand per column."""

    def __init__(self, sim, model, U, poses, B=None):
        """poses (T, r + p) are coordinates in the pose basis B = [U | L] (default U): positions
        x = X + B z; the forces are projected on U only."""
        B = U if B is None else B
        qd = model.quadrature
        n = model.num_vertices
        r = U.shape[1]
        self.tets = qd.elements.reshape(-1, 4).astype(np.int64)
        self.g = qd.qp_dNdX.reshape(-1, 4, 3)
        self.vol = qd.qp_weight
        self.Ue = U.reshape(n, 3, r)[self.tets]  # (m, 4, 3, r)
        X = model.rest_positions
        self.P = np.empty((len(poses), len(self.tets), 3, 3))
        b = np.empty((len(poses), r))
        for t, q in enumerate(poses):
            x = X + (B @ q).reshape(n, 3)
            self.P[t] = sim.stresses(x)
            b[t] = U.T @ sim.elastic_forces(x).reshape(-1)
        self.bnorm = np.linalg.norm(b, axis=1)
        self.bnorm[self.bnorm == 0.0] = 1.0
        self.b = (b / self.bnorm[:, None]).reshape(-1)
        self.r = r

    def columns(self, elems) -> np.ndarray:
        """(T r, len(elems)) normalised force columns of the given elements."""
        elems = np.asarray(elems, dtype=np.int64)
        f = -self.vol[elems][None, :, None, None] * np.einsum("tcij,caj->tcai", self.P[:, elems], self.g[elems])
        cols = np.einsum("tcak,cakj->tjc", f, self.Ue[elems]) / self.bnorm[:, None, None]
        return cols.reshape(-1, len(elems))

    def error(self, elems, w) -> float:
        if len(elems) == 0:
            return 1.0
        return float(np.linalg.norm(self.columns(elems) @ w - self.b) / np.linalg.norm(self.b))


def snapshot_poses(U, model, snapshots, *, lifting=None, sim=None) -> np.ndarray:
    """Project full-mesh positions x (each (n, 3), m) onto the basis: rows z = [q; a] with
    a fitted on the handles (``lifting``, see :mod:`warpfem.reduced.lifting`) and
    q = M_r^-1 U^T M (x - X - L a) (the M-orthogonal projection; M_r = I for our bases)."""
    from warpfem.reduced.basis import _full_simulator

    sim = sim or _full_simulator(model)
    M = sim.mass_matrix()
    Mr = U.T @ (M @ U)
    X = model.rest_positions.reshape(-1)
    out = []
    for x in snapshots:
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        if x.shape != model.rest_positions.shape or not np.all(np.isfinite(x)):
            raise ValueError(f"snapshot positions must be finite with shape {model.rest_positions.shape}, got {x.shape}")
        d = x.reshape(-1) - X
        a = np.zeros(0)
        if lifting is not None and lifting.size:
            a = lifting.coords_from_positions(x)
            d = d - lifting.L @ a
        out.append(np.concatenate([np.linalg.solve(Mr, U.T @ (M @ d)), a]))
    return np.array(out)


POSE_SOURCES = ("random", "snapshots", "random+snapshots")


def train_cubature(model, U, *, tolerance: float = 0.05, max_points: int = 200, seed: int = 0,
                   num_training_poses: int = 100, num_validation_poses: int = 30, candidates: int = 256,
                   amplitude: float = 0.1, snapshots=None, pose_source: str | None = None, lifting=None,
                   handle_coords=None, sim=None) -> Cubature:
    """Greedy NNLS cubature for the basis U (3n x r) of ``model`` (Tet4, one point per element).

    Args:
        tolerance: target relative force error on the training poses (0 < tol < 1).
        max_points: cap on cubature points.
        seed: seeds the poses and the candidate sampling (same seed, same result).
        num_training_poses, num_validation_poses: random poses (see :func:`training_poses`);
            validation poses come from an independent stream of the same seed.
        candidates: elements sampled per greedy iteration.
        amplitude: pose size as a fraction of the object's bounding-box diagonal.
        snapshots: optional list of full-mesh positions (n, 3) from a simulation, projected onto
            the basis (:func:`snapshot_poses`).
        pose_source: "random" (default without snapshots), "snapshots" (only the projected
            snapshots: every 4th one is held out as the validation set, the rest train) or
            "random+snapshots" (default with snapshots: random poses and 3 of every 4 snapshots
            train; the random validation poses and every 4th snapshot validate).
        lifting: a :class:`~warpfem.reduced.lifting.Lifting` (kinematic handles): poses are then
            z = [q; a] in the basis [U | L] and the forces are projected on U.
        handle_coords: (S, p) handle coordinates a that random poses draw from (e.g. the scene's
            handle motion at random ramp fractions); default a = 0.
    """
    from warpfem.reduced.basis import _full_simulator

    if not (np.isfinite(tolerance) and 0.0 < tolerance < 1.0):
        raise ValueError(f"cubature tolerance must be in (0, 1), got {tolerance!r}")
    if int(max_points) != max_points or max_points < 1:
        raise ValueError(f"max_cubature_points must be a positive integer, got {max_points!r}")
    from warpfem.mesh.element_types import get_element

    if not get_element(model.quadrature.element_type).is_linear_tet:
        raise ValueError(f"cubature training supports tet4 meshes only, got {model.quadrature.element_type!r}")
    if pose_source is None:
        pose_source = "random" if snapshots is None else "random+snapshots"
    if pose_source not in POSE_SOURCES:
        raise ValueError(f"pose_source must be one of {POSE_SOURCES}, got {pose_source!r}")
    if pose_source != "random" and (snapshots is None or len(snapshots) < (4 if pose_source == "snapshots" else 1)):
        raise ValueError(f"pose_source={pose_source!r} needs snapshots (at least 4 for 'snapshots': every 4th validates)")
    t0 = time.perf_counter()
    sim = sim or _full_simulator(model)
    K = sim.stiffness_matrix(model.rest_positions, project=False)
    ss = np.random.SeedSequence(int(seed))
    s_train, s_val, s_pick = (int(c.generate_state(1)[0]) for c in ss.spawn(3))
    p = 0 if lifting is None else lifting.size
    B = U if p == 0 else np.hstack([U, lifting.L])

    def random_poses(count, s):
        z = training_poses(U, model, count, seed=s, amplitude=amplitude, K=K)
        if p:
            a = np.zeros((count, p))
            if handle_coords is not None and len(handle_coords):
                hc = np.asarray(handle_coords, dtype=np.float64).reshape(-1, p)
                a = hc[np.random.default_rng(s + 1).integers(len(hc), size=count)]
            z = np.hstack([z, a])
        return z

    val_poses = None
    val_snap = np.zeros((0, B.shape[1]))
    if pose_source == "snapshots":
        z = snapshot_poses(U, model, snapshots, lifting=lifting, sim=sim)
        held = np.arange(len(z)) % 4 == 3
        poses, val_poses = z[~held], z[held]
    else:
        poses = random_poses(num_training_poses, s_train)
        if pose_source == "random+snapshots":
            z = snapshot_poses(U, model, snapshots, lifting=lifting, sim=sim)
            held = (np.arange(len(z)) % 4 == 3) if len(z) >= 4 else np.zeros(len(z), dtype=bool)
            poses = np.vstack([poses, z[~held]])
            val_snap = z[held]
    table = _ForceTable(sim, model, U, poses, B)
    m = len(table.tets)
    rng = np.random.default_rng(s_pick)
    sel = np.zeros(0, dtype=np.int64)
    A = np.zeros((len(table.b), 0))
    w = np.zeros(0)
    err = 1.0
    bnorm = np.linalg.norm(table.b)
    for _ in range(4 * int(max_points)):
        if err <= tolerance or len(sel) >= max_points:
            break
        remaining = np.setdiff1d(np.arange(m), sel)
        if remaining.size == 0:
            break
        cand = rng.choice(remaining, size=min(int(candidates), remaining.size), replace=False)
        cols = table.columns(cand)
        res = table.b - A @ w
        norms = np.linalg.norm(cols, axis=0)
        score = (cols.T @ res) / np.maximum(norms, 1e-300)
        best = int(np.argmax(score))
        sel = np.append(sel, cand[best])
        A = np.hstack([A, cols[:, best:best + 1]])
        w, _ = scipy.optimize.nnls(A, table.b, maxiter=50 * A.shape[1] + 100)
        keep = w > 0.0
        sel, A, w = sel[keep], A[:, keep], w[keep]
        err = float(np.linalg.norm(A @ w - table.b) / bnorm)
    order = np.argsort(sel)
    sel, w = sel[order], w[order]
    train_err = table.error(sel, w)
    del table
    if val_poses is None:
        val_poses = random_poses(num_validation_poses, s_val) if num_validation_poses > 0 else np.zeros((0, B.shape[1]))
        val_poses = np.vstack([val_poses, val_snap])
    val_err = _ForceTable(sim, model, U, val_poses, B).error(sel, w) if len(val_poses) else float("nan")
    return Cubature(elements=sel, weights=w, training_error=train_err, validation_error=val_err,
                    training_seconds=time.perf_counter() - t0, training_poses=poses, tolerance=float(tolerance),
                    max_points=int(max_points), seed=int(seed), reached_tolerance=bool(train_err <= tolerance),
                    num_validation_poses=int(len(val_poses)))


def relative_force_error(forces_approx, forces_exact) -> float:
    """||A w - b|| / ||b|| over poses, each pose normalised by ||b_t|| (the training metric).

    Both arguments are (T, r) reduced forces.
    """
    a = np.asarray(forces_approx, dtype=np.float64)
    b = np.asarray(forces_exact, dtype=np.float64)
    nb = np.linalg.norm(b, axis=1)
    nb[nb == 0.0] = 1.0
    return float(np.linalg.norm((a - b) / nb[:, None]) / np.linalg.norm(b / nb[:, None]))
