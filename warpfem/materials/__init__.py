"""Isotropic hyperelastic materials: Python classes and Warp functions (docs/design.md).

Kinds (runtime ints for the kernels): LINEAR = 0, STVK = 1, COROTATED = 2, STABLE_NEO_HOOKEAN = 3,
STABLE_NEO_HOOKEAN_LOG = 4.
Warp side: ``material_psi``, ``material_pk1``, ``material_eigensystem`` (dispatch.py) and
``hessian_block`` (eigensystem.py). Python side: ``LinearElastic``, ``StVenantKirchhoff``,
``Corotated``, ``StableNeoHookean``, ``StableNeoHookeanLog`` and ``make_material(name, **kw)``.
"""

from .base import (COROTATED, LINEAR, STABLE_NEO_HOOKEAN, STABLE_NEO_HOOKEAN_LOG, STVK, Material, lame_parameters,
                   validate_parameters)
from .corotated import Corotated
from .dispatch import material_eigensystem, material_hessian_parts, material_pk1, material_psi
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

#: scene name -> class
MATERIALS = {
    "linear": LinearElastic,
    "stvk": StVenantKirchhoff,
    "corotated": Corotated,
    "stable_neo_hookean": StableNeoHookean,
    "stable_neo_hookean_log": StableNeoHookeanLog,
}


def make_material(name: str, **kw) -> Material:
    """Build a material from its scene name ("linear", "stvk", "corotated",
    "stable_neo_hookean", "stable_neo_hookean_log") and keyword arguments youngs_modulus=, poisson_ratio=, density=."""
    try:
        cls = MATERIALS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown material {name!r}; expected one of {sorted(MATERIALS)}") from None
    return cls(**kw)
