"""The ``auto`` linear solver: a choice by device and size.

The rule and the measurements behind it are in docs/linear_solvers.md (bunny, octopus and box
scenes at their Poisson ratio and at 0.49, on this project's 2-core CPU):

* CUDA: ``pcg`` (the data stay on the device; the loop is a CUDA graph with a host check every k
  iterations; the host backends would copy the matrix down and back every Newton iteration).
* CPU, up to DIRECT_MAX_DOFS_CPU unknowns with PARDISO installed: ``direct``. Per step it was
  2.5x (nu = 0.4) and 6.4x (nu = 0.49) faster than block-Jacobi PCG on the bunny (16k unknowns)
  and 3.8x / 11x on the octopus, and its cost does not grow with nu. On the mass-dominated box
  beam PCG needs few iterations: at 15k unknowns PCG was 1.8x faster at nu = 0.3 and direct 1.6x
  faster at nu = 0.49; at 56k unknowns (100k tets) direct and PCG were even (4.5 s vs 4.1 s per
  step at nu = 0.3). Above that the factorisation (O(n^2) flops on 3D meshes) falls behind.
* CPU without PARDISO: ``direct`` (SuperLU, no symbolic reuse) up to SUPERLU_MAX_DOFS_CPU
  (its bunny factorisation, 1.9 s, is about one Newton iteration of PCG there).
* Larger: ``pcg``. ``amg`` is not chosen automatically: it needs 7-28x fewer iterations than
  block-Jacobi but pyamg's setup and host V-cycles cost more than they save on every mesh
  measured here except the octopus (where direct is faster still) and the 100k-tet box at nu = 0.3
  (0.88x of PCG's time); select it explicitly for large, stiff, nearly incompressible problems
  after measuring.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

DIRECT_MAX_DOFS_CPU = 60_000
SUPERLU_MAX_DOFS_CPU = 20_000


def _pardiso_available() -> bool:
    from warpfem.solvers.linear.direct import available_backends

    return available_backends()[0] == "pardiso"


def choose(pattern) -> str:
    """The solver ``auto`` builds for this pattern (see the module docstring)."""
    dofs = 3 * pattern.num_rows
    if pattern.device.is_cuda:
        return "pcg"
    limit = DIRECT_MAX_DOFS_CPU if _pardiso_available() else SUPERLU_MAX_DOFS_CPU
    return "direct" if dofs <= limit else "pcg"
