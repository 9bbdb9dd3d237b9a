"""Element library: Lagrange shape functions, reference gradients and Gauss rules.

Element types (``ELEMENT_TYPES``) and node ordering (the VTK ordering meshio uses for
``tetra``, ``tetra10``, ``hexahedron`` and ``hexahedron27`` cells):

* ``tet4``  reference tet {xi >= 0, sum xi <= 1}; nodes 0:(0,0,0) 1:(1,0,0) 2:(0,1,0) 3:(0,0,1).
* ``tet10`` corners as tet4, then edge mid-nodes 4:(0,1) 5:(1,2) 6:(0,2) 7:(0,3) 8:(1,3) 9:(2,3).
  N_corner = L (2 L - 1), N_edge(a,b) = 4 L_a L_b with L = (1 - xi - eta - zeta, xi, eta, zeta).
* ``hex8``  reference cube [-1, 1]^3; corners 0:(-,-,-) 1:(+,-,-) 2:(+,+,-) 3:(-,+,-) 4:(-,-,+)
  5:(+,-,+) 6:(+,+,+) 7:(-,+,+); trilinear N = prod (1 + xi_i r_i) / 8.
* ``hex27`` corners as hex8; edge mid-nodes 8:(0,1) 9:(1,2) 10:(2,3) 11:(3,0) 12:(4,5) 13:(5,6)
  14:(6,7) 15:(7,4) 16:(0,4) 17:(1,5) 18:(2,6) 19:(3,7); face centres 20:-x 21:+x 22:-y 23:+y
  24:-z 25:+z; 26: centre. Triquadratic N = prod_i L_{r_i}(xi_i), L the 1D quadratic Lagrange
  polynomials on the nodes -1, 0, 1.

Gauss rules (``gauss_rule(element_type, purpose)``), weights sum to the reference volume
(1/6 for tets, 8 for hexes):

* tet4: 1 point (centroid), degree 1 (stiffness and mass: the Tet4 mass uses the closed form).
* tet10: 4 points, degree 2 (stiffness); mass: 27-point conical product (Gauss-Jacobi), degree 5.
* hex8: 2x2x2 Gauss-Legendre, exact for degree <= 3 in each variable; ``"volumetric"``: 1 point.
* hex27: 3x3x3 Gauss-Legendre, exact for degree <= 5 in each variable.
"""

from __future__ import annotations

import numpy as np

ELEMENT_TYPES = ("tet4", "tet10", "hex8", "hex27")
NODES_PER_ELEMENT = {"tet4": 4, "tet10": 10, "hex8": 8, "hex27": 27}
#: meshio cell type of each element type
MESHIO_CELL_TYPE = {"tet4": "tetra", "tet10": "tetra10", "hex8": "hexahedron", "hex27": "hexahedron27"}
#: polynomial degree of the stated exactness of each rule (per variable for hexes)
RULE_DEGREE = {("tet4", "stiffness"): 1, ("tet10", "stiffness"): 2, ("tet10", "mass"): 5,
               ("hex8", "stiffness"): 3, ("hex8", "volumetric"): 1, ("hex27", "stiffness"): 5,
               ("tet4", "mass"): 5, ("hex8", "mass"): 3, ("hex27", "mass"): 5}

TET10_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]], dtype=np.int64)

HEX8_NODES = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                       [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64)
HEX27_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                        [0, 4], [1, 5], [2, 6], [3, 7]], dtype=np.int64)
_HEX27_FACES = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.float64)
HEX27_NODES = np.concatenate([HEX8_NODES, 0.5 * (HEX8_NODES[HEX27_EDGES[:, 0]] + HEX8_NODES[HEX27_EDGES[:, 1]]),
                              _HEX27_FACES, np.zeros((1, 3))])
TET4_NODES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
TET10_NODES = np.concatenate([TET4_NODES, 0.5 * (TET4_NODES[TET10_EDGES[:, 0]] + TET4_NODES[TET10_EDGES[:, 1]])])

#: reference coordinates of the nodes of each element type, (k, 3)
REFERENCE_NODES = {"tet4": TET4_NODES, "tet10": TET10_NODES, "hex8": HEX8_NODES, "hex27": HEX27_NODES}
#: reference volume
REFERENCE_VOLUME = {"tet4": 1.0 / 6.0, "tet10": 1.0 / 6.0, "hex8": 8.0, "hex27": 8.0}


def check_element_type(element_type: str) -> str:
    if element_type not in ELEMENT_TYPES:
        raise ValueError(f"unknown element type {element_type!r}; supported: {', '.join(ELEMENT_TYPES)}")
    return element_type


def _as_points(xi):
    xi = np.asarray(xi, dtype=np.float64)
    if xi.ndim == 1:
        xi = xi[None, :]
    if xi.ndim != 2 or xi.shape[1] != 3:
        raise ValueError(f"reference points must have shape (p, 3), got {xi.shape}")
    return xi


def _lagrange2(t):
    """1D quadratic Lagrange polynomials on -1, 0, 1 and their derivatives; t (p,) -> (p, 3) each
    with columns for the nodes (-1, 0, 1)."""
    L = np.stack([0.5 * t * (t - 1.0), 1.0 - t * t, 0.5 * t * (t + 1.0)], axis=1)
    dL = np.stack([t - 0.5, -2.0 * t, t + 0.5], axis=1)
    return L, dL


def shape_functions(element_type: str, xi) -> np.ndarray:
    """Shape functions N_a(xi) at reference points xi (p, 3) -> (p, k)."""
    return _shape(element_type, xi)[0]


