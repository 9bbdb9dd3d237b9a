"""Rest-state mass matrices of a Tet4 mesh (scalar per vertex; the 3D matrix is M kron I3)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["lumped_mass", "consistent_mass"]


def _density_per_tet(mesh, density):
    rho = np.asarray(density, dtype=np.float64)
    if rho.ndim == 0:
        rho = np.full(mesh.num_tets, float(rho))
    if rho.shape != (mesh.num_tets,):
        raise ValueError(f"density must be a scalar or shape ({mesh.num_tets},), got {rho.shape}")
    bad = np.flatnonzero(~(np.isfinite(rho) & (rho > 0)))
    if bad.size:
        raise ValueError(f"density must be finite and > 0; tet {bad[0]} has {rho[bad[0]]}")
    return rho


def lumped_mass(mesh, density):
    """Row-sum lumped mass, (n,) float64: each tet gives rho V / 4 to each of its vertices."""
    m_e = _density_per_tet(mesh, density) * mesh.rest_volumes() / 4.0
    return np.bincount(mesh.tets.ravel(), weights=np.repeat(m_e, 4), minlength=mesh.num_vertices)


def consistent_mass(mesh, density):
    """Consistent Tet4 mass, scipy.sparse.csr_matrix (n, n): per tet rho V / 20 (1 + delta_ab)."""
    m_e = _density_per_tet(mesh, density) * mesh.rest_volumes() / 20.0
    t = mesh.tets
    rows = np.repeat(t, 4, axis=1).ravel()  # a a a a b b b b ...
    cols = np.tile(t, (1, 4)).ravel()  # a b c d a b c d ...
    local = (np.ones((4, 4)) + np.eye(4)).ravel()
    vals = (m_e[:, None] * local[None, :]).ravel()
    n = mesh.num_vertices
    M = sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr()
    M.sum_duplicates()
    M.sort_indices()
    return M
