"""Tet4: the linear tetrahedron. Nodes 0:(0,0,0) 1:(1,0,0) 2:(0,1,0) 3:(0,0,1) (meshio ``tetra``);
N = barycentric coordinates L = (1 - xi - eta - zeta, xi, eta, zeta). Stiffness: 1 point (the
centroid), exact for degree 1; mass: 27-point conical product (the Tet4 mass also has a closed form)."""

import numpy as np

from .base import SimplexElement, as_points, register_element, tet_conical_rule

TET4_NODES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
_DL = np.array([[-1.0, -1.0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])  # dL_i/dxi


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

    def shape(self, xi):
        xi = as_points(xi)
        L, dL = barycentric(xi)
        return L, np.broadcast_to(dL, (len(xi), 4, 3)).copy()

    def _rule(self, purpose):
        if purpose == "stiffness":
            return np.full((1, 3), 0.25), np.array([1.0 / 6.0])
        return tet_conical_rule(3)
