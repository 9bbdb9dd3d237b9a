"""Element types, one module each, registered in ``ELEMENTS`` (name -> :class:`ElementType`).

A new element type is one module here (a subclass of ``ElementType`` decorated with
``register_element``) plus its name in the import line below; meshes, masses, quadrature, the model,
boundary faces and embedding then work with it through the object (``docs/design.md``)."""

from .base import (ELEMENTS, ElementError, ElementType, element_point_data, gauss_rule, get_element, register_element,
                   shape_functions, shape_gradients)
from . import tet4, tet10, hex8, hex27  # noqa: F401, E402, I001 - the element modules (they register)

__all__ = ["ELEMENTS", "ElementError", "ElementType", "get_element", "register_element", "shape_functions",
           "shape_gradients", "gauss_rule", "element_point_data"]
