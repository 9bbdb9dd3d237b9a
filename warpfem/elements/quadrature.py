"""Per-quadrature-point precompute (rest-state data) for the element kernels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .library import ELEMENT_TYPES, gauss_rule, shape_gradients

SUPPORTED_ELEMENTS = ELEMENT_TYPES
VOLUMETRIC_INTEGRATION = ("full", "reduced")


class ElementError(ValueError):
    """An element whose rest configuration cannot be integrated (det J <= 0 at a point)."""


@dataclass(frozen=True)
class QuadratureData:
    """Flat rest-state data for the quadrature-point kernels.

    Attributes:
        element_type: name of the element type ("tet4", ...).
        nodes_per_element: k, the stride of ``elements``.
        elements: (m * k,) int32 flat connectivity.
        qp_element: (Q,) int32 element of each quadrature point.
        qp_weight: (Q,) float64 Gauss weight x det J (m^3).
        qp_dNdX: (Q * k, 3) float64 material shape-function gradients (1/m).
        volumetric: optional second point set (selective reduced integration, hex8): one point per
            element with weight V_e (the element volume) and the volume-averaged ("uniform",
            Flanagan & Belytschko 1981) gradients (1/V_e) int_e dN_a/dX dV, integrated exactly by
            the 2x2x2 rule; the kernels run the volumetric part of the material
            (``Material.volumetric_split``) over this set and the rest over the main set.
            None for ordinary (full) integration.
    """

    element_type: str
    nodes_per_element: int
    elements: np.ndarray
    qp_element: np.ndarray
    qp_weight: np.ndarray
    qp_dNdX: np.ndarray
    volumetric: "QuadratureData | None" = None

    @property
    def num_elements(self) -> int:
        return len(self.elements) // self.nodes_per_element

    @property
    def num_points(self) -> int:
        return len(self.qp_element)


def tet4_shape_gradients(vertices: np.ndarray, tets: np.ndarray):
    """Rest volumes (m,) and shape-function gradients (m, 4, 3) of linear tets.

    Dm = [X1 - X0, X2 - X0, X3 - X0]; F = Ds Dm^-1 = sum_a x_a g_a^T with g_a = Dm^-T e_a
    (a = 1..3) and g_0 = -(g_1 + g_2 + g_3) (barycentric shape functions; Sifakis & Barbič,
    "FEM simulation of 3D deformable solids", SIGGRAPH 2012 course notes).
    """
    X = vertices[tets]  # (m, 4, 3)
    Dm = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)  # columns
    det = np.linalg.det(Dm)
    vol = det / 6.0
    bad = np.flatnonzero(~(vol > 0.0))
    if bad.size:
        raise ElementError(
            f"{bad.size} tet4 element(s) have non-positive rest volume (first: {bad[:5].tolist()})"
        )
    Dm_inv = np.linalg.inv(Dm)
    g = np.empty((len(tets), 4, 3))
    g[:, 1:, :] = Dm_inv  # row a-1 of Dm^-1 is (Dm^-T e_a)^T
    g[:, 0, :] = -g[:, 1:, :].sum(axis=1)
    return vol, g


def element_point_data(vertices: np.ndarray, elements: np.ndarray, element_type: str, points: np.ndarray):
    """Isoparametric map at reference points for every element.

    Returns det J (m, q) and material gradients dN/dX (m, q, k, 3), where J = dX/dxi =
    sum_a X_a (dN_a/dxi)^T and dN/dX = J^-T dN/dxi. Raises :class:`ElementError` naming the
    elements whose det J is not positive at some point.
    """
    dNdxi = shape_gradients(element_type, points)  # (q, k, 3)
    X = vertices[elements]  # (m, k, 3)
    J = np.einsum("mai,qaj->mqij", X, dNdxi)  # (m, q, 3, 3)
    det = np.linalg.det(J)
    bad = np.flatnonzero(~(det > 0.0).all(axis=1))
    if bad.size:
        raise ElementError(
            f"{bad.size} {element_type} element(s) have det J <= 0 at a quadrature point (inverted or "
            f"degenerate rest shape, or wrong node order); first: {bad[:10].tolist()}, "
            f"min det J {float(det[bad[0]].min()):.3g} in element {int(bad[0])}")
    Jinv = np.linalg.inv(J)
    dNdX = np.einsum("qaj,mqji->mqai", dNdxi, Jinv)  # dN/dX_i = sum_j dN/dxi_j dxi_j/dX_i
    return det, dNdX


def _generic_quadrature(vertices, elements, element_type, purpose):
    pts, w = gauss_rule(element_type, purpose)
    det, dNdX = element_point_data(vertices, elements, element_type, pts)
    m, q = det.shape
    k = elements.shape[1]
    return QuadratureData(
        element_type=element_type,
        nodes_per_element=k,
        elements=np.ascontiguousarray(elements.reshape(-1), dtype=np.int32),
        qp_element=np.repeat(np.arange(m, dtype=np.int32), q),
        qp_weight=np.ascontiguousarray((det * w[None, :]).reshape(-1)),
        qp_dNdX=np.ascontiguousarray(dNdX.reshape(-1, 3)),
    )


def mean_gradient_quadrature(qd: QuadratureData) -> QuadratureData:
    """One point per element: weight V_e = sum_q w_q and gradient g_a = (1/V_e) sum_q w_q dN_a/dX(q).

    F there is the element's volume-averaged deformation gradient, so the volumetric energy is
    psi_vol(mean F) V_e: for linear elasticity the mean-dilatation / B-bar element (Nagtegaal,
    Parks, Rice 1974; Hughes 1980). Unlike the centroid gradients, the nodal vectors w g_a equal
    int_e dN_a/dX dV exactly, so on distorted (non-parallelepiped) hexes a homogeneous
    deformation still leaves no force on interior nodes (patch test); on parallelepipeds the two
    coincide (the centroid value of dN/dX is its mean there).
    """
    m, k = qd.num_elements, qd.nodes_per_element
    w = qd.qp_weight.reshape(m, -1)
    V = w.sum(axis=1)
    g = np.einsum("mq,mqai->mai", w, qd.qp_dNdX.reshape(m, -1, k, 3)) / V[:, None, None]
    return QuadratureData(
        element_type=qd.element_type,
        nodes_per_element=k,
        elements=qd.elements,
        qp_element=np.arange(m, dtype=np.int32),
        qp_weight=np.ascontiguousarray(V),
        qp_dNdX=np.ascontiguousarray(g.reshape(-1, 3)),
    )


def precompute_quadrature(vertices: np.ndarray, elements: np.ndarray, element_type: str = "tet4", *,
                          volumetric_integration: str = "full") -> QuadratureData:
    """Build :class:`QuadratureData` for a mesh of one element type.

    ``element_type``: "tet4" (1 point), "tet10" (4 points), "hex8" (2x2x2), "hex27" (3x3x3); node
    order as in :mod:`warpfem.elements.library`. ``volumetric_integration="reduced"`` (hex8 only)
    adds the 1-point volumetric set of selective reduced integration, with volume-averaged
    gradients (see :func:`mean_gradient_quadrature`).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    elements = np.asarray(elements)
    if volumetric_integration not in VOLUMETRIC_INTEGRATION:
        raise ValueError(f"volumetric_integration must be 'full' or 'reduced', got {volumetric_integration!r}")
    if volumetric_integration == "reduced" and element_type != "hex8":
        raise ValueError(f"volumetric_integration='reduced' is only available for hex8 elements, not {element_type!r}")
    if element_type in SUPPORTED_ELEMENTS and element_type != "tet4":
        from .library import NODES_PER_ELEMENT

        k = NODES_PER_ELEMENT[element_type]
        if elements.ndim != 2 or elements.shape[1] != k:
            raise ValueError(f"{element_type} elements must have shape (m, {k}), got {elements.shape}")
        qd = _generic_quadrature(vertices, elements.astype(np.int64), element_type, "stiffness")
        if volumetric_integration == "reduced":
            vol = mean_gradient_quadrature(qd)
            qd = QuadratureData(qd.element_type, qd.nodes_per_element, qd.elements, qd.qp_element,
                                qd.qp_weight, qd.qp_dNdX, volumetric=vol)
        return qd
    if element_type == "tet4":
        vol, g = tet4_shape_gradients(vertices, elements)
        m = len(elements)
        return QuadratureData(
            element_type="tet4",
            nodes_per_element=4,
            elements=np.ascontiguousarray(elements.reshape(-1), dtype=np.int32),
            qp_element=np.arange(m, dtype=np.int32),
            qp_weight=vol.astype(np.float64),
            qp_dNdX=np.ascontiguousarray(g.reshape(-1, 3)),
        )
    raise ValueError(f"unknown element type {element_type!r}; supported: {', '.join(SUPPORTED_ELEMENTS)}")
