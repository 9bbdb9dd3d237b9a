"""Hex27: the triquadratic hexahedron on [-1, 1]^3. Corners as Hex8; edge mid-nodes 8:(0,1) 9:(1,2)
10:(2,3) 11:(3,0) 12:(4,5) 13:(5,6) 14:(6,7) 15:(7,4) 16:(0,4) 17:(1,5) 18:(2,6) 19:(3,7); face
centres 20:-x 21:+x 22:-y 23:+y 24:-z 25:+z; 26: centre (meshio ``hexahedron27``). N = prod_i
L_{r_i}(xi_i), L the 1D quadratic Lagrange polynomials on -1, 0, 1. Stiffness and mass: 3x3x3
Gauss-Legendre (degree 5 per variable); lumped by HRZ."""

import numpy as np

from .base import HexElement, as_points, hex_gauss_rule, register_element
from .hex8 import HEX8_NODES

HEX27_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                        [0, 4], [1, 5], [2, 6], [3, 7]], dtype=np.int64)
_HEX27_FACES = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.float64)
HEX27_NODES = np.concatenate([HEX8_NODES, 0.5 * (HEX8_NODES[HEX27_EDGES[:, 0]] + HEX8_NODES[HEX27_EDGES[:, 1]]),
                              _HEX27_FACES, np.zeros((1, 3))])


def lagrange2(t):
    """1D quadratic Lagrange polynomials on -1, 0, 1 and their derivatives; t (p,) -> (p, 3) each
    with columns for the nodes (-1, 0, 1)."""
    L = np.stack([0.5 * t * (t - 1.0), 1.0 - t * t, 0.5 * t * (t + 1.0)], axis=1)
    dL = np.stack([t - 0.5, -2.0 * t, t + 0.5], axis=1)
    return L, dL


@register_element
class Hex27(HexElement):
    name = "hex27"
    nodes_per_element = 27
    meshio_cell = "hexahedron27"
    reference_nodes = HEX27_NODES
    lumping = "hrz"
    rule_degree = {"stiffness": 5, "mass": 5}
    description = "triquadratic hexahedron, 27 nodes, 3x3x3 quadrature points"

    def box_mesh(self, *, size, cells, origin, name=None):
        from warpfem.mesh.box import box_hex_mesh  # mesh/ builds on element types: import at use

        return box_hex_mesh(size=size, cells=cells, origin=origin, order=2, name=name)

    def shape(self, xi):
        xi = as_points(xi)
        col = (self.reference_nodes + 1).astype(np.int64)  # (27, 3) in {0, 1, 2}
        Ls, dLs = zip(*(lagrange2(xi[:, d]) for d in range(3)))
        f = np.stack([Ls[d][:, col[:, d]] for d in range(3)], axis=2)  # (p, 27, 3)
        df = np.stack([dLs[d][:, col[:, d]] for d in range(3)], axis=2)
        N = f.prod(axis=2)
        dN = np.stack([df[..., 0] * f[..., 1] * f[..., 2], f[..., 0] * df[..., 1] * f[..., 2],
                       f[..., 0] * f[..., 1] * df[..., 2]], axis=2)
        return N, dN

    def _rule(self, purpose):
        return hex_gauss_rule(3)
