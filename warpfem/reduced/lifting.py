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

Rotation-aware lifting (``rotation_order`` = J >= 2, handles with all three components): the
interior follows the handle's rigid motion with the rotation *angle* interpolated,

    x = X + w (A (X - c) + b - (X - c)) + sum_{j=2..J} (w^j - w) / j! [omega]_x^j (X - c)
      = X + w t + (exp(w [omega]_x) - I)(X - c) + O(|omega|^(J+1) / (J+1)!)   for a rigid motion,

with w the handle's harmonic weight (scalar Laplace extension: 1 on the handle, 0 on the other
handles and the fixed vertices), c the handle's rest centroid, (A, b) the handle's fitted affine
motion and omega the rotation vector of its rotation (Kabsch fit of the handle vertices). The first
term is linear blend skinning of the affine motion, the sum turns the blend of rotations into a
rotation by w omega (no shrinking "candy wrapper" at large angles). It is still linear in the handle
coordinates: [omega]_x^(2m+1) = (-|omega|^2)^m [omega]_x and [omega]_x^(2m) = (-|omega|^2)^(m-1)
[omega]_x^2, so each odd j adds 3 columns (w^j - w) e_i x (X - c) with coordinates
(-|omega|^2)^m omega_i / j!, each even j adds 6 columns for the products omega_a omega_b. The
correction columns vanish on the handle (w = 1) and on the fixed vertices (w = 0), so the handle
is still exactly where its targets put it.
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
    rotation: list | None = None  # per group: None, or (J, centre (3,)): rotation-aware columns after its affine ones

    @property
    def size(self) -> int:
        return int(self.L.shape[1])

    def rotation_of(self, g):
        """The rotation fitted for handle group g, or None."""
        return self.rotation[g] if self.rotation is not None and g < len(self.rotation) else None

    @property
    def signature(self) -> str:
        return handle_signature([(g[0], g[1]) for g in self.groups])

    def group_coords(self, g: int, targets) -> np.ndarray:
        """Coordinates of handle ``g`` (its block of a) for target positions (h, 3), m.

        Least squares on the handle's vertices (exact for affine motions of the handle)."""
        ids, comps, Q, _ = self.groups[g]
        y = np.asarray(targets, dtype=np.float64).reshape(len(ids), 3)
        d = y - self._X[ids]
        rot = self.rotation_of(g)
        if rot is None:
            return np.concatenate([Q.T @ d[:, "xyz".index(c)] for c in comps])
        Xh = self._X[ids]
        omega = handle_rotation_vector(Xh, y)
        sc, cc, R = _rotation_factors(omega)
        d = d - (Xh - rot[1]) @ (R - np.eye(3)).T  # what the rigid rotation about the centre leaves: affine
        return np.concatenate(
            [*(Q.T @ d[:, k] for k in range(3)), sc * omega, cc * np.array([omega[a] * omega[b] for a, b in _PAIRS]),
             rotation_coords(omega, rot[0])])

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
        rot = self.rotation_of(g)
        return slice(first, first + len(comps) * Q.shape[1] + (0 if rot is None else 9 + num_rotation_coords(rot[0])))

    def bind(self, rest_positions):
        self._X = np.asarray(rest_positions, dtype=np.float64)
        return self


_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def num_rotation_coords(order: int) -> int:
    """Rotation-aware columns of one handle for ``order`` J: 3 per odd j, 6 per even j, j = 2..J."""
    return sum(3 if j % 2 else 6 for j in range(2, int(order) + 1))


def handle_rotation_vector(rest, targets) -> np.ndarray:
    """Rotation vector (3,) of the best rigid fit (Kabsch) of a handle's rest positions (h, 3) to
    its targets: the rotation the rotation-aware lifting interpolates."""
    from scipy.spatial.transform import Rotation

    P = rest - rest.mean(axis=0)
    Q = targets - targets.mean(axis=0)
    u, _, vt = np.linalg.svd(P.T @ Q)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T)) or 1.0])
    return Rotation.from_matrix(vt.T @ D @ u.T).as_rotvec()


