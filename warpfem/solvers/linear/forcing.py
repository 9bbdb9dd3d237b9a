"""Forcing terms of inexact Newton: the relative tolerance of each Newton system's linear solve.

``fixed``: every solve to ``cg_tol``. ``eisenstat_walker``: choice 2 of "Choosing the forcing terms
in an inexact Newton method" (Eisenstat, Walker), eta_k = gamma (||g_k|| / ||g_{k-1}||)^alpha with
gamma 0.9 and alpha 2, safeguarded from dropping fast (eta_k >= gamma eta_{k-1}^alpha when that is
above 0.1), capped at ``eta_max`` and never below ``cg_tol`` (the fixed scheme's tolerance, so no
system is solved more accurately than before), nor below what the Newton tolerance needs
(0.5 tol ||g_0|| / ||g_k||, "Iterative Methods for Linear and Nonlinear Equations", Kelley): early
iterations far from the solution get loose solves, the last ones the fixed tolerance. The first
system is solved to ``eta0`` (default ``eta_max``).
"""

from __future__ import annotations

FORCING = ("fixed", "eisenstat_walker")


class ForcingTerms:
    """The linear tolerance of each Newton iteration of one nonlinear solve.

    Args:
        kind: "fixed" or "eisenstat_walker".
        cg_tol: the fixed tolerance (and the floor of the adaptive one).
        tol: the Newton solve's relative gradient tolerance.
        eta_max, eta0: cap, and the first iteration's tolerance, of the adaptive terms.
    """

    def __init__(self, kind: str, cg_tol: float, tol: float, *, eta_max: float = 0.1, eta0: float | None = None,
                 gamma: float = 0.9, alpha: float = 2.0):
        if kind not in FORCING:
            raise ValueError(f"forcing must be one of {FORCING}, got {kind!r}")
        self.kind, self.cg_tol, self.tol = kind, float(cg_tol), float(tol)
        self.eta_max = max(float(eta_max), self.cg_tol)
        self.gamma, self.alpha = float(gamma), float(alpha)
        self.eta = self.eta_max if eta0 is None else min(max(float(eta0), self.cg_tol), self.eta_max)
        self._g0 = self._g_prev = None
        self._pending = False

    def first_tolerance(self) -> float:
        """The first system's tolerance (known before the start's gradient norm is)."""
        return self.cg_tol if self.kind == "fixed" else self.eta

    def start(self, gnorm0: float, *, first_solved: bool = False) -> None:
        """Register the start's gradient norm; ``first_solved``: the first system was already
        solved at :meth:`first_tolerance` (the Newton loop's fused first iteration), so the next
        call of :meth:`next` is for the second."""
        if self.kind == "fixed":
            return
        self._g0 = self._g_prev = gnorm0
        self._pending = not first_solved

    def next(self, gnorm: float) -> float:
        """The tolerance of the solve at a point whose gradient norm is ``gnorm``."""
        if self.kind == "fixed":
            return self.cg_tol
        if self._g0 is None:
            self._g0 = self._g_prev = gnorm
            return self.eta
        if self._pending:  # the first system, after start()
            self._pending = False
            return self.eta
        ratio = gnorm / self._g_prev if self._g_prev > 0.0 else 0.0
        eta = self.gamma * ratio ** self.alpha
        floor = self.gamma * self.eta ** self.alpha
        if floor > 0.1:
            eta = max(eta, floor)
        eta = min(eta, self.eta_max)
        if gnorm > 0.0:
            eta = max(eta, 0.5 * self.tol * self._g0 / gnorm)
        eta = min(max(eta, self.cg_tol), self.eta_max)
        self.eta, self._g_prev = eta, gnorm
        return eta
