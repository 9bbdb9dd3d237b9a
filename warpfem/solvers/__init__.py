"""Solvers: the Newton loop over forms (:mod:`.nonlinear`), the energy forms (:mod:`.forms`), linear
solvers (:mod:`.linear`), the simulation state (:mod:`.state`) and stiffness warping.

The Newton loop lives in ``warpfem.solvers.nonlinear`` (not ``newton``, which a reader would take for
the separate ``newton`` physics package)."""
