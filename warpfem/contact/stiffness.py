"""Adaptive barrier stiffness kappa for the contact barriers (colliders and surface pairs).

After Li et al. 2020, "Incremental Potential Contact: Intersection- and Inversion-free,
Large-Deformation Dynamics" (its adaptive barrier stiffness), in this project's units: the
potential is in joules (E = 1/2 |y - y_hat|^2_M + Psi(x) + kappa B(x) + ..., x = x_b + s y), where
that paper's is h^2 times it, so its kappa is ours times s^2.

* **Bounds.** kappa_min makes the barrier's curvature in the distance at a gap of
  ``D0_FRACTION`` x the body's diagonal equal to ``MIN_SCALE`` x the mean vertex mass / s^2 (the
  inertia of a vertex scaled up); kappa_max = ``MAX_FACTOR`` x kappa_min. For the
  squared-distance barrier b(d^2, dhat^2) of surface pairs the curvature is taken as
  4 d^2 b''(d^2) (the paper's; its 2 b' term is smaller there), for the collider barrier
  b(d, dhat) it is b''(d).
* **When a contact starts** (a pair, or a vertex and a collider, closer than dhat at a step's
  start, none in the step before): the kappa that best balances the barrier's gradient g_B (at
  kappa = 1) against the gradient g_E of the rest of the potential at the step's start,
  argmin |g_E + kappa g_B| = -g_E.g_B / |g_B|^2, clamped to the bounds. While the contact lasts
  kappa is kept (raising it then would add energy to a compressed barrier); after a step without
  any distance below dhat it returns to kappa_min.
* **During a solve**, after every accepted Newton iteration: when the smallest distance is below
  ``SHRINK_FRACTION`` x dhat and smaller than after the previous iteration, kappa doubles (up to
  kappa_max) and the Newton loop re-evaluates the potential (``newton_solve``'s
  ``after_iteration`` hook).

Measured effect: docs/contact.md, "Adaptive barrier stiffness".
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["AdaptiveStiffness", "barrier_second_derivative", "min_stiffness", "balanced_stiffness", "parse_stiffness"]

#: kappa_min: the barrier's curvature at the gap D0_FRACTION x diagonal is MIN_SCALE x (mean vertex mass / s^2)
MIN_SCALE = 1e11
D0_FRACTION = 1e-8
#: kappa_max / kappa_min
MAX_FACTOR = 100.0
#: kappa doubles when the smallest distance keeps shrinking below this fraction of dhat
SHRINK_FRACTION = 0.01


def parse_stiffness(value, where="stiffness"):
    """(adaptive, kappa): ``"auto"`` -> (True, None); ``None`` -> (False, None) (the fixed default
    from the material); a number > 0 -> (False, that kappa)."""
    if value is None:
        return False, None
    if isinstance(value, str) and value.strip().lower() == "auto":
        return True, None
    if isinstance(value, str):
        raise ValueError(f"{where} must be a number > 0 or \"auto\", got {value!r}")
    v = float(value)
    if not (np.isfinite(v) and v > 0.0):
        raise ValueError(f"{where} must be > 0 or \"auto\", got {value!r}")
    return False, v


def barrier_second_derivative(d, dhat):
    """b''(d) of b(d) = -(d - dhat)^2 ln(d / dhat) (0 < d < dhat); the same function of s = d^2 and
    t = dhat^2 for the squared-distance barrier."""
    r = d - dhat
    return -2.0 * math.log(d / dhat) - 4.0 * r / d + (r / d) ** 2


def min_stiffness(mean_mass, diagonal, dhat, s, *, squared):
    """kappa_min (see the module docstring): collider barrier (N/m) or, ``squared``, the
    squared-distance barrier of surface pairs (N/m^3)."""
    d0 = D0_FRACTION * diagonal
    if not d0 < dhat:
        d0 = 0.5 * dhat
    if squared:
        curvature = 4.0 * d0 * d0 * barrier_second_derivative(d0 * d0, dhat * dhat)
    else:
        curvature = barrier_second_derivative(d0, dhat)
    return MIN_SCALE * float(mean_mass) / (float(s) ** 2 * curvature)


def balanced_stiffness(g_rest, g_barrier):
    """argmin_kappa |g_rest + kappa g_barrier| (None when g_barrier is 0)."""
    gb = np.asarray(g_barrier, dtype=np.float64).ravel()
    nb = float(gb @ gb)
    if not nb > 0.0:
        return None
    return -float(np.asarray(g_rest, dtype=np.float64).ravel() @ gb) / nb


class AdaptiveStiffness:
    """kappa of one barrier (a collider, or all surface pairs) over a run.

    ``mean_mass`` (kg per vertex), ``diagonal`` (m, of the body's box), ``dhat`` (m), ``squared``:
    the squared-distance barrier (surface pairs)."""

    def __init__(self, mean_mass, diagonal, dhat, *, squared):
        self.mean_mass, self.diagonal, self.dhat, self.squared = float(mean_mass), float(diagonal), float(dhat), squared
        self.kappa = None
        self.kappa_min = self.kappa_max = None
        self.d_prev = math.inf
        self.touched = False  # whether a distance below dhat was seen since the last step start
        self.doublings = 0  # kappa doublings during solves (cumulative, for benchmarks)

    def bounds(self, s):
        kmin = min_stiffness(self.mean_mass, self.diagonal, self.dhat, s, squared=self.squared)
        return kmin, MAX_FACTOR * kmin

    def initial(self, s):
        """kappa before any step (kappa_min for the step scale s)."""
        self.kappa_min, self.kappa_max = self.bounds(s)
        if self.kappa is None:
            self.kappa = self.kappa_min
        return self.kappa

    def begin_step(self, s, dmin, g_rest=None, g_barrier=None):
        """kappa for a step of scale s whose start has smallest distance ``dmin`` (m); with a pair
        inside dhat, ``g_rest`` and ``g_barrier`` (flat arrays over the free components) balance
        it. Returns kappa."""
        kmin, kmax = self.kappa_min, self.kappa_max = self.bounds(s)
        self.d_prev = float(dmin)
        was, self.touched = self.touched, bool(dmin < self.dhat)
        prev = kmin if self.kappa is None else self.kappa
        if not self.touched:
            # no pair inside dhat now: back to kappa_min unless the last step touched (it may again)
            self.kappa = min(kmax, max(kmin, prev)) if was else kmin
        elif was:  # the contact goes on: kappa stays (raising it would add energy to a compressed barrier)
            self.kappa = min(kmax, max(kmin, prev))
        else:  # a contact starts at this step's start: balanced against the rest of the potential
            k = None if g_barrier is None else balanced_stiffness(g_rest, g_barrier)
            self.kappa = kmin if k is None or not np.isfinite(k) else min(kmax, max(kmin, k))
        return self.kappa

    def update(self, dmin) -> bool:
        """After an accepted Newton iteration whose smallest distance is ``dmin``: double kappa
        when dmin is below SHRINK_FRACTION x dhat and shrinking. Returns whether kappa changed."""
        dmin = float(dmin)
        self.touched = self.touched or dmin < self.dhat
        changed = False
        if dmin < SHRINK_FRACTION * self.dhat and dmin < self.d_prev and self.kappa < self.kappa_max:
            self.kappa = min(self.kappa_max, 2.0 * self.kappa)
            self.doublings += 1
            changed = True
        self.d_prev = dmin
        return changed

    def state(self):
        return self.kappa, self.d_prev, self.touched

    def restore(self, state):
        self.kappa, self.d_prev, self.touched = state

    def state_dict(self) -> dict:
        """kappa, its bounds, the last smallest distance, whether it touched, the doublings."""
        from warpfem.io.checkpoint import optional_number

        return {"kappa": optional_number(self.kappa), "kappa_min": optional_number(self.kappa_min),
                "kappa_max": optional_number(self.kappa_max), "d_prev": float(self.d_prev), "touched": bool(self.touched),
                "doublings": int(self.doublings)}

    @staticmethod
    def read_state(view) -> dict:
        """The checked values of :meth:`state_dict` from a :class:`warpfem.io.checkpoint.StateView`."""
        return {"kappa": view.number("kappa", optional=True), "kappa_min": view.number("kappa_min", optional=True),
                "kappa_max": view.number("kappa_max", optional=True), "d_prev": view.number("d_prev"),
                "touched": view.flag("touched"), "doublings": view.integer("doublings")}

    def set_state(self, values: dict):
        """Set the values :meth:`read_state` returned."""
        for k, v in values.items():
            setattr(self, k, v)
