"""Contact with kinematic colliders (floor, spheres, boxes, triangle meshes) in the incremental
potential: smooth barrier, continuous-collision step bound, lagged friction (docs/contact.md)."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names for type checkers and the API docs (read statically)
    from warpfem.contact.colliders import (COLLIDER_TYPES, Box, Capsule, Collider, MeshCollider, Plane, Sphere, make_collider,
                                           register_collider, unregister_collider)
    from warpfem.contact.contact import CollisionError, ContactForm, ContactSet
    from warpfem.contact.surface import ContactSurface, SurfaceContact, SurfaceContactForm, contact_surface

from warpfem.lazy import lazy_attributes  # noqa: E402

# name -> defining module, imported on first access (PEP 562): the scene schema reads the collider
# registry without loading the contact forms and their kernels (a scene without contact never does).
_LAZY = {
    **dict.fromkeys(["COLLIDER_TYPES", "Box", "Capsule", "Collider", "MeshCollider", "Plane", "Sphere", "make_collider",
                     "register_collider", "unregister_collider"], "warpfem.contact.colliders"),
    **dict.fromkeys(["CollisionError", "ContactForm", "ContactSet"], "warpfem.contact.contact"),
    **dict.fromkeys(["ContactSurface", "SurfaceContact", "SurfaceContactForm", "contact_surface"],
                    "warpfem.contact.surface"),
}

__all__ = ["Collider", "Plane", "Sphere", "Box", "Capsule", "MeshCollider", "make_collider", "COLLIDER_TYPES",
           "register_collider", "unregister_collider",
           "ContactSet", "ContactForm", "CollisionError", "ContactSurface", "SurfaceContact", "SurfaceContactForm",
           "contact_surface"]


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
