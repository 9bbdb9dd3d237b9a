"""Tet10: the quadratic tetrahedron. Corners as Tet4, then edge mid-nodes 4:(0,1) 5:(1,2) 6:(0,2)
7:(0,3) 8:(1,3) 9:(2,3) (meshio ``tetra10``); N_corner = L (2 L - 1), N_edge(a,b) = 4 L_a L_b.
Stiffness: 4 points, degree 2; mass: 27-point conical product (Gauss-Jacobi), degree 5; lumped
by HRZ (row sums of a quadratic element are negative at the corners)."""

import numpy as np

from .base import TET_FACES, SimplexElement, as_points, register_element, tet_conical_rule
from .tet4 import TET4_NODES, barycentric

TET10_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]], dtype=np.int64)
TET10_NODES = np.concatenate([TET4_NODES, 0.5 * (TET4_NODES[TET10_EDGES[:, 0]] + TET4_NODES[TET10_EDGES[:, 1]])])


@register_element
class Tet10(SimplexElement):
    name = "tet10"
    nodes_per_element = 10
    meshio_cell = "tetra10"
    reference_nodes = TET10_NODES
    lumping = "hrz"
    rule_degree = {"stiffness": 2, "mass": 5}
    description = "quadratic tetrahedron, 10 nodes, 4 quadrature points"

    def shape(self, xi):
        xi = as_points(xi)
        p = len(xi)
        L, dL = barycentric(xi)
        N = np.empty((p, 10))
        dN = np.empty((p, 10, 3))
        N[:, :4] = L * (2.0 * L - 1.0)
        dN[:, :4] = (4.0 * L - 1.0)[:, :, None] * dL[None]
        a, b = TET10_EDGES[:, 0], TET10_EDGES[:, 1]
        N[:, 4:] = 4.0 * L[:, a] * L[:, b]
        dN[:, 4:] = 4.0 * (L[:, a, None] * dL[None, b] + L[:, b, None] * dL[None, a])
        return N, dN

    def box_mesh(self, *, size, cells, origin, name=None):
        from warpfem.mesh.box import box_tet_mesh, tet10_from_tet4  # mesh/ builds on element types

        return tet10_from_tet4(box_tet_mesh(size=size, cells=cells, origin=origin), name=name)

    def from_tet4(self, mesh, *, name=None):
        from warpfem.mesh.box import tet10_from_tet4

        return tet10_from_tet4(mesh, name=name)

    def _rule(self, purpose):
        if purpose == "stiffness":
            a, b = 0.5854101966249685, 0.1381966011250105
            pts = np.array([[b, b, b], [a, b, b], [b, a, b], [b, b, a]])
            return pts, np.full(4, 1.0 / 24.0)
        return tet_conical_rule(3)

    def face_triangles(self):
        """Each face split into 4 triangles through its edge mid-nodes."""
        edge = {}
        for i, (a, b) in enumerate(TET10_EDGES):
            edge[(a, b)] = edge[(b, a)] = 4 + i
        out = []
        for a, b, c in TET_FACES:
            ab, bc, ca = edge[(a, b)], edge[(b, c)], edge[(c, a)]
            out.append((np.array([a, b, c]), np.array([(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)])))
        return out
