"""Mass matrices of any element type from quadrature (scalar per node pair; 3D = M kron I3)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .library import check_element_type, gauss_rule, shape_functions
from warpfem.mesh.element_types import ELEMENTS, get_element

__all__ = ["element_mass_matrices", "consistent_mass_matrix", "lumped_mass_vector", "mass_matrices"]

#: lumping scheme used per element type (each element type object says its own)
LUMPING = {n: e.lumping for n, e in ELEMENTS.items()}


def _density(density, m):
    rho = np.asarray(density, dtype=np.float64)
    if rho.ndim == 0:
        rho = np.full(m, float(rho))
    if rho.shape != (m,):
        raise ValueError(f"density must be a scalar or shape ({m},), got {rho.shape}")
    bad = np.flatnonzero(~(np.isfinite(rho) & (rho > 0)))
    if bad.size:
        raise ValueError(f"density must be finite and > 0 (kg/m^3); element {bad[0]} has {rho[bad[0]]}")
    return rho


def element_mass_matrices(vertices, elements, element_type: str, density) -> np.ndarray:
    """Consistent element mass matrices (m, k, k), kg: rho sum_q w_q det J_q N_a N_b with the mass
    rule of :func:`~warpfem.elements.library.gauss_rule` (exact for affine elements)."""
    from .quadrature import element_point_data

    check_element_type(element_type)
    vertices = np.asarray(vertices, dtype=np.float64)
    elements = np.asarray(elements, dtype=np.int64)
    pts, w = gauss_rule(element_type, "mass")
    det, _ = element_point_data(vertices, elements, element_type, pts)
    N = shape_functions(element_type, pts)  # (q, k)
    rho = _density(density, len(elements))
    return np.einsum("m,mq,qa,qb->mab", rho, det * w[None, :], N, N)


def _assemble(elements, Me, n):
    m, k = elements.shape
    rows = np.repeat(elements, k, axis=1).ravel()
    cols = np.tile(elements, (1, k)).ravel()
    M = sp.coo_matrix((Me.reshape(-1), (rows, cols)), shape=(n, n)).tocsr()
    M.sum_duplicates()
    M.sort_indices()
    return M


def _lump(Me, element_type):
    if get_element(element_type).lumping == "row-sum":
        return Me.sum(axis=2)
    # HRZ (Hinton, Rock & Zienkiewicz 1976): diagonal scaled to the element mass, always > 0
    d = np.einsum("maa->ma", Me)
    return d * (Me.sum(axis=(1, 2)) / d.sum(axis=1))[:, None]


def consistent_mass_matrix(mesh, density) -> sp.csr_matrix:
    """Consistent mass (n, n) scipy CSR (kg) of an element mesh (``vertices``, ``elements``,
    ``element_type``)."""
    el = np.asarray(mesh.elements, dtype=np.int64)
    Me = element_mass_matrices(mesh.vertices, el, mesh.element_type, density)
    return _assemble(el, Me, len(mesh.vertices))


def lumped_mass_vector(mesh, density) -> np.ndarray:
    """Lumped nodal masses (n,) kg, all positive, summing to the total mass rho V.

    Tet4 and Hex8: row-sum lumping (rho int N_a, positive for these elements).
    Tet10 and Hex27: HRZ diagonal scaling m_a = M_aa * (element mass / sum_b M_bb); row sums would
    give zero (Hex27 corners stay positive but Tet10 corners get -rho V / 20) masses.
    """
    el = np.asarray(mesh.elements, dtype=np.int64)
    Me = element_mass_matrices(mesh.vertices, el, mesh.element_type, density)
    return np.bincount(el.ravel(), weights=_lump(Me, mesh.element_type).ravel(), minlength=len(mesh.vertices))


def mass_matrices(model, density):
    """(lumped (n,), mass matrix (n, n) CSR) for a :class:`warpfem.Model`: the second item is the
    consistent matrix when ``model.mass_matrix_kind == "consistent"``, else diag(lumped).
    Lumping: the element type's (row-sum for Tet4/Hex8, HRZ for Tet10/Hex27, see
    :func:`lumped_mass_vector`). Tet4 uses the closed forms of :mod:`warpfem.mesh.mass`."""
    mesh = model.mesh
    etype = mesh.element_type
    if etype == "tet4":  # closed form: rho V / 20 (1 + delta_ij) per tet, lumped = rho V / 4 per corner
        from warpfem.mesh import consistent_mass, lumped_mass

        lumped = lumped_mass(mesh, density)
        consistent = getattr(model, "mass_matrix_kind", "lumped") == "consistent"
        M = consistent_mass(mesh, density) if consistent else sp.diags(lumped)
        return lumped, sp.csr_matrix(M)
    el = np.asarray(mesh.elements, dtype=np.int64)
    Me = element_mass_matrices(model.rest_positions, el, etype, density)
    n = model.num_vertices
    lumped = np.bincount(el.ravel(), weights=_lump(Me, etype).ravel(), minlength=n)
    if getattr(model, "mass_matrix_kind", "lumped") == "consistent":
        M = _assemble(el, Me, n)
    else:
        M = sp.diags(lumped).tocsr()
    return lumped, M
