"""Per-quadrature-point precompute (rest-state data) for the element kernels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from warpfem.mesh.element_types import ElementError, element_point_data, get_element

__all__ = ["ElementError", "QuadratureData", "precompute_quadrature", "mean_gradient_quadrature", "element_point_data",
           "VOLUMETRIC_INTEGRATION"]

VOLUMETRIC_INTEGRATION = ("full", "reduced")


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


def precompute_quadrature(vertices: np.ndarray, elements: np.ndarray, element_type="tet4", *,
                          volumetric_integration: str = "full") -> QuadratureData:
    """Build :class:`QuadratureData` for a mesh of one element type (a registered name or the
    element object: Tet4 1 point, Tet10 4, Hex8 2x2x2, Hex27 3x3x3; node order of
    ``warpfem.mesh.element_types``), from the element's ``point_data`` (weight x det J, dN/dX;
    :class:`ElementError` naming the elements with det J <= 0). ``volumetric_integration="reduced"``
    (element types with a 1-point "volumetric" rule: Hex8) adds the 1-point volumetric set of
    selective reduced integration, with volume-averaged gradients (see :func:`mean_gradient_quadrature`).
    """
    element = get_element(element_type)
    vertices = np.asarray(vertices, dtype=np.float64)
    elements = np.asarray(elements)
    if volumetric_integration not in VOLUMETRIC_INTEGRATION:
        raise ValueError(f"volumetric_integration must be 'full' or 'reduced', got {volumetric_integration!r}")
    if volumetric_integration == "reduced" and "volumetric" not in element.rule_degree:
        from warpfem.mesh.element_types import ELEMENTS

        with_rule = [n for n, e in ELEMENTS.items() if "volumetric" in e.rule_degree]
        raise ValueError(f"volumetric_integration='reduced' is only available for {', '.join(with_rule)} elements, "
                         f"not {element.name!r}")
    k = element.nodes_per_element
    if elements.ndim != 2 or elements.shape[1] != k:
        raise ValueError(f"{element.name} elements must have shape (m, {k}), got {elements.shape}")
    elements = elements.astype(np.int64)
    w, dNdX = element.point_data(vertices, elements, "stiffness")  # (m, q), (m, q, k, 3)
    m, q = w.shape
    qd = QuadratureData(
        element_type=element.name,
        nodes_per_element=k,
        elements=np.ascontiguousarray(elements.reshape(-1), dtype=np.int32),
        qp_element=np.repeat(np.arange(m, dtype=np.int32), q),
        qp_weight=np.ascontiguousarray(w.reshape(-1), dtype=np.float64),
        qp_dNdX=np.ascontiguousarray(dNdX.reshape(-1, 3)),
    )
    if volumetric_integration == "reduced":
        vol = mean_gradient_quadrature(qd)
        qd = QuadratureData(qd.element_type, qd.nodes_per_element, qd.elements, qd.qp_element,
                            qd.qp_weight, qd.qp_dNdX, volumetric=vol)
    return qd
