"""Element library by name: views of the element type objects (``warpfem.mesh.element_types``).

Each element type is one object in its own module (``types/tet4.py``, ...); the tables and
functions here look them up by name for callers that hold a name.

Element types (``ELEMENT_TYPES``) and node ordering (the VTK ordering meshio uses for
``tetra``, ``tetra10``, ``hexahedron`` and ``hexahedron27`` cells):

* ``tet4``  reference tet {xi >= 0, sum xi <= 1}; nodes 0:(0,0,0) 1:(1,0,0) 2:(0,1,0) 3:(0,0,1).
* ``tet10`` corners as tet4, then edge mid-nodes 4:(0,1) 5:(1,2) 6:(0,2) 7:(0,3) 8:(1,3) 9:(2,3).
  N_corner = L (2 L - 1), N_edge(a,b) = 4 L_a L_b with L = (1 - xi - eta - zeta, xi, eta, zeta).
* ``hex8``  reference cube [-1, 1]^3; corners 0:(-,-,-) 1:(+,-,-) 2:(+,+,-) 3:(-,+,-) 4:(-,-,+)
  5:(+,-,+) 6:(+,+,+) 7:(-,+,+); trilinear N = prod (1 + xi_i r_i) / 8.
* ``hex27`` corners as hex8; edge mid-nodes 8:(0,1) 9:(1,2) 10:(2,3) 11:(3,0) 12:(4,5) 13:(5,6)
  14:(6,7) 15:(7,4) 16:(0,4) 17:(1,5) 18:(2,6) 19:(3,7); face centres 20:-x 21:+x 22:-y 23:+y
  24:-z 25:+z; 26: centre. Triquadratic N = prod_i L_{r_i}(xi_i), L the 1D quadratic Lagrange
  polynomials on the nodes -1, 0, 1.

Gauss rules (``gauss_rule(element_type, purpose)``), weights sum to the reference volume
(1/6 for tets, 8 for hexes):

* tet4: 1 point (centroid), degree 1 (stiffness and mass: the Tet4 mass uses the closed form).
* tet10: 4 points, degree 2 (stiffness); mass: 27-point conical product (Gauss-Jacobi), degree 5.
* hex8: 2x2x2 Gauss-Legendre, exact for degree <= 3 in each variable; ``"volumetric"``: 1 point.
* hex27: 3x3x3 Gauss-Legendre, exact for degree <= 5 in each variable.
"""

from __future__ import annotations

import numpy as np

from warpfem.mesh.element_types import ELEMENTS, get_element
from warpfem.mesh.element_types.base import as_points as _as_points, hex_gauss_rule, tet_conical_rule  # noqa: F401
from warpfem.mesh.element_types.hex8 import HEX8_NODES
from warpfem.mesh.element_types.hex27 import HEX27_EDGES, HEX27_NODES, lagrange2 as _lagrange2  # noqa: F401
from warpfem.mesh.element_types.tet4 import TET4_NODES
from warpfem.mesh.element_types.tet10 import TET10_EDGES, TET10_NODES

__all__ = ["ELEMENT_TYPES", "NODES_PER_ELEMENT", "MESHIO_CELL_TYPE", "RULE_DEGREE", "REFERENCE_NODES",
           "REFERENCE_VOLUME", "TET10_EDGES", "HEX27_EDGES", "TET4_NODES", "TET10_NODES", "HEX8_NODES",
           "HEX27_NODES", "check_element_type", "shape_functions", "shape_gradients", "gauss_rule",
           "hex_gauss_rule", "tet_conical_rule", "get_element"]

ELEMENT_TYPES = tuple(ELEMENTS)
NODES_PER_ELEMENT = {n: e.nodes_per_element for n, e in ELEMENTS.items()}
#: meshio cell type of each element type
MESHIO_CELL_TYPE = {n: e.meshio_cell for n, e in ELEMENTS.items()}
#: polynomial degree of the stated exactness of each rule (per variable for hexes)
RULE_DEGREE = {(n, purpose): d for n, e in ELEMENTS.items() for purpose, d in e.rule_degree.items()}
#: reference coordinates of the nodes of each element type, (k, 3)
REFERENCE_NODES = {n: e.reference_nodes for n, e in ELEMENTS.items()}
#: reference volume
REFERENCE_VOLUME = {n: e.reference_volume for n, e in ELEMENTS.items()}


def check_element_type(element_type: str) -> str:
    get_element(element_type)
    return element_type


def shape_functions(element_type: str, xi) -> np.ndarray:
    """Shape functions N_a(xi) at reference points xi (p, 3) -> (p, k)."""
    return get_element(element_type).shape(xi)[0]


def shape_gradients(element_type: str, xi) -> np.ndarray:
    """Reference gradients dN_a/dxi at reference points xi (p, 3) -> (p, k, 3)."""
    return get_element(element_type).shape(xi)[1]


def gauss_rule(element_type: str, purpose: str = "stiffness"):
    """Reference points (q, 3) and weights (q,) of the rule used for ``purpose``:
    "stiffness" (the element's integration rule), "mass" (exact for N_a N_b on affine elements) or
    "volumetric" (hex8 only: the 1-point rule of selective reduced integration)."""
    return get_element(element_type).rule(purpose)
