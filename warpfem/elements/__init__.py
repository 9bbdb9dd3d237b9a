"""Element meshes turned into flat quadrature-point data.

Every mesh (``warpfem.mesh.VolumeMesh`` of any element type) is precomputed, once, into the arrays
the kernels consume (see ``docs/design.md``): the flat connectivity with its stride
``nodes_per_element`` and, per quadrature point, the element it belongs to, its weight (Gauss weight
x det J, i.e. the volume it represents, m^3) and the material gradients dN_a/dX of the element's
shape functions (1/m). The element types themselves (nodes, shape functions, rules, mass, faces) are
objects in ``warpfem.mesh.element_types``.
"""

from __future__ import annotations

from .quadrature import (ElementError, QuadratureData, element_point_data, mean_gradient_quadrature,
                         precompute_quadrature)

__all__ = ["ElementError", "QuadratureData", "element_point_data", "mean_gradient_quadrature", "precompute_quadrature"]
