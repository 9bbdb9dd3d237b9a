"""The material registry: each material kind is defined once, where its module registers it.

A material module defines its Warp functions and its Python class, and registers the class::

    @register_material("linear", kind=0, psi=linear_psi, pk1=linear_pk1, eigen=linear_eigen, svd=False)
    class LinearElastic(Material): ...

``name`` is the scene name (``[material].model``), ``kind`` the runtime int the kernels switch on
(stable: subspace caches store it), ``psi(F, mu, lam)`` / ``pk1(F, mu, lam)`` the energy density
and first Piola-Kirchhoff stress, and ``eigen`` the Hessian's eigen form: ``eigen(s, mu, lam) ->
(A, twist, flip)`` in the signed singular values s of F (``svd=True``), or ``eigen(F, mu, lam)``
with U = V = I (``svd=False``, linear elasticity). The compiled dispatch (:mod:`.dispatch`) is
built from this registry, so a new material is its module plus its name in the import line of
material modules in :mod:`.dispatch`.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["MaterialType", "MATERIAL_TYPES", "register_material", "material_type"]


@dataclass(frozen=True)
class MaterialType:
    """A registered material: scene name, kernel kind, class and Warp functions (see the module doc)."""

    name: str
    kind: int
    cls: type
    psi: object
    pk1: object
    eigen: object
    svd: bool = True


#: scene name -> MaterialType, in registration order (the dispatch tests kinds in this order)
MATERIAL_TYPES: dict[str, MaterialType] = {}


def register_material(name: str, *, kind: int, psi, pk1, eigen, svd: bool = True):
    """Class decorator: register a material class under its scene ``name`` and kernel ``kind``
    (sets ``cls.name`` and ``cls.kind``). Names and kinds must be unique."""

    def deco(cls):
        if name in MATERIAL_TYPES:
            raise ValueError(f"material {name!r} is already registered")
        other = next((t for t in MATERIAL_TYPES.values() if t.kind == int(kind)), None)
        if other is not None:
            raise ValueError(f"material kind {kind} of {name!r} is already used by {other.name!r}")
        cls.name, cls.kind = name, int(kind)
        MATERIAL_TYPES[name] = MaterialType(name, int(kind), cls, psi, pk1, eigen, bool(svd))
        return cls

    return deco


def material_type(name: str) -> MaterialType:
    """The registered material ``name``; ValueError listing the known names otherwise."""
    try:
        return MATERIAL_TYPES[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown material {name!r}; expected one of {sorted(MATERIAL_TYPES)}") from None
