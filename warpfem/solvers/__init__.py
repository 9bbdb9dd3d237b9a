"""Solvers: the Newton loop over forms (:mod:`.nonlinear`), the energy forms (:mod:`.forms`), linear
solvers (:mod:`.linear`), the simulation state (:mod:`.state`) and stiffness warping.

The Newton loop lives in ``warpfem.solvers.nonlinear`` (not ``newton``, which a reader would take for
the separate ``newton`` physics package)."""

import sys as _sys

from . import nonlinear as _nonlinear

# Transitional alias for code written before the rename (``from warpfem.solvers.newton import ...``);
# new code imports warpfem.solvers.nonlinear.
_sys.modules.setdefault(__name__ + ".newton", _nonlinear)
