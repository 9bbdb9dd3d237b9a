"""Element types turned into flat quadrature-point data.

Every element type is precomputed, once, into the arrays the kernels consume (see
``docs/design.md``): the flat connectivity with its stride ``nodes_per_element`` and, per
quadrature point, the element it belongs to, its weight (Gauss weight x det J, i.e. the volume it
represents, m^3) and the material gradients dN_a/dX of the element's shape functions (1/m).

Element types "tet4", "tet10", "hex8", "hex27" (node order = meshio / VTK): one object each in
``warpfem.mesh.element_types`` (``ELEMENTS``, ``get_element``), holding nodes, shape functions,
quadrature rules, faces, lumping and corner sub-tets; ``library`` looks them up by name.
"""

from __future__ import annotations

from warpfem.mesh.element_types import ELEMENTS, ElementType, get_element, register_element
from .library import ELEMENT_TYPES, NODES_PER_ELEMENT, gauss_rule, shape_functions, shape_gradients
from .mass import consistent_mass_matrix, element_mass_matrices, lumped_mass_vector, mass_matrices
from .meshes import (ElementMesh, box_hex_mesh, embed_points_in_elements, load_element_mesh,
                     save_element_mesh, tet10_from_tet4)
from .quadrature import SUPPORTED_ELEMENTS, ElementError, QuadratureData, precompute_quadrature

__all__ = [
    "ELEMENTS", "ElementType", "get_element", "register_element",
    "ELEMENT_TYPES", "NODES_PER_ELEMENT", "SUPPORTED_ELEMENTS", "ElementError", "ElementMesh", "QuadratureData",
    "box_hex_mesh", "consistent_mass_matrix", "element_mass_matrices", "embed_points_in_elements", "gauss_rule",
    "load_element_mesh", "lumped_mass_vector", "mass_matrices", "precompute_quadrature", "save_element_mesh",
    "shape_functions", "shape_gradients", "tet10_from_tet4",
]
