"""Kinematic handles in a subspace: a prescribed displacement field ("lifting") for handle motion.

The basis U is built with the handle vertices fixed (zero rows), and the handle motion enters as

    x = X + U q + L a,

with a the handle coordinates (prescribed each step from the targets) and L (3n x p) the lifting
columns: for every handle g, every prescribed component k and every affine function phi_j of the
rest position restricted to the handle (1, X - c, Y - c, Z - c, orthonormalised over the handle's
vertices, rank-deficient ones dropped: a flat handle has no function across its thickness), the
column is the *static linear-elastic extension* of the displacement phi_j e_k on the handle (and 0
on every other fixed component) into the free DOFs: K_ff L_f = -K_fc L_c, K the rest stiffness.

Any affine motion of a handle (the scene's translations and rotations at a given ramp fraction
are affine in X) is represented exactly on the handle vertices; the interior follows the linear
extension and U q corrects it dynamically (exact for small motions, an approximation for large
rotations, where a linear field shears).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import scipy.sparse.linalg


def handle_signature(handles) -> str:
    """sha256 of the handle vertex ids and components (what the lifting was built for)."""
    h = hashlib.sha256()
    for ids, comps in handles:
        h.update(np.unique(np.asarray(ids, dtype=np.int64)).tobytes())
        h.update(str(comps).encode())
        h.update(b"|")
    return h.hexdigest()


@dataclass
class Lifting:
    """Lifting columns L (3n, p) and how to get the handle coordinates a from targets.

    groups: per handle, ``(ids (h,), components (str), Q (h, k) orthonormal affine functions,
    first column index)``; the handle's columns are ``first + comp_index * k + j``.
    """

    L: np.ndarray
    groups: list

    @property
    def size(self) -> int:
        return int(self.L.shape[1])

    @property
    def signature(self) -> str:
        return handle_signature([(g[0], g[1]) for g in self.groups])

    def group_coords(self, g: int, targets) -> np.ndarray:
        """Coordinates of handle ``g`` (its block of a) for target positions (h, 3), m.

        Least squares on the handle's vertices (exact for affine motions of the handle)."""
        ids, comps, Q, _ = self.groups[g]
        d = np.asarray(targets, dtype=np.float64).reshape(len(ids), 3) - self._X[ids]
        return np.concatenate([Q.T @ d[:, "xyz".index(c)] for c in comps])

    def coords_from_positions(self, x) -> np.ndarray:
        """a (p,) fitted to full-mesh positions x (n, 3) on every handle."""
        x = np.asarray(x, dtype=np.float64)
        return np.concatenate([self.group_coords(g, x[grp[0]]) for g, grp in enumerate(self.groups)]) \
            if self.groups else np.zeros(0)

    def coords_from_targets(self, targets_per_group) -> np.ndarray:
        """a (p,) from a list of per-handle target arrays (h_g, 3)."""
        return np.concatenate([self.group_coords(g, t) for g, t in enumerate(targets_per_group)]) \
            if self.groups else np.zeros(0)

    def group_slice(self, g: int) -> slice:
        ids, comps, Q, first = self.groups[g]
        return slice(first, first + len(comps) * Q.shape[1])

    def bind(self, rest_positions):
        self._X = np.asarray(rest_positions, dtype=np.float64)
        return self


def _affine_functions(Xh, *, rel_tol=1e-8):
    c = Xh.mean(axis=0)
    s = max(float(np.abs(Xh - c).max()), 1e-300)
    F = np.hstack([np.ones((len(Xh), 1)), (Xh - c) / s])
    Q, R = np.linalg.qr(F)
    keep = np.abs(np.diag(R)) > rel_tol * np.abs(np.diag(R)).max()
    if keep.all():
        return Q
    # rank deficient (flat or collinear handle): orthonormal basis of the column space via SVD
    Uf, sv, _ = np.linalg.svd(F, full_matrices=False)
    return Uf[:, sv > rel_tol * sv[0]]


def build_lifting(model, handles, *, sim=None) -> Lifting:
    """Lifting columns for ``handles`` = [(vertex ids, components "xyz"/"z"/...), ...].

    The handle components must be fixed in ``model`` (the scene fixes them). One sparse LU of the
    free-free rest stiffness, p right-hand sides (p <= 12 per handle).
    """
    from warpfem.model import parse_components
    from warpfem.reduced.basis import _free_dofs, _full_simulator

    n = model.num_vertices
    X = model.rest_positions
    groups, cols = [], []
    for gi, (ids, comps) in enumerate(handles):
        ids = np.unique(np.asarray(ids, dtype=np.int64))
        if ids.size == 0:
            raise ValueError(f"handle #{gi + 1} has no vertices")
        axes = parse_components(comps)
        comps = "".join("xyz"[a] for a in axes)
        if not model.fixed[np.ix_(ids, axes)].all():
            raise ValueError(f"handle #{gi + 1}: its components {comps!r} must be fixed in the model")
        Q = _affine_functions(X[ids])
        groups.append((ids, comps, Q))
        block = np.zeros((3 * n, len(axes) * Q.shape[1]))
        for ci, a in enumerate(axes):
            for j in range(Q.shape[1]):
                block[3 * ids + a, ci * Q.shape[1] + j] = Q[:, j]
        cols.append(block)
    if not cols:
        return Lifting(np.zeros((3 * n, 0)), []).bind(X)
    L = np.hstack(cols)
    first = 0
    fixed_groups = []  # (ids, comps, Q, first column)
    for ids, comps, Q in groups:
        fixed_groups.append((ids, comps, Q, first))
        first += len(comps) * Q.shape[1]
    sim = sim or _full_simulator(model)
    K = sim.stiffness_matrix(X, project=False).tocsr()
    free = _free_dofs(model)
    fixed = np.flatnonzero(np.asarray(model.fixed).reshape(-1))
    Kff = K[free][:, free].tocsc()
    Kfc = K[free][:, fixed]
    rhs = -(Kfc @ L[fixed])
    L[free] = scipy.sparse.linalg.splu(Kff).solve(np.asarray(rhs))
    return Lifting(np.ascontiguousarray(L), fixed_groups).bind(X)
