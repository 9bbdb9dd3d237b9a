"""The element-type interface and its registry.

An element type is one object (a subclass of :class:`ElementType`, one module per type in this
package) that knows everything the rest of the code asks about an element: its nodes (reference
coordinates, in meshio / VTK order), shape functions and their reference gradients, quadrature
rules per purpose, boundary faces (with a face quadrature rule, for tractions), how its mass is
lumped and how it splits into corner sub-tets (for point location and embedding). Adding an
element (say Tet20 or a prism) means one new module here that registers its object.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["ElementType", "ELEMENTS", "register_element", "get_element", "hex_gauss_rule", "tet_conical_rule",
           "TET_FACES", "HEX_FACES", "TRI_RULE"]

# tet faces, outward (a, b, c) of the corner nodes
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)
# hex faces: (axis, sign) -> in-plane axes (u, v) with e_u x e_v = sign e_axis (outward normal)
HEX_FACES = [(0, -1, 2, 1), (0, 1, 1, 2), (1, -1, 0, 2), (1, 1, 2, 0), (2, -1, 1, 0), (2, 1, 0, 1)]

# 6-point degree-4 rule on the reference triangle {s, t >= 0, s + t <= 1} (weights sum to 1/2)
_TRI_A, _TRI_B = 0.445948490915965, 0.091576213509771
TRI_RULE = (np.array([[_TRI_A, _TRI_A], [1 - 2 * _TRI_A, _TRI_A], [_TRI_A, 1 - 2 * _TRI_A],
                      [_TRI_B, _TRI_B], [1 - 2 * _TRI_B, _TRI_B], [_TRI_B, 1 - 2 * _TRI_B]]),
            0.5 * np.array([0.223381589678011] * 3 + [0.109951743655322] * 3))


def as_points(xi):
    xi = np.asarray(xi, dtype=np.float64)
    if xi.ndim == 1:
        xi = xi[None, :]
    if xi.ndim != 2 or xi.shape[1] != 3:
        raise ValueError(f"reference points must have shape (p, 3), got {xi.shape}")
    return xi


def hex_gauss_rule(n: int):
    """n x n x n Gauss-Legendre on [-1, 1]^3: points (n^3, 3), weights (n^3,) summing to 8."""
    x, w = np.polynomial.legendre.leggauss(n)
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


class ElementType:
    """One element type. Subclasses set the class attributes and implement :meth:`shape`.

    name: the scene / file name ("tet4", ...); nodes_per_element: k; meshio_cell: meshio's cell
    type; reference_nodes: (k, 3); reference_volume; corner_nodes: the local ids of the straight
    corners (4 for tets, 8 for hexes); corner_tets: (s, 4) local node ids of the sub-tets the element
    splits into (point location); lumping: "row-sum" or "hrz" (diagonal mass); rules: purpose ->
    (points, weights) provider; rule_degree: purpose -> the polynomial degree the rule is exact for
    (per variable on hexes); description: one line for docs and ``warpfem describe``.
    """

    name: str = ""
    nodes_per_element: int = 0
    meshio_cell: str = ""
    reference_nodes: np.ndarray = np.zeros((0, 3))
    reference_volume: float = 0.0
    corner_nodes: np.ndarray = np.zeros(0, dtype=np.int64)
    corner_tets: np.ndarray = np.zeros((0, 4), dtype=np.int64)
    lumping: str = "row-sum"
    rule_degree: dict = {}
    description: str = ""

    def __repr__(self) -> str:
        return f"<element type {self.name}>"

    # -- shape functions -------------------------------------------------------------------------
    def shape(self, xi) -> tuple[np.ndarray, np.ndarray]:
        """(N (p, k), dN/dxi (p, k, 3)) at reference points xi (p, 3)."""
        raise NotImplementedError

    def shape_functions(self, xi) -> np.ndarray:
        return self.shape(xi)[0]

    def shape_gradients(self, xi) -> np.ndarray:
        return self.shape(xi)[1]

    # -- quadrature --------------------------------------------------------------------------------
    def rule(self, purpose: str = "stiffness"):
        """Reference points (q, 3) and weights (q,) of the rule used for ``purpose``: "stiffness"
        (the element's integration rule), "mass" (exact for N_a N_b on affine elements) or
        "volumetric" (the 1-point rule of selective reduced integration, where provided)."""
        if purpose not in ("stiffness", "mass", "volumetric"):
            raise ValueError(f"purpose must be 'stiffness', 'mass' or 'volumetric', got {purpose!r}")
        if (purpose) not in self.rule_degree:
            raise ValueError(f"the 1-point volumetric rule is only provided for hex8, not {self.name!r}")
        return self._rule(purpose)

    def _rule(self, purpose: str):
        raise NotImplementedError

    @property
    def points_per_element(self) -> int:
        return len(self.rule("stiffness")[1])

    # -- faces -------------------------------------------------------------------------------------
    def faces(self) -> list:
        """Per local face: (face node ids, corner ids, reference origin (3,), tangents (2, 3), rule
        points (g, 2), rule weights (g,)), with xi(s, t) = origin + s T0 + t T1 and T0 x T1 pointing
        out of the element."""
        raise NotImplementedError


class SimplexElement(ElementType):
    """Tetrahedra on the reference tet {xi >= 0, sum xi <= 1}."""

    reference_volume = 1.0 / 6.0
    corner_nodes = np.arange(4, dtype=np.int64)
    corner_tets = np.array([[0, 1, 2, 3]], dtype=np.int64)

    def faces(self) -> list:
        nodes = self.reference_nodes
        P = nodes[:4]
        lam = np.concatenate([1.0 - nodes.sum(axis=1, keepdims=True), nodes], axis=1)  # barycentric of each node
        out = []
        for a, b, c in TET_FACES:
            d = ({0, 1, 2, 3} - {int(a), int(b), int(c)}).pop()
            on = np.flatnonzero(np.abs(lam[:, d]) < 1e-12)
            out.append((on, np.array([a, b, c]), P[a], np.stack([P[b] - P[a], P[c] - P[a]]), *TRI_RULE))
        return out


class HexElement(ElementType):
    """Hexahedra on the reference cube [-1, 1]^3."""

    reference_volume = 8.0
    corner_nodes = np.arange(8, dtype=np.int64)
    # the 6 tets around the 0-6 diagonal (the box mesher's split, conforming across cells)
    corner_tets = np.array([[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]],
                           dtype=np.int64)

    def faces(self) -> list:
        nodes = self.reference_nodes
        g = np.array([-math.sqrt(0.6), 0.0, math.sqrt(0.6)])
        w = np.array([5.0, 8.0, 5.0]) / 9.0
        pts = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
        wts = np.outer(w, w).ravel()
        out = []
        for axis, sign, u, v in HEX_FACES:
            on = np.flatnonzero(np.abs(nodes[:, axis] - sign) < 1e-12)
            corners = on[np.all(np.abs(np.abs(nodes[on]) - 1.0) < 1e-12, axis=1)]
            origin = np.zeros(3)
            origin[axis] = sign
            T = np.zeros((2, 3))
            T[0, u] = T[1, v] = 1.0
            out.append((on, corners, origin, T, pts, wts))
        return out


#: name -> element type object, in registration order
ELEMENTS: dict[str, ElementType] = {}


def register_element(cls):
    """Class decorator: register one instance of an element type under ``cls.name``."""
    if cls.name in ELEMENTS:
        raise ValueError(f"element type {cls.name!r} is already registered")
    ELEMENTS[cls.name] = cls()
    return cls


def get_element(element_type) -> ElementType:
    """The element type object for a name (or the object itself); ValueError naming the known ones."""
    if isinstance(element_type, ElementType):
        return element_type
    try:
        return ELEMENTS[element_type]
    except (KeyError, TypeError):
        raise ValueError(f"unknown element type {element_type!r}; supported: {', '.join(ELEMENTS)}") from None