def _rotation_factors(omega):
    """(sin t / t, (1 - cos t) / t^2, R) for rotation vector omega, t = |omega|: R = I + s [w]_x + c [w]_x^2."""
    t = float(np.linalg.norm(omega))
    if t < 1e-4:  # Taylor: exact to round-off
        sc, cc = 1.0 - t * t / 6.0, 0.5 - t * t / 24.0
    else:
        sc, cc = np.sin(t) / t, (1.0 - np.cos(t)) / (t * t)
    W = np.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])
    return sc, cc, np.eye(3) + sc * W + cc * (W @ W)


def rotation_coords(omega, order: int) -> np.ndarray:
    """Coordinates of the rotation-aware columns for rotation vector ``omega``: for odd j = 2m + 1,
    (-|omega|^2)^m omega / j!; for even j = 2m, (-|omega|^2)^(m - 1) omega_a omega_b / j! (pairs
    a <= b in :data:`_PAIRS` order)."""
    import math

    w = np.asarray(omega, dtype=np.float64)
    n2 = float(w @ w)
    prods = np.array([w[a] * w[b] for a, b in _PAIRS])
    out = []
    for j in range(2, int(order) + 1):
        if j % 2:
            out.append((-n2) ** ((j - 1) // 2) / math.factorial(j) * w)
        else:
            out.append((-n2) ** (j // 2 - 1) / math.factorial(j) * prods)
    return np.concatenate(out) if out else np.zeros(0)


def _rotation_columns(r, w, order, *, first=2):
    """(3n, .) columns f_j [.]_x^j r for r = X - c (n, 3), w (n,), j = first..order: f_j = w^j - w
    (the interpolation corrections), or for ``first`` = 0 the rigid blend w [.]_x r, w [.]_x^2 r."""
    n = len(r)
    cols = []
    for j in ((1, 2) if first == 0 else range(first, int(order) + 1)):
        f = (w if first == 0 else w ** j - w)[:, None]
        if j % 2:
            for i in range(3):
                e = np.zeros(3)
                e[i] = 1.0
                cols.append((f * np.cross(e, r)).reshape(-1))
        else:
            for a, b in _PAIRS:
                v = np.zeros((n, 3))
                if a == b:
                    v[:, a] = r[:, a]
                    v -= r
                else:
                    v[:, a] = r[:, b]
                    v[:, b] = r[:, a]
                cols.append((f * v).reshape(-1))
    return np.array(cols).T if cols else np.zeros((3 * n, 0))


def harmonic_weights(model, ones, zeros) -> np.ndarray:
    """Scalar harmonic extension w (n,) (piecewise-linear Laplace equation on the tets) with w = 1
    on vertex ids ``ones`` and w = 0 on ``zeros``; w = 1 everywhere when ``zeros`` is empty."""
    import scipy.sparse

    qd = model.quadrature
    from warpfem.mesh.element_types import get_element

    if not get_element(qd.element_type).is_linear_tet:
        raise ValueError(f"rotation-aware lifting supports tet4 meshes only, got {qd.element_type!r}")
    n = model.num_vertices
    zeros = np.setdiff1d(np.asarray(zeros, dtype=np.int64), ones)
    if zeros.size == 0:
        return np.ones(n)
    tets = qd.elements.reshape(-1, 4)
    G = qd.qp_dNdX.reshape(-1, 4, 3)
    Ke = np.einsum("eai,ebi->eab", G, G) * qd.qp_weight[:, None, None]
    rows = np.repeat(tets, 4, axis=1).reshape(-1)
    cols = np.tile(tets, (1, 4)).reshape(-1)
    K = scipy.sparse.csr_matrix((Ke.reshape(-1), (rows, cols)), shape=(n, n))
    w = np.zeros(n)
    w[ones] = 1.0
    known = np.zeros(n, dtype=bool)
    known[ones] = known[zeros] = True
    free = np.flatnonzero(~known)
    if free.size:
        rhs = -(K[free][:, known] @ w[known])
        w[free] = scipy.sparse.linalg.spsolve(K[free][:, free].tocsc(), rhs)
    return np.clip(w, 0.0, 1.0)


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


def build_lifting(model, handles, *, sim=None, rotation_order: int = 0) -> Lifting:
    """Lifting columns for ``handles`` = [(vertex ids, components "xyz"/"z"/...), ...].

    The handle components must be fixed in ``model`` (the scene fixes them). One sparse LU of the
    free-free rest stiffness, p right-hand sides (p <= 12 per handle).

    ``rotation_order`` = J >= 2: handles with all three components get the rotation-aware lifting
    (module docstring): linear blend skinning with harmonic weights plus
    ``num_rotation_coords(J)`` columns that interpolate the rotation angle (J = 7: error below
    1e-4 of the handle's size for a 90-degree turn); other handles keep the elastic extension.
    """
    if rotation_order and int(rotation_order) < 2:
        raise ValueError(f"rotation_order must be 0 (linear lifting) or >= 2, got {rotation_order!r}")
    if rotation_order:
        return _build_rotation_lifting(model, handles, int(rotation_order), sim=sim)
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


def _build_rotation_lifting(model, handles, order, *, sim=None) -> Lifting:
    from warpfem.model import parse_components

    n = model.num_vertices
    X = model.rest_positions
    fixed = np.asarray(model.fixed)
    all_ids = [np.unique(np.asarray(ids, dtype=np.int64)) for ids, _ in handles]
    plain, plain_at = [], []
    for gi, (ids, comps) in enumerate(handles):
        if len(parse_components(comps)) < 3:
            plain.append((ids, comps))
            plain_at.append(gi)
    base = build_lifting(model, plain, sim=sim) if plain else None
    fully_fixed = np.flatnonzero(fixed.all(axis=1))
    groups, blocks, rotation, first = [], [], [], 0
    for gi, (ids, comps) in enumerate(handles):
        ids = all_ids[gi]
        if gi in plain_at:
            k = plain_at.index(gi)
            bid, bcomps, Q, bfirst = base.groups[k]
            blocks.append(base.L[:, base.group_slice(k)])
            groups.append((bid, bcomps, Q, first))
            rotation.append(None)
            first += blocks[-1].shape[1]
            continue
        if ids.size == 0:
            raise ValueError(f"handle #{gi + 1} has no vertices")
        if not fixed[ids].all():
            raise ValueError(f"handle #{gi + 1}: its components 'xyz' must be fixed in the model")
        zeros = np.setdiff1d(np.concatenate([fully_fixed] + [all_ids[h] for h in range(len(handles)) if h != gi]), ids)
        w = harmonic_weights(model, ids, zeros)
        Xh = X[ids]
        c = Xh.mean(axis=0)
        Q = _affine_functions(Xh)
        # the affine functions Q (values on the handle) as functions of X everywhere: Q = F C
        # (centred: a flat handle's functions extend constant across its thickness, min-norm)
        F = np.hstack([np.ones((len(Xh), 1)), Xh - c])
        C = np.linalg.lstsq(F, Q, rcond=None)[0]
        Qx = np.hstack([np.ones((n, 1)), X - c]) @ C  # (n, k)
        block = np.zeros((3 * n, 3 * Q.shape[1]))
        for a in range(3):
            for j in range(Q.shape[1]):
                block[a::3, a * Q.shape[1] + j] = w * Qx[:, j]
        block = np.hstack([block, _rotation_columns(X - c, w, order, first=0), _rotation_columns(X - c, w, order)])
        other = fixed.copy()
        other[ids] = False
        block[other.reshape(-1)] = 0.0  # zero at every fixed component but this handle's
        for a in range(3):  # on the handle: exactly the affine functions (w = 1 there)
            for j in range(Q.shape[1]):
                block[3 * ids + a, a * Q.shape[1] + j] = Q[:, j]
        blocks.append(block)
        groups.append((ids, "xyz", Q, first))
        rotation.append((order, c))
        first += block.shape[1]
    L = np.hstack(blocks) if blocks else np.zeros((3 * n, 0))
    return Lifting(np.ascontiguousarray(L), groups, rotation).bind(X)
