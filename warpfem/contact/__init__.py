"""Contact with kinematic colliders (floor, spheres, boxes, triangle meshes) in the incremental
potential: smooth barrier, continuous-collision step bound, lagged friction (docs/contact.md)."""

from warpfem.contact.colliders import (COLLIDER_TYPES, Box, Collider, MeshCollider, Plane, Sphere, make_collider,
                                       register_collider, unregister_collider)
from warpfem.contact.contact import CollisionError, ContactForm, ContactSet
from warpfem.contact.surface import ContactSurface, SurfaceContact, SurfaceContactForm, contact_surface

__all__ = ["Collider", "Plane", "Sphere", "Box", "MeshCollider", "make_collider", "COLLIDER_TYPES",
           "register_collider", "unregister_collider",
           "ContactSet", "ContactForm", "CollisionError", "ContactSurface", "SurfaceContact", "SurfaceContactForm",
           "contact_surface"]
