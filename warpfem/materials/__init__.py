"""Isotropic hyperelastic materials: Python classes and Warp functions (docs/design.md).

Each material module registers its class, scene name and kernel kind (the runtime int of the
kernels) in :mod:`.registry`; ``MATERIAL_TYPES`` lists them. The constants ``LINEAR``, ``STVK``,
``COROTATED``, ``STABLE_NEO_HOOKEAN``, ``STABLE_NEO_HOOKEAN_LOG`` below are read from it.
Warp side: ``material_psi``, ``material_pk1``, ``material_eigensystem`` (dispatch.py) and
``hessian_block`` (eigensystem.py). Python side: ``LinearElastic``, ``StVenantKirchhoff``,
``Corotated``, ``StableNeoHookean``, ``StableNeoHookeanLog`` and ``make_material(name, **kw)``.
"""

from .base import Material, lame_parameters, validate_parameters
from .dispatch import material_eigensystem, material_hessian_parts, material_pk1, material_psi  # registers all
from .corotated import Corotated  # noqa: I001
from .eigensystem import cofactor, hessian_block, signed_svd
from .evaluate import evaluate
from .linear import LinearElastic
from .stable_neo_hookean import StableNeoHookean
from .stable_neo_hookean_log import StableNeoHookeanLog
from .stvk import StVenantKirchhoff

__all__ = [
    "LINEAR",
    "STVK",
    "COROTATED",
    "STABLE_NEO_HOOKEAN",
    "STABLE_NEO_HOOKEAN_LOG",
    "MATERIALS",
    "MATERIAL_TYPES",
    "register_material",
    "Material",
    "LinearElastic",
    "StVenantKirchhoff",
    "Corotated",
    "StableNeoHookean",
    "StableNeoHookeanLog",
    "make_material",
    "lame_parameters",
    "validate_parameters",
    "material_psi",
    "material_pk1",
    "material_eigensystem",
    "material_hessian_parts",
    "hessian_block",
    "signed_svd",
    "cofactor",
    "evaluate",
]

from .registry import MATERIAL_TYPES, material_type, register_material  # noqa: E402

# kernel kinds, from the registry (defined once, where each material registers itself)
LINEAR = MATERIAL_TYPES["linear"].kind
STVK = MATERIAL_TYPES["stvk"].kind
COROTATED = MATERIAL_TYPES["corotated"].kind
STABLE_NEO_HOOKEAN = MATERIAL_TYPES["stable_neo_hookean"].kind
STABLE_NEO_HOOKEAN_LOG = MATERIAL_TYPES["stable_neo_hookean_log"].kind

#: scene name -> class (a view of the registry)
MATERIALS = {name: t.cls for name, t in MATERIAL_TYPES.items()}


def make_material(name: str, **kw) -> Material:
    """Build a material from its scene name (a key of ``MATERIAL_TYPES``: "linear", "stvk",
    "corotated", "stable_neo_hookean", "stable_neo_hookean_log") and keyword arguments
    youngs_modulus=, poisson_ratio=, density=."""
    return material_type(name).cls(**kw)
