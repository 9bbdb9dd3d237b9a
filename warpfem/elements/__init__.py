"""Element types turned into flat quadrature-point data.

Every element type is precomputed, once, into the arrays the kernels consume (see
``docs/design.md``): the flat connectivity with its stride ``nodes_per_element`` and, per
quadrature point, the element it belongs to, its weight (Gauss weight x det J, i.e. the volume it
represents, m^3) and the material gradients dN_a/dX of the element's shape functions (1/m).
"""

from __future__ import annotations

from .quadrature import QuadratureData, precompute_quadrature, SUPPORTED_ELEMENTS

__all__ = ["QuadratureData", "precompute_quadrature", "SUPPORTED_ELEMENTS"]
