"""Rigid bodies as affine bodies in the incremental potential (docs/rigid.md).

:class:`RigidBody` is a body of ``Model.from_bodies`` that moves as x = p + A X; its 12 degrees of
freedom (p and the columns of A) are four vec3 nodes of the simulator's unknown, and the stiff
orthogonality energy of "Affine Body Dynamics: Fast, Stable and Intersection-free Simulation of
Stiff Materials" (Lan et al. 2022) keeps A a rotation. :mod:`warpfem.rigid.embedding` maps the
unknown to the vertices the contact forms see. Imported on demand (``import warpfem`` stays lazy).
"""

from warpfem.rigid.body import RigidBody, mass_properties

__all__ = ["RigidBody", "mass_properties"]
