"""Bridges from other simulators to warpfem (the top layer: nothing in warpfem imports it).

* :mod:`warpfem.interop.newton`: :class:`~warpfem.interop.newton.SolverFEM`, warpfem as a solver of
  newton (the Warp physics engine); needs the optional ``newton`` package (``pip install
  "warpfem[newton]"``).

``import warpfem`` imports none of these.
"""
