"""Tet4: the linear tetrahedron. Nodes 0:(0,0,0) 1:(1,0,0) 2:(0,1,0) 3:(0,0,1) (meshio ``tetra``);
N = barycentric coordinates L = (1 - xi - eta - zeta, xi, eta, zeta). Stiffness: 1 point (the
centroid), exact for degree 1. The geometry has closed forms, used instead of the generic
isoparametric code: volume 1/6 det[x1 - x0, x2 - x0, x3 - x0], gradients from Dm^-1, consistent mass
rho V / 20 (1 + delta_ab), lumped mass rho V / 4 per corner (Zienkiewicz & Taylor, "The Finite Element
Method")."""

import numpy as np

from .base import ElementError, SimplexElement, as_points, register_element, tet_conical_rule

TET4_NODES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
_DL = np.array([[-1.0, -1.0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])  # dL_i/dxi


def tet_volumes(vertices, tets):
    """Signed volumes 1/6 det[x1 - x0, x2 - x0, x3 - x0] of each tet, shape (m,)."""
    x = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64)
    x0 = x[t[:, 0]]
    d1 = x[t[:, 1]] - x0
    d2 = x[t[:, 2]] - x0
    d3 = x[t[:, 3]] - x0
    return np.einsum("ij,ij->i", d1, np.cross(d2, d3)) / 6.0


def tet4_shape_gradients(vertices, tets):
    """Rest volumes (m,) and shape-function gradients (m, 4, 3) of linear tets.

    Dm = [X1 - X0, X2 - X0, X3 - X0]; F = Ds Dm^-1 = sum_a x_a g_a^T with g_a = Dm^-T e_a
    (a = 1..3) and g_0 = -(g_1 + g_2 + g_3) (barycentric shape functions; Sifakis & Barbic,
    "FEM simulation of 3D deformable solids", SIGGRAPH 2012 course notes).
    """
    X = np.asarray(vertices, dtype=np.float64)[np.asarray(tets, dtype=np.int64)]  # (m, 4, 3)
    Dm = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)  # columns
    det = np.linalg.det(Dm)
    vol = det / 6.0
    bad = np.flatnonzero(~(vol > 0.0))
    if bad.size:
        raise ElementError(
            f"{bad.size} tet4 element(s) have non-positive rest volume (first: {bad[:5].tolist()})"
        )
    Dm_inv = np.linalg.inv(Dm)
    g = np.empty((len(X), 4, 3))
    g[:, 1:, :] = Dm_inv  # row a-1 of Dm^-1 is (Dm^-T e_a)^T
    g[:, 0, :] = -g[:, 1:, :].sum(axis=1)
    return vol, g


def barycentric(xi):
    """L (p, 4) and dL/dxi (4, 3) at reference points xi (p, 3)."""
    return np.stack([1.0 - xi.sum(axis=1), xi[:, 0], xi[:, 1], xi[:, 2]], axis=1), _DL


@register_element
class Tet4(SimplexElement):
    name = "tet4"
    nodes_per_element = 4
    meshio_cell = "tetra"
    reference_nodes = TET4_NODES
    lumping = "row-sum"
    rule_degree = {"stiffness": 1, "mass": 5}
    description = "linear tetrahedron, 4 nodes, 1 quadrature point"
    noun = "tet"

    def shape(self, xi):
        xi = as_points(xi)
        L, dL = barycentric(xi)
        return L, np.broadcast_to(dL, (len(xi), 4, 3)).copy()

    def box_mesh(self, *, size, cells, origin, name=None):
        from warpfem.mesh.box import box_tet_mesh  # mesh/ builds on element types: import at use

        return box_tet_mesh(size=size, cells=cells, origin=origin, name=name)

    def from_tet4(self, mesh, *, name=None):
        return mesh

    def _rule(self, purpose):
        if purpose == "stiffness":
            return np.full((1, 3), 0.25), np.array([1.0 / 6.0])
        return tet_conical_rule(3)

    # closed forms of the generic geometry (same results up to round-off, cheaper)
    def point_data(self, vertices, elements, purpose="stiffness"):
        if purpose != "stiffness":
            return super().point_data(vertices, elements, purpose)
        vol, g = tet4_shape_gradients(vertices, elements)
        return vol.astype(np.float64)[:, None], g[:, None]

    def signed_point_volumes(self, vertices, elements):
        return tet_volumes(vertices, elements)[:, None]

    def rest_volumes(self, vertices, elements):
        return tet_volumes(vertices, elements)

    def element_mass(self, vertices, elements, rho):
        m_e = rho * tet_volumes(vertices, elements) / 20.0
        return m_e[:, None, None] * (np.ones((4, 4)) + np.eye(4))[None]

    def lumped_element_mass(self, vertices, elements, rho, Me=None):
        m_e = rho * tet_volumes(vertices, elements) / 4.0
        return np.repeat(m_e, 4).reshape(-1, 4)
