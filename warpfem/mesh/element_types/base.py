"""The element-type interface and its registry.

An element type is one object (a subclass of :class:`ElementType`, one module per type in this
package) that knows everything the rest of the code asks about an element: its nodes (reference
coordinates, in meshio / VTK order), shape functions and their reference gradients, quadrature
rules per purpose, boundary faces (with a face quadrature rule, for tractions), how its mass is
lumped and how it splits into corner sub-tets (for point location and embedding), and the
geometry every mesh of it needs: the isoparametric map at reference points (det J, dN/dX), signed
volumes for validation, the mirror image used to reorient inverted elements, element mass
matrices and their lumping, and the triangles of its faces. ``warpfem.mesh.VolumeMesh``, the mass
module (``warpfem.mesh.mass``), the quadrature precompute (``warpfem.elements``) and the model ask the
element object and never switch on its name. Adding an element (say Tet20 or a prism) means one new
module here that registers its object, plus its name in the import line of ``__init__.py``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["ElementType", "ElementError", "ELEMENTS", "register_element", "get_element", "hex_gauss_rule",
           "tet_conical_rule", "TET_FACES", "HEX_FACES", "TRI_RULE", "shape_functions", "shape_gradients", "gauss_rule",
           "element_point_data"]


class ElementError(ValueError):
    """An element whose rest configuration cannot be integrated (det J <= 0 at a point)."""


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
    #: what messages call one element ("tet" for Tet4: "tet 3 repeats a vertex")
    noun: str = ""

    def __init__(self):
        if not self.noun:
            self.noun = f"{self.name} element"

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
            with_rule = [n for n, e in ELEMENTS.items() if purpose in e.rule_degree]
            raise ValueError(f"the {purpose!r} rule is only provided for {', '.join(with_rule) or 'no element type'}, "
                             f"not {self.name!r}")
        return self._rule(purpose)

    def _rule(self, purpose: str):
        raise NotImplementedError

    @property
    def points_per_element(self) -> int:
        return len(self.rule("stiffness")[1])

    @property
    def has_reduced_volumetric_rule(self) -> bool:
        """True when the type provides the 1-point "volumetric" rule of selective reduced integration."""
        return "volumetric" in self.rule_degree

    # -- meshes a scene can ask for (None: this type has no such mesh) --------------------------
    def box_mesh(self, *, size, cells, origin, name=None):
        """A mesh of this type filling ``origin + [0, size]`` with ``cells`` grid cells, or None
        where the type has no box generator (``[mesh] generator = "box"`` then names the types that do)."""
        return None

    def from_tet4(self, mesh, *, name=None):
        """This type made from a Tet4 mesh (a tet file, a tetrahedralised surface), or None where a
        tet mesh cannot become this type (a file with this type's own cells is then needed)."""
        return None

    @property
    def has_box_mesh(self) -> bool:
        return type(self).box_mesh is not ElementType.box_mesh

    @property
    def has_from_tet4(self) -> bool:
        return type(self).from_tet4 is not ElementType.from_tet4

    @property
    def is_linear_tet(self) -> bool:
        """True when the element is its own single corner tet (4 nodes, shape functions = barycentric
        coordinates): point location and surface loads then take the plain tet paths."""
        return self.nodes_per_element == 4 and len(self.corner_tets) == 1

    # -- faces -------------------------------------------------------------------------------------
    def faces(self) -> list:
        """Per local face: (face node ids, corner ids, reference origin (3,), tangents (2, 3), rule
        points (g, 2), rule weights (g,)), with xi(s, t) = origin + s T0 + t T1 and T0 x T1 pointing
        out of the element."""
        raise NotImplementedError

    def face_triangles(self) -> list:
        """Per local face: (corner node ids (c,), outward triangles (t, 3) over local node ids) that
        cover the face through all its nodes (a boundary surface that follows every node)."""
        raise NotImplementedError

    # -- orientation -------------------------------------------------------------------------------
    def reflect(self, xi) -> np.ndarray:
        """A mirror map of the reference element onto itself (reverses orientation)."""
        raise NotImplementedError

    @property
    def mirror_permutation(self) -> np.ndarray:
        """(k,) local node order of the mirror image: ``elements[:, perm]`` turns an element with
        det J < 0 everywhere into one with det J > 0 (the same nodes, reoriented)."""
        nodes = self.reference_nodes
        image = self.reflect(nodes)
        d = np.linalg.norm(image[:, None, :] - nodes[None, :, :], axis=2)
        perm = d.argmin(axis=1)
        if not np.allclose(d[np.arange(len(nodes)), perm], 0.0) or len(set(perm.tolist())) != len(nodes):
            raise ValueError(f"{self.name}: reflect() does not map the reference nodes onto each other")
        return perm

    # -- geometry of a mesh of this element ----------------------------------------------------------
    def point_data_at(self, vertices, elements, points):
        """Isoparametric map at reference points for every element: det J (m, q) and material
        gradients dN/dX (m, q, k, 3), where J = dX/dxi = sum_a X_a (dN_a/dxi)^T and dN/dX = J^-T dN/dxi.
        Raises :class:`ElementError` naming the elements whose det J is not positive at some point."""
        dNdxi = self.shape_gradients(points)  # (q, k, 3)
        X = np.asarray(vertices, dtype=np.float64)[np.asarray(elements, dtype=np.int64)]  # (m, k, 3)
        J = np.einsum("mai,qaj->mqij", X, dNdxi)  # (m, q, 3, 3)
        det = np.linalg.det(J)
        bad = np.flatnonzero(~(det > 0.0).all(axis=1))
        if bad.size:
            raise ElementError(
                f"{bad.size} {self.name} element(s) have det J <= 0 at a quadrature point (inverted or "
                f"degenerate rest shape, or wrong node order); first: {bad[:10].tolist()}, "
                f"min det J {float(det[bad[0]].min()):.3g} in element {int(bad[0])}")
        Jinv = np.linalg.inv(J)
        dNdX = np.einsum("qaj,mqji->mqai", dNdxi, Jinv)  # dN/dX_i = sum_j dN/dxi_j dxi_j/dX_i
        return det, dNdX

    def point_data(self, vertices, elements, purpose: str = "stiffness"):
        """(weights (m, q) = Gauss weight x det J, the volume each point represents; dN/dX (m, q, k, 3))
        with the rule of ``purpose``; :class:`ElementError` for det J <= 0."""
        pts, w = self.rule(purpose)
        det, dNdX = self.point_data_at(vertices, elements, pts)
        return det * w[None, :], dNdX

    def signed_point_volumes(self, vertices, elements) -> np.ndarray:
        """(m, q) det J x reference volume at the stiffness points (the volume the element would have
        with that Jacobian everywhere; equal to its volume for affine elements), any sign: for validation."""
        pts, _ = self.rule("stiffness")
        X = np.asarray(vertices, dtype=np.float64)[np.asarray(elements, dtype=np.int64)]
        J = np.einsum("mai,qaj->mqij", X, self.shape_gradients(pts))
        return np.linalg.det(J) * self.reference_volume

    def rest_volumes(self, vertices, elements) -> np.ndarray:
        """(m,) element volumes sum_q w_q det J_q (exact for affine elements)."""
        w, _ = self.point_data(vertices, elements, "stiffness")
        return w.sum(axis=1)

    # -- mass ----------------------------------------------------------------------------------------
    def element_mass(self, vertices, elements, rho) -> np.ndarray:
        """Consistent element mass matrices (m, k, k), kg: rho_e sum_q w_q det J_q N_a N_b with the
        "mass" rule (exact for affine elements); ``rho`` (m,) per element."""
        pts, w = self.rule("mass")
        det, _ = self.point_data_at(vertices, elements, pts)
        N = self.shape_functions(pts)  # (q, k)
        return np.einsum("m,mq,qa,qb->mab", rho, det * w[None, :], N, N)

    def lump(self, Me) -> np.ndarray:
        """Diagonal (lumped) masses (m, k) from element matrices (m, k, k) by the type's ``lumping``:
        "row-sum", or "hrz" (Hinton, Rock & Zienkiewicz 1976, "A note on mass lumping and related
        processes in the finite element method": the diagonal scaled to the element mass, always > 0)."""
        if self.lumping == "row-sum":
            return Me.sum(axis=2)
        d = np.einsum("maa->ma", Me)
        return d * (Me.sum(axis=(1, 2)) / d.sum(axis=1))[:, None]

    def lumped_element_mass(self, vertices, elements, rho, Me=None) -> np.ndarray:
        """(m, k) lumped nodal masses of each element, kg (``Me``: the element matrices, when the
        caller has them already)."""
        return self.lump(self.element_mass(vertices, elements, rho) if Me is None else Me)


class SimplexElement(ElementType):
    """Tetrahedra on the reference tet {xi >= 0, sum xi <= 1}."""

    reference_volume = 1.0 / 6.0
    corner_nodes = np.arange(4, dtype=np.int64)
    corner_tets = np.array([[0, 1, 2, 3]], dtype=np.int64)

    def reflect(self, xi):
        """Swap eta and zeta (corners 2 and 3)."""
        return as_points(xi)[:, [0, 2, 1]]

    def face_triangles(self) -> list:
        """Straight faces: each face is its corner triangle (quadratic tets override this)."""
        return [(np.asarray(f), np.asarray(f)[None, :]) for f in TET_FACES]

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

    def reflect(self, xi):
        """zeta -> -zeta (bottom and top faces swap)."""
        return as_points(xi) * np.array([1.0, 1.0, -1.0])

    def face_triangles(self) -> list:
        """Each face's grid of nodes (2 x 2 for Hex8, 3 x 3 for Hex27, read off the reference nodes)
        split into outward triangles."""
        nodes = self.reference_nodes
        lookup = {tuple(np.rint(4 * p).astype(int)): i for i, p in enumerate(nodes)}
        levels = np.unique(nodes[:, 0])
        out = []
        for axis, sign, u, v in HEX_FACES:
            def node(a, b):
                c = np.zeros(3)
                c[axis], c[u], c[v] = sign, a, b
                return lookup[tuple(np.rint(4 * c).astype(int))]

            corners = [node(-1, -1), node(1, -1), node(1, 1), node(-1, 1)]
            tris = []
            for i in range(len(levels) - 1):
                for j in range(len(levels) - 1):
                    a, b = node(levels[i], levels[j]), node(levels[i + 1], levels[j])
                    c, d = node(levels[i + 1], levels[j + 1]), node(levels[i], levels[j + 1])
                    tris += [(a, b, c), (a, c, d)]
            out.append((np.array(corners), np.array(tris)))
        return out

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


# -- name-based conveniences (for callers holding a name; each asks the element object) ---------------
def shape_functions(element_type, xi) -> np.ndarray:
    """Shape functions N_a(xi) at reference points xi (p, 3) -> (p, k)."""
    return get_element(element_type).shape(xi)[0]


def shape_gradients(element_type, xi) -> np.ndarray:
    """Reference gradients dN_a/dxi at reference points xi (p, 3) -> (p, k, 3)."""
    return get_element(element_type).shape(xi)[1]


def gauss_rule(element_type, purpose: str = "stiffness"):
    """Reference points (q, 3) and weights (q,) of the element type's rule for ``purpose``."""
    return get_element(element_type).rule(purpose)


def element_point_data(vertices, elements, element_type, points):
    """det J (m, q) and dN/dX (m, q, k, 3) at reference points (:meth:`ElementType.point_data_at`)."""
    return get_element(element_type).point_data_at(vertices, elements, points)
