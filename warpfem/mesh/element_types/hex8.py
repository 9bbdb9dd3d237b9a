"""Hex8: the trilinear hexahedron on [-1, 1]^3. Corners 0:(-,-,-) 1:(+,-,-) 2:(+,+,-) 3:(-,+,-)
4:(-,-,+) 5:(+,-,+) 6:(+,+,+) 7:(-,+,+) (meshio ``hexahedron``); N = prod (1 + xi_i r_i) / 8.
Stiffness and mass: 2x2x2 Gauss-Legendre (degree 3 per variable); ``"volumetric"``: the 1-point
rule of selective reduced integration (Hughes, "The Finite Element Method", ch. 4)."""

import numpy as np

from .base import HexElement, as_points, hex_gauss_rule, register_element

HEX8_NODES = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                       [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64)


@register_element
class Hex8(HexElement):
    name = "hex8"
    nodes_per_element = 8
    meshio_cell = "hexahedron"
    reference_nodes = HEX8_NODES
    lumping = "row-sum"
    rule_degree = {"stiffness": 3, "volumetric": 1, "mass": 3}
    description = "trilinear hexahedron, 8 nodes, 2x2x2 quadrature points"

    def box_mesh(self, *, size, cells, origin, name=None):
        from warpfem.mesh.box import box_hex_mesh  # mesh/ builds on element types: import at use

        return box_hex_mesh(size=size, cells=cells, origin=origin, order=1, name=name)

    def shape(self, xi):
        xi = as_points(xi)
        p = len(xi)
        nodes = self.reference_nodes
        f = 1.0 + xi[:, None, :] * nodes[None, :, :]  # (p, 8, 3)
        N = 0.125 * f.prod(axis=2)
        dN = np.empty((p, 8, 3))
        dN[..., 0] = 0.125 * nodes[None, :, 0] * f[..., 1] * f[..., 2]
        dN[..., 1] = 0.125 * nodes[None, :, 1] * f[..., 0] * f[..., 2]
        dN[..., 2] = 0.125 * nodes[None, :, 2] * f[..., 0] * f[..., 1]
        return N, dN

    def _rule(self, purpose):
        if purpose == "volumetric":
            return np.zeros((1, 3)), np.array([8.0])
        return hex_gauss_rule(2)
