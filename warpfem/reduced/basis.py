"""Subspace bases: linear vibration modes and modal derivatives (Barbic & James 2005).

All bases are (3n x r) dense float64 with rows ordered vertex-major (row 3 v + k is component k
of vertex v), zero rows at fixed components, and mass-orthonormal: U^T M U = I.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg


@dataclass
class Basis:
    """A subspace basis and what it was built from.

    Attributes:
        U: (3n, r) float64, mass-orthonormal columns (U^T M U = I), zero at fixed components.
        linear_frequencies: (m,) angular frequencies omega_i (rad/s) of the linear modes computed
            (elastic modes only, ascending).
        frequencies: (r,) angular frequencies (rad/s) of the basis itself: sqrt of the eigenvalues of
            U^T K U (rest stiffness projected), ascending order of the columns is not implied.
        num_rigid: number of rigid columns kept (3 translations for unconstrained objects, else 0).
        modal_derivatives: whether modal derivatives were added before the mass-PCA.
    """

    U: np.ndarray
    linear_frequencies: np.ndarray
    frequencies: np.ndarray
    num_rigid: int = 0
    modal_derivatives: bool = False
    info: dict = field(default_factory=dict)

    @property
    def size(self) -> int:
        return int(self.U.shape[1])


def _full_simulator(model):
    from warpfem.simulator import Simulator

    return Simulator(model, device="cpu", precision="float64")


def _free_dofs(model) -> np.ndarray:
    return np.flatnonzero(~np.asarray(model.fixed).reshape(-1))


def _translation_columns(model, M) -> np.ndarray:
    """Mass-orthonormal rigid translations (3n x 3)."""
    n = model.num_vertices
    T = np.zeros((3 * n, 3))
    for k in range(3):
        T[k::3, k] = 1.0
    G = T.T @ (M @ T)
    return T @ np.linalg.inv(np.linalg.cholesky(G)).T


def linear_modes(model, num_modes: int, *, sim=None):
    """Lowest ``num_modes`` elastic vibration modes of K u = lambda M u at rest.

    Fixed components are removed (rows/columns dropped). Solved with ``scipy.sparse.linalg.eigsh``
    in shift-invert mode. For an unconstrained object (no fixed component) the 6 rigid modes
    (eigenvalue ~0) are computed too and dropped, so only elastic modes are returned.

    Returns (Phi (3n, m) mass-orthonormal, omega (m,) rad/s ascending, rigid_dropped: int).
    """
    if int(num_modes) != num_modes or num_modes < 1:
        raise ValueError(f"num_modes must be a positive integer, got {num_modes!r}")
    num_modes = int(num_modes)
    sim = sim or _full_simulator(model)
    X = model.rest_positions
    K = sim.stiffness_matrix(X, project=False).tocsc()
    M = sim.mass_matrix().tocsc()
    free = _free_dofs(model)
    unconstrained = len(free) == K.shape[0]
    rigid = 6 if unconstrained else 0
    nf = len(free)
    want = num_modes + rigid
    if want >= nf - 1:
        raise ValueError(f"asked for {num_modes} modes but the mesh has only {nf} free degrees of freedom")
    Kf = K[free][:, free]
    Mf = M[free][:, free]
    # shift below zero so that K - sigma M is non-singular even with rigid modes
    scale = float(Kf.diagonal().mean() / Mf.diagonal().mean())
    sigma = -1e-6 * scale
    vals, vecs = scipy.sparse.linalg.eigsh(Kf, k=want, M=Mf, sigma=sigma, which="LM",
                                           v0=np.ones(nf) / np.sqrt(nf))
    order = np.argsort(vals)
    vals, vecs = vals[order], vecs[:, order]
    vals, vecs = vals[rigid:], vecs[:, rigid:]
    if np.any(vals <= 0):
        raise ValueError(f"non-positive stiffness eigenvalue {vals.min():.3e}: the model is not "
                         "constrained enough (or the material is unstable at rest)")
    Phi = np.zeros((K.shape[0], num_modes))
    Phi[free] = vecs
    # re-normalise against the full M (eigsh already does, but be exact)
    Phi /= np.sqrt(np.einsum("ij,ij->j", Phi, M @ Phi))
    return Phi, np.sqrt(vals), rigid


def modal_derivatives(model, Phi, *, sim=None, step: float | None = None) -> np.ndarray:
    """Modal derivatives phi_ij (i <= j) solving K phi_ij = -(dK/dq_i) psi_j on the free DOFs.

    The directional derivative dK/dq_i is a central finite difference of the assembled (unprojected)
    stiffness along psi_i with step ``step`` (default: 1e-4 of the object size over max|psi_i|).
    Requires fixed vertices (K must be invertible on the free DOFs). Returns (3n, m (m+1) / 2).
    """
    sim = sim or _full_simulator(model)
    free = _free_dofs(model)
    if len(free) == 3 * model.num_vertices:
        raise ValueError("modal derivatives need a constrained object (fix some vertices); "
                         "they are not defined for free-floating bodies here")
    X = model.rest_positions
    size = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    K0 = sim.stiffness_matrix(X, project=False).tocsc()
    lu = scipy.sparse.linalg.splu(K0[free][:, free].tocsc())
    m = Phi.shape[1]
    out = []
    for i in range(m):
        psi = Phi[:, i]
        h = step if step is not None else 1e-4 * size / np.abs(psi).max()
        Kp = sim.stiffness_matrix(X + h * psi.reshape(-1, 3), project=False)
        Km = sim.stiffness_matrix(X - h * psi.reshape(-1, 3), project=False)
        dK = (Kp - Km) / (2.0 * h)
        for j in range(i, m):
            rhs = -(dK @ Phi[:, j])[free]
            phi = np.zeros(3 * model.num_vertices)
            phi[free] = lu.solve(rhs)
            out.append(phi)
    return np.array(out).T if out else np.zeros((3 * model.num_vertices, 0))


def mass_pca(B: np.ndarray, M, r: int, *, rel_tol: float = 1e-10) -> np.ndarray:
    """Best r-dimensional mass-orthonormal subspace of the columns of B (M-weighted PCA).

    With G = B^T M B = V diag(s) V^T (descending), returns B V_r diag(s_r)^-1/2; columns whose
    singular value is below rel_tol * s_max are discarded (so fewer than r may come back).
    """
    G = B.T @ (M @ B)
    G = 0.5 * (G + G.T)
    s, V = np.linalg.eigh(G)
    order = np.argsort(s)[::-1]
    s, V = s[order], V[:, order]
    keep = s > rel_tol * s[0]
    k = min(int(r), int(keep.sum()))
    U = B @ (V[:, :k] / np.sqrt(s[:k]))
    # one more M-orthonormalisation (Cholesky) removes the round-off of small singular values
    G = U.T @ (M @ U)
    return U @ np.linalg.inv(np.linalg.cholesky(0.5 * (G + G.T))).T


def _modes_for_derivatives(r: int) -> int:
    m = 1
    while m + m * (m + 1) // 2 < r:
        m += 1
    return m


def static_load_response(model, *, sim=None) -> np.ndarray | None:
    """Linear static response u = K^-1 f_ext (3n,) to the model's external loads (gravity + applied),
    zero at fixed components; None when there is no load or no fixed vertex."""
    sim = sim or _full_simulator(model)
    f = model.external_forces().reshape(-1)
    free = _free_dofs(model)
    if len(free) == f.size or not np.any(f[free]):
        return None
    K = sim.stiffness_matrix(model.rest_positions, project=False).tocsc()
    u = np.zeros_like(f)
    u[free] = scipy.sparse.linalg.spsolve(K[free][:, free].tocsc(), f[free])
    return u


def _with_load_column(U, u, M, r):
    """[s, PCA of U M-orthogonalised against s] with r columns, s = u / |u|_M (mass-orthonormal)."""
    s = u / np.sqrt(u @ (M @ u))
    rest = U - np.outer(s, s @ (M @ U))
    return np.hstack([s[:, None], mass_pca(rest, M, r - 1)])


def snapshot_displacements(model, snapshots, lifting=None) -> np.ndarray:
    """Displacements (3n, T) of full-mesh positions x_t (each (n, 3), m) with the handle motion
    removed: d_t = x_t - X - L a(x_t) (``lifting``), zero at fixed components."""
    X = np.asarray(model.rest_positions, dtype=np.float64)
    fixed = np.asarray(model.fixed).reshape(-1)
    cols = []
    for x in snapshots:
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        if x.shape != X.shape or not np.all(np.isfinite(x)):
            raise ValueError(f"snapshot positions must be finite with shape {X.shape}, got {x.shape}")
        d = (x - X).reshape(-1)
        if lifting is not None and lifting.size:
            d = d - lifting.L @ lifting.coords_from_positions(x)
        d[fixed] = 0.0
        cols.append(d)
    return np.array(cols).T if cols else np.zeros((X.size, 0))


def pod_columns(D, M, U=None, k: int = 0, *, rel_tol: float = 1e-12):
    """Mass-weighted POD (proper orthogonal decomposition) of snapshot displacements D (3n, T):
    the k dominant M-orthonormal directions of D after removing its M-orthogonal projection on
    span U (so [U | P] stays mass-orthonormal). Directions whose energy is below rel_tol of the
    largest (relative to the snapshots' own M-norm) are dropped, so fewer than k may come back.

    Returns (P (3n, <= k), captured: fraction of the residual's M-energy that P spans)."""
    D = np.asarray(D, dtype=np.float64)
    if k <= 0 or D.shape[1] == 0:
        return np.zeros((D.shape[0], 0)), 1.0
    R = D if U is None or U.shape[1] == 0 else D - U @ (U.T @ (M @ D))
    G = R.T @ (M @ R)
    G = 0.5 * (G + G.T)
    s, V = np.linalg.eigh(G)
    order = np.argsort(s)[::-1]
    s, V = np.clip(s[order], 0.0, None), V[:, order]
    total = float(np.einsum("ij,ij->", D, M @ D))
    keep = s > rel_tol * max(total, 1e-300)
    kk = min(int(k), int(keep.sum()))
    if kk == 0:
        return np.zeros((D.shape[0], 0)), 1.0
    P = R @ (V[:, :kk] / np.sqrt(s[:kk]))
    if U is not None and U.shape[1]:
        P = P - U @ (U.T @ (M @ P))  # re-orthogonalise (round-off)
    G = P.T @ (M @ P)
    P = P @ np.linalg.inv(np.linalg.cholesky(0.5 * (G + G.T))).T
    captured = float(s[:kk].sum() / max(s.sum(), 1e-300))
    return P, captured


def projection_error(U, M, D) -> np.ndarray:
    """Per-snapshot M-norm of the part of D (3n, T) outside span U (M-orthonormal U): the error of
    the best mass-weighted fit of each snapshot in the span (the floor of any reduced run)."""
    D = np.asarray(D, dtype=np.float64)
    R = D - U @ (U.T @ (M @ D)) if U.shape[1] else D
    return np.sqrt(np.clip(np.einsum("ij,ij->j", R, M @ R), 0.0, None))


def build_basis(model, *, modes: int, modal_derivatives_: bool = False, load_response: bool = False,
                sim=None, snapshot_displacements_=None, pod_modes: int = 0) -> Basis:
    """The r = ``modes`` column basis used by the reduced simulator.

    * without modal derivatives: the ``modes`` lowest linear modes;
    * with: m linear modes (smallest m with m + m(m+1)/2 >= modes) and their m(m+1)/2 modal
      derivatives, scaled by omega_1^2/omega_i^2 and omega_1^4/(omega_i^2 omega_j^2)
      (Barbic & James 2005), then mass-PCA down to ``modes`` columns.
    * ``load_response=True`` (constrained objects with loads): the linear static response to the
      external loads, K^-1 f_ext, is made one of the r columns exactly (the other r - 1 come from
      the modes / derivatives M-orthogonalised against it). Low vibration modes need not span the
      load response: the bunny's lowest modes sway, gravity compresses it (measured: r = 10 modal
      derivatives miss 72 % of K^-1 f_gravity).
    * ``pod_modes`` = k > 0 with ``snapshot_displacements_`` (3n, T) (from
      :func:`snapshot_displacements`, e.g. frames of a full run of the scene): k more columns, the
      mass-weighted POD of the snapshots' part outside the modal span (:func:`pod_columns`), so
      r = ``modes`` + k (fewer when the snapshots have fewer independent directions). The whole
      basis stays mass-orthonormal.
    * Unconstrained objects: rigid modes are handled explicitly by keeping the 3 rigid
      translations as exact columns (so the body can move and fall); infinitesimal rotations are
      not kept (a linear subspace cannot rotate an object without shearing it), so
      ``modes`` = 3 translations + (modes - 3) elastic modes. Modal derivatives need fixed vertices.
    """
    if int(modes) != modes or modes < 1:
        raise ValueError(f"modes must be a positive integer, got {modes!r}")
    modes = int(modes)
    sim = sim or _full_simulator(model)
    M = sim.mass_matrix()
    K = sim.stiffness_matrix(model.rest_positions, project=False)
    unconstrained = not np.asarray(model.fixed).any()
    info = {}
    if unconstrained:
        if modal_derivatives_:
            raise ValueError("modal_derivatives=True needs fixed vertices; this model has none")
        if modes < 4:
            raise ValueError("an unconstrained object needs modes >= 4 (3 rigid translations + elastic modes)")
        Phi, omega, _ = linear_modes(model, modes - 3, sim=sim)
        U = np.hstack([_translation_columns(model, M), Phi])
        nrig = 3  # elastic modes are M-orthogonal to translations (eigenvectors of K u = l M u)
    elif modal_derivatives_:
        # symmetric cross-sections give linearly dependent derivatives: add linear modes until the
        # mass-PCA has r independent directions
        m = _modes_for_derivatives(modes)
        while True:
            Phi, omega, _ = linear_modes(model, m, sim=sim)
            D = modal_derivatives(model, Phi, sim=sim)
            w1 = omega[0] ** 2
            scales = [w1 ** 2 / (omega[i] ** 2 * omega[j] ** 2) for i in range(m) for j in range(i, m)]
            U = mass_pca(np.hstack([Phi * (w1 / omega ** 2), D * np.array(scales)]), M, modes)
            if U.shape[1] >= modes or m >= modes:
                break
            m += 1
        if U.shape[1] < modes:
            raise ValueError(f"could only build {U.shape[1]} independent columns, asked for modes={modes}")
        nrig = 0
        info["linear_modes_used"] = m
        info["modal_derivatives_computed"] = D.shape[1]
    else:
        Phi, omega, _ = linear_modes(model, modes, sim=sim)
        U, nrig = Phi, 0
    if load_response and not unconstrained:
        u = static_load_response(model, sim=sim)
        if u is not None:
            U = _with_load_column(U, u, M, modes)
            info["load_response"] = True
    if pod_modes and snapshot_displacements_ is not None:
        P, captured = pod_columns(snapshot_displacements_, M, U, int(pod_modes))
        U = np.hstack([U, P])
        info["pod_modes"] = int(P.shape[1])
        info["pod_captured"] = captured
        D = np.asarray(snapshot_displacements_)
        dn = np.sqrt(np.einsum("ij,ij->j", D, M @ D))
        info["snapshot_floor"] = float((projection_error(U, M, D) / max(dn.max(), 1e-300)).max())
    Kr = U.T @ (K @ U)
    ev = np.linalg.eigvalsh(0.5 * (Kr + Kr.T))
    freqs = np.sqrt(np.clip(ev, 0.0, None))
    return Basis(U=np.ascontiguousarray(U), linear_frequencies=omega, frequencies=freqs, num_rigid=nrig,
                 modal_derivatives=bool(modal_derivatives_), info=info)


def basis_amplitudes(basis: Basis, model, K=None) -> np.ndarray:
    """Per-column Rayleigh frequencies omega_j = sqrt(u_j^T K u_j) (rad/s; 0 for rigid columns)."""
    if K is None:
        K = _full_simulator(model).stiffness_matrix(model.rest_positions, project=False)
    d = np.einsum("ij,ij->j", basis.U, K @ basis.U)
    return np.sqrt(np.clip(d, 0.0, None))
