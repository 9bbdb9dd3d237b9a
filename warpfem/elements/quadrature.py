"""Per-quadrature-point precompute (rest-state data) for the element kernels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SUPPORTED_ELEMENTS = ("tet4",)


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
    """

    element_type: str
    nodes_per_element: int
    elements: np.ndarray
    qp_element: np.ndarray
    qp_weight: np.ndarray
    qp_dNdX: np.ndarray

    @property
    def num_elements(self) -> int:
        return len(self.elements) // self.nodes_per_element

    @property
    def num_points(self) -> int:
        return len(self.qp_element)


def tet4_shape_gradients(vertices: np.ndarray, tets: np.ndarray):
    """Rest volumes (m,) and shape-function gradients (m, 4, 3) of linear tets.

    Dm = [X1 - X0, X2 - X0, X3 - X0]; F = Ds Dm^-1 = sum_a x_a g_a^T with g_a = Dm^-T e_a
    (a = 1..3) and g_0 = -(g_1 + g_2 + g_3) (seed 004, barycentric shape functions).
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


def precompute_quadrature(vertices: np.ndarray, elements: np.ndarray, element_type: str = "tet4") -> QuadratureData:
    """Build :class:`QuadratureData` for a mesh of one element type."""
    vertices = np.asarray(vertices, dtype=np.float64)
    elements = np.asarray(elements)
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