def shape_gradients(element_type: str, xi) -> np.ndarray:
    """Reference gradients dN_a/dxi at reference points xi (p, 3) -> (p, k, 3)."""
    return _shape(element_type, xi)[1]


def _shape(element_type, xi):
    check_element_type(element_type)
    xi = _as_points(xi)
    p = len(xi)
    if element_type in ("tet4", "tet10"):
        L = np.stack([1.0 - xi.sum(axis=1), xi[:, 0], xi[:, 1], xi[:, 2]], axis=1)  # (p, 4)
        dL = np.array([[-1.0, -1.0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])  # dL_i/dxi
        if element_type == "tet4":
            return L, np.broadcast_to(dL, (p, 4, 3)).copy()
        N = np.empty((p, 10))
        dN = np.empty((p, 10, 3))
        N[:, :4] = L * (2.0 * L - 1.0)
        dN[:, :4] = (4.0 * L - 1.0)[:, :, None] * dL[None]
        a, b = TET10_EDGES[:, 0], TET10_EDGES[:, 1]
        N[:, 4:] = 4.0 * L[:, a] * L[:, b]
        dN[:, 4:] = 4.0 * (L[:, a, None] * dL[None, b] + L[:, b, None] * dL[None, a])
        return N, dN
    nodes = REFERENCE_NODES[element_type]
    if element_type == "hex8":
        f = 1.0 + xi[:, None, :] * nodes[None, :, :]  # (p, 8, 3)
        N = 0.125 * f.prod(axis=2)
        dN = np.empty((p, 8, 3))
        dN[..., 0] = 0.125 * nodes[None, :, 0] * f[..., 1] * f[..., 2]
        dN[..., 1] = 0.125 * nodes[None, :, 1] * f[..., 0] * f[..., 2]
        dN[..., 2] = 0.125 * nodes[None, :, 2] * f[..., 0] * f[..., 1]
        return N, dN
    # hex27: tensor product of 1D quadratics
    col = (nodes + 1).astype(np.int64)  # (27, 3) in {0, 1, 2}
    Ls, dLs = zip(*(_lagrange2(xi[:, d]) for d in range(3)))
    f = np.stack([Ls[d][:, col[:, d]] for d in range(3)], axis=2)  # (p, 27, 3)
    df = np.stack([dLs[d][:, col[:, d]] for d in range(3)], axis=2)
    N = f.prod(axis=2)
    dN = np.stack([df[..., 0] * f[..., 1] * f[..., 2], f[..., 0] * df[..., 1] * f[..., 2],
                   f[..., 0] * f[..., 1] * df[..., 2]], axis=2)
    return N, dN


def _gauss_line(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return x, w


def hex_gauss_rule(n: int):
    """n x n x n Gauss-Legendre on [-1, 1]^3: points (n^3, 3), weights (n^3,) summing to 8."""
    x, w = _gauss_line(n)
    X = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1).reshape(-1, 3)
    W = np.einsum("i,j,k->ijk", w, w, w).reshape(-1)
    return X, W


def tet_conical_rule(n: int):
    """Conical-product (Stroud) rule on the reference tet with n^3 points, exact for degree 2n-1,
    all weights positive (sum 1/6). Collapsed coordinates x = u, y = v (1 - u), z = w (1 - u)(1 - v)
    with Gauss-Jacobi points for the weights (1 - u)^2 and (1 - v)."""
    from scipy.special import roots_jacobi

    tu, wu = roots_jacobi(n, 2.0, 0.0)
    tv, wv = roots_jacobi(n, 1.0, 0.0)
    tw, ww = roots_jacobi(n, 0.0, 0.0)
    u, v, w = (tu + 1) / 2, (tv + 1) / 2, (tw + 1) / 2
    wu, wv, ww = wu / 8.0, wv / 4.0, ww / 2.0  # map [-1,1] -> [0,1] with the Jacobi weights
    U, V, Wc = np.meshgrid(u, v, w, indexing="ij")
    weights = np.einsum("i,j,k->ijk", wu, wv, ww).reshape(-1)
    U, V, Wc = U.reshape(-1), V.reshape(-1), Wc.reshape(-1)
    pts = np.stack([U, V * (1 - U), Wc * (1 - U) * (1 - V)], axis=1)
    return pts, weights


def gauss_rule(element_type: str, purpose: str = "stiffness"):
    """Reference points (q, 3) and weights (q,) of the rule used for ``purpose``:
    "stiffness" (the element's integration rule), "mass" (exact for N_a N_b on affine elements) or
    "volumetric" (hex8 only: the 1-point rule of selective reduced integration)."""
    check_element_type(element_type)
    if purpose not in ("stiffness", "mass", "volumetric"):
        raise ValueError(f"purpose must be 'stiffness', 'mass' or 'volumetric', got {purpose!r}")
    if purpose == "volumetric":
        if element_type != "hex8":
            raise ValueError(f"the 1-point volumetric rule is only provided for hex8, not {element_type!r}")
        return np.zeros((1, 3)), np.array([8.0])
    if element_type == "tet4" and purpose == "stiffness":
        return np.full((1, 3), 0.25), np.array([1.0 / 6.0])
    if element_type == "tet10" and purpose == "stiffness":
        a, b = 0.5854101966249685, 0.1381966011250105
        pts = np.array([[b, b, b], [a, b, b], [b, a, b], [b, b, a]])
        return pts, np.full(4, 1.0 / 24.0)
    if element_type in ("tet4", "tet10"):
        return tet_conical_rule(3)
    if element_type == "hex8":
        return hex_gauss_rule(2)
    return hex_gauss_rule(3)
