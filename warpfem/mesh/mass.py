"""Rest-state mass matrices of a mesh of any element type (scalar per node pair; the 3D matrix is
M kron I3), through the element type object (``mesh.element``):

* consistent: the element matrices rho int N_a N_b dV (``element.element_mass``: the "mass" rule,
  exact for affine elements; Tet4 uses the closed form rho V / 20 (1 + delta_ab)), assembled;
* lumped: the element's lumping (``element.lump``): row sums for Tet4 and Hex8 (Tet4: rho V / 4 per
  corner), HRZ diagonal scaling for Tet10 and Hex27 (row sums would give zero or negative corner
  masses there).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .element_types import get_element

__all__ = ["lumped_mass", "consistent_mass", "mass_matrices", "element_mass_matrices", "MASS_MATRIX_KINDS"]

MASS_MATRIX_KINDS = ("lumped", "consistent")


def _density_per_element(mesh, density):
    m = len(mesh.elements)
    rho = np.asarray(density, dtype=np.float64)
    if rho.ndim == 0:
        rho = np.full(m, float(rho))
    if rho.shape != (m,):
        raise ValueError(f"density must be a scalar or shape ({m},), got {rho.shape}")
    bad = np.flatnonzero(~(np.isfinite(rho) & (rho > 0)))
    if bad.size:
        raise ValueError(f"density must be finite and > 0 (kg/m^3); element {bad[0]} has {rho[bad[0]]}")
    return rho


def _parts(mesh):
    return (get_element(mesh.element_type), np.asarray(mesh.vertices, dtype=np.float64),
            np.asarray(mesh.elements, dtype=np.int64))


def element_mass_matrices(mesh, density) -> np.ndarray:
    """Consistent element mass matrices (m, k, k), kg."""
    element, X, el = _parts(mesh)
    return element.element_mass(X, el, _density_per_element(mesh, density))


def _assemble(elements, Me, n):
    k = elements.shape[1]
    rows = np.repeat(elements, k, axis=1).ravel()  # a a a a b b b b ...
    cols = np.tile(elements, (1, k)).ravel()  # a b c d a b c d ...
    M = sp.coo_matrix((Me.reshape(-1), (rows, cols)), shape=(n, n)).tocsr()
    M.sum_duplicates()
    M.sort_indices()
    return M


def _scatter(elements, lumped_e, n):
    return np.bincount(elements.ravel(), weights=lumped_e.ravel(), minlength=n)


def consistent_mass(mesh, density) -> sp.csr_matrix:
    """Consistent mass, scipy.sparse.csr_matrix (n, n), kg."""
    _, X, el = _parts(mesh)
    return _assemble(el, element_mass_matrices(mesh, density), len(X))


def lumped_mass(mesh, density) -> np.ndarray:
    """Lumped nodal masses (n,) kg, all positive, summing to the total mass rho V."""
    element, X, el = _parts(mesh)
    return _scatter(el, element.lumped_element_mass(X, el, _density_per_element(mesh, density)), len(X))


def mass_matrices(mesh, density, kind: str = "lumped"):
    """(lumped (n,), mass matrix (n, n) CSR): the second item is the consistent matrix for
    ``kind="consistent"``, diag(lumped) for ``"lumped"``."""
    if kind not in MASS_MATRIX_KINDS:
        raise ValueError(f"mass_matrix must be 'lumped' or 'consistent', got {kind!r}")
    element, X, el = _parts(mesh)
    rho = _density_per_element(mesh, density)
    if kind == "lumped":
        lumped = _scatter(el, element.lumped_element_mass(X, el, rho), len(X))
        return lumped, sp.diags(lumped).tocsr()
    Me = element.element_mass(X, el, rho)
    lumped_e = element.lumped_element_mass(X, el, rho, Me=Me)  # the generic lumping reuses Me
    return _scatter(el, lumped_e, len(X)), _assemble(el, Me, len(X))
