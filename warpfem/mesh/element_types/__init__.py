"""Element types, one module each, registered in ``ELEMENTS`` (name -> :class:`ElementType`).

A new element type is one module here (a subclass of ``ElementType`` decorated with
``register_element``) plus its name in the import line below."""

from .base import ELEMENTS, ElementType, get_element, register_element
from . import tet4, tet10, hex8, hex27  # noqa: F401, E402, I001 - the element modules (they register)

__all__ = ["ELEMENTS", "ElementType", "get_element", "register_element"]
