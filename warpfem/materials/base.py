"""Python base class shared by all materials: parameter validation, Lame mapping, numpy evaluators.

Lame parameters from Young's modulus E and Poisson ratio nu (small-strain moduli):

    mu     = E / (2 (1 + nu))
    lambda = E nu / ((1 + nu) (1 - 2 nu))

Each material stores the values its Warp functions expect in ``kernel_mu`` and ``kernel_lam``
(for the stable neo-Hookean materials these are reparametrised, not Lame's: see
``stable_neo_hookean.py`` and ``stable_neo_hookean_log.py``); the plain Lame values are kept in
``mu_lame`` and ``lam_lame``. There is deliberately no plain ``mu`` / ``lam``: every use names
which of the two it means.

Material kinds (the runtime ints of the kernels) are defined where each material registers itself
(:mod:`.registry`).
"""

from __future__ import annotations

import math
import numbers

import numpy as np

__all__ = ["Material", "lame_parameters", "validate_parameters"]


def _check_real(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, np.floating, np.integer)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def validate_parameters(youngs_modulus, poisson_ratio, density) -> tuple[float, float, float]:
    """Check E > 0, -1 < nu < 0.5, density > 0; raise ValueError naming the parameter and value."""
    E = _check_real("youngs_modulus", youngs_modulus)
    nu = _check_real("poisson_ratio", poisson_ratio)
    rho = _check_real("density", density)
    if not E > 0.0:
        raise ValueError(f"youngs_modulus must be > 0, got {youngs_modulus!r}")
    if not (-1.0 < nu < 0.5):
        raise ValueError(f"poisson_ratio must satisfy -1 < poisson_ratio < 0.5, got {poisson_ratio!r}")
    if not rho > 0.0:
        raise ValueError(f"density must be > 0, got {density!r}")
    return E, nu, rho


def lame_parameters(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """Lame (mu, lambda) from (E, nu): mu = E/(2(1+nu)), lambda = E nu/((1+nu)(1-2nu))."""
    E, nu = float(youngs_modulus), float(poisson_ratio)
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


class Material:
    """Isotropic hyperelastic material (abstract base).

    Keyword-only constructor ``(youngs_modulus=, poisson_ratio=, density=)``. Attributes:
    ``kind`` (int passed to the Warp dispatch functions) and ``name`` (scene name), both set by
    :func:`~warpfem.materials.registry.register_material`; ``kernel_mu``, ``kernel_lam`` (the
    values passed to kernels), ``mu_lame``, ``lam_lame`` (plain Lame
    values), ``density``, ``youngs_modulus``, ``poisson_ratio``.
    """

    kind: int = -1
    name: str = ""

    def __init__(self, *, youngs_modulus, poisson_ratio, density):
        E, nu, rho = validate_parameters(youngs_modulus, poisson_ratio, density)
        self.youngs_modulus = E
        self.poisson_ratio = nu
        self.density = rho
        self.mu_lame, self.lam_lame = lame_parameters(E, nu)
        self.kernel_mu, self.kernel_lam = self.kernel_parameters(self.mu_lame, self.lam_lame)

    @staticmethod
    def kernel_parameters(mu_lame: float, lam_lame: float) -> tuple[float, float]:
        """Map the Lame values to the (mu, lam) the Warp functions take (identity by default)."""
        return mu_lame, lam_lame

    def volumetric_split(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """Kernel parameters ((mu, lam) of the full-rule part, (mu, lam) of the volumetric part) for
        selective reduced integration (``Model(volumetric_integration="reduced")``).

        The contract: psi(F; mu, lam) = psi(F; *full) + psi(F; *volumetric) for every F (the
        energy splits exactly, so force and Hessian do too), the volumetric part carries every
        lambda-scaled term (the one that locks as nu -> 1/2) and nothing else, and both parts
        are stress-free and positive semi-definite at F = I (so the per-part SPD projection leaves
        the small-strain stiffness exact). Default: ((mu, 0), (0, lam)), exact for materials whose
        energy is mu psi_mu(F) + lam psi_lam(F): linear (lam/2 tr(eps)^2), StVK (lam/2 tr(E)^2),
        corotated (lam/2 (J - 1)^2).
        """
        return (self.kernel_mu, 0.0), (0.0, self.kernel_lam)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(youngs_modulus={self.youngs_modulus!r}, "
            f"poisson_ratio={self.poisson_ratio!r}, density={self.density!r})"
        )

    # numpy-facing evaluators (Warp kernel in float64 on the CPU) -------------------------------
    def _eval(self, F, **kw):
        from .evaluate import evaluate

        return evaluate(self.kind, F, self.kernel_mu, self.kernel_lam, **kw)

    def psi(self, F) -> np.ndarray:
        """Energy density (J/m^3) for F of shape (N, 3, 3) (or (3, 3)); returns (N,)."""
        return self._eval(F, outputs=("psi",))["psi"]

    def pk1(self, F) -> np.ndarray:
        """First Piola-Kirchhoff stress P = dpsi/dF for F (N, 3, 3); returns (N, 3, 3)."""
        return self._eval(F, outputs=("pk1",))["pk1"]

    def hessian(self, F, project: bool = False) -> np.ndarray:
        """dP/dF as a (N, 9, 9) matrix, F flattened row-major (index 3 i + j for F[i, j]).

        With ``project=True`` the eigenvalues of the analytic eigensystem are clamped at 0
        (the SPD projection of Smith, de Goes, Kim 2019).
        """
        key = "hessian_projected" if project else "hessian"
        return self._eval(F, outputs=(key,))[key]
