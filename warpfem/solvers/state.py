"""State API shared by the full-space simulators (``Simulator``, ``StiffnessWarpingSimulator``).

:class:`SimulatorState` is a mixin: positions and velocities as device arrays of vec3, Dirichlet
components (``fix``/``release``, kept on the model) and kinematic targets for the next step.
A class using it provides:

* ``self.model`` (a :class:`~warpfem.model.Model`: ``fix``, ``release``, ``_indices``),
* ``self.num_vertices``, ``self.x``, ``self.v`` (device arrays of vec3, n entries),
* ``self._vec_array(a=None)`` -> a device vec3 array of n entries (zeros, or from a float64 (n, 3)),
* ``self._targets`` (dict vertex -> (3,) float64 target position), cleared by ``step``,
* ``self.sync_model()`` (uploads the fixed mask / external forces after a model change).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import linalg as LK
from warpfem.kernels.generic import launch

__all__ = ["SimulatorState", "PRECISIONS", "check_simulator_options"]

#: precision name -> (scalar, vec3, mat33 Warp types, numpy dtype)
PRECISIONS = {
    "float32": (wp.float32, wp.vec3, wp.mat33, np.float32),
    "float64": (wp.float64, wp.vec3d, wp.mat33d, np.float64),
}


def check_simulator_options(precision, dt, damping_mass, damping_stiffness):
    """Validate the options every time stepper takes; returns ``PRECISIONS[precision]``.

    Raises ValueError naming the option: precision not "float32"/"float64", dt not a positive
    finite number of seconds, a negative (or NaN) Rayleigh coefficient."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be 'float32' or 'float64', got {precision!r}")
    if not (isinstance(dt, (int, float, np.integer, np.floating)) and not isinstance(dt, bool)
            and np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    if not (damping_mass >= 0 and damping_stiffness >= 0):
        raise ValueError(f"Rayleigh damping coefficients must be >= 0, got damping_mass={damping_mass!r}, "
                         f"damping_stiffness={damping_stiffness!r}")
    return PRECISIONS[precision]


class SimulatorState:
    """positions / velocities / set_positions / set_velocities / fix / release / set_targets."""

    # -- boundary conditions (no re-assembly, no pattern rebuild) --------------------------------------
    def fix(self, indices, components="xyz"):
        """Fix vertex components (a subset of "xyz") at their current positions from the next step on."""
        self.model.fix(indices, components)
        self.sync_model()

    def release(self, indices, components="xyz"):
        """Release fixed components (no re-assembly)."""
        self.model.release(indices, components)
        self.sync_model()

    def set_targets(self, indices, positions):
        """Prescribe end-of-step positions (m) of fixed vertices for the next step or static solve
        (kinematic handles); ``positions`` has one row of 3 per index."""
        idx = self.model._indices(indices)
        pos = np.asarray(positions, dtype=np.float64).reshape(len(idx), 3)
        if not np.all(np.isfinite(pos)):
            raise ValueError("target positions must be finite")
        for i, p in zip(idx.tolist(), pos):
            self._targets[i] = p

    # -- state access ------------------------------------------------------------------------------
    def positions(self) -> np.ndarray:
        """Current positions (n, 3), m, float64 copy."""
        return self.x.numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Current velocities (n, 3), m/s, float64 copy."""
        return self.v.numpy().astype(np.float64)

    def _checked_state(self, a, what: str) -> np.ndarray:
        a = np.asarray(a, dtype=np.float64)
        if a.shape != (self.num_vertices, 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"{what} must be finite with shape ({self.num_vertices}, 3), got {a.shape}")
        return a

    def set_positions(self, x):
        """Replace the positions (m), (n, 3); raises ValueError (state untouched) for a wrong shape or NaN/inf."""
        self.x = self._vec_array(self._checked_state(x, "positions"))
        self._state_changed()

    def set_velocities(self, v):
        """Replace the velocities (m/s), (n, 3); raises ValueError (state untouched) for a wrong shape or NaN/inf."""
        self.v = self._vec_array(self._checked_state(v, "velocities"))
        self._state_changed()

    # -- the interface time integrators use (warpfem.integrators) -----------------------------------
    def _istate(self):
        return self.x, self.v

    def _iset_state(self, x, v):
        self.x, self.v = x, v

    def _ivec(self):
        return self._vec_array()

    def _ilincomb(self, a, x, b, y, out):
        launch(LK.lincomb_kernel, self.num_vertices, [self._s(a), x, self._s(b), y, out], self.device)

    def _state_changed(self):
        """The state was set from outside: time integrators restart their history (BDF2 takes a
        backward Euler step, Newmark recomputes the acceleration)."""
        integrator = getattr(self, "integrator", None)
        if integrator is not None:
            integrator.reset()
