"""The ``auto`` linear solver: a choice by device, size and compressibility.

The rule and the measurements behind it are in docs/linear_solvers.md.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

# Thresholds (see docs/linear_solvers.md for the measurements that set them).
DIRECT_MAX_DOFS_CPU = 400_000  # the direct solver beats PCG and AMG per Newton iteration below this on the CPU
NEARLY_INCOMPRESSIBLE_NU = 0.45


def _direct_available() -> bool:
    from warpfem.solvers.linear.direct import available_backends

    return available_backends()[0] == "pardiso"


def _amg_available() -> bool:
    try:
        import pyamg  # noqa: F401
    except ImportError:
        return False
    return True


def choose(pattern, *, poisson_ratio=None) -> str:
    """``pcg`` on CUDA (the data stay on the device, the loop is a CUDA graph); on the CPU
    ``direct`` up to DIRECT_MAX_DOFS_CPU DOFs when a fast backend (PARDISO or QDLDL) is installed,
    above it ``amg`` (when installed) for nearly incompressible materials (nu >= 0.45) and
    ``direct`` otherwise; ``pcg`` when the extras are missing."""
    dofs = 3 * pattern.num_rows
    if pattern.device.is_cuda:
        return "pcg"
    nearly_incompressible = poisson_ratio is not None and poisson_ratio >= NEARLY_INCOMPRESSIBLE_NU
    if dofs <= DIRECT_MAX_DOFS_CPU and _direct_available():
        return "direct"
    if nearly_incompressible and _amg_available():
        return "amg"
    if _direct_available():
        return "direct"
    return "pcg"
