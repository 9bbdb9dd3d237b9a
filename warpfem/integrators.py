"""Time integrators written as one incremental-potential minimisation per step.

Every implicit scheme here solves, for the end-of-step velocity v (the unknown: an increment-sized
quantity, so float32 round-off stays small), the stationarity condition of

    E(v) = 1/2 (v - v_hat)^T M (v - v_hat) + s/2 v^T C v + V(x_b + s v) - s v^T f_ext,
    x_{n+1} = x_b + s v,

whose gradient M (v - v_hat) + s (C v - f(x_b + s v) - f_ext) = 0 is M a = f + f_ext - C v with
a = (v - v_hat) / s. The three schemes differ only in the predicted position x_b (so
x~ = x_b + s v_hat is the inertial prediction), the predicted velocity v_hat and the scale s (the
factor s^2 in front of the elastic energy in the position form 1/2 |x - x~|_M^2 + s^2 V(x)):

=================  =====================================  ===============================  ==========
scheme             x_b                                    v_hat                            s
=================  =====================================  ===============================  ==========
backward Euler     x_n                                    v_n                              h
BDF2               x_n + (x_n - x_{n-1}) / 3              v_n + (v_n - v_{n-1}) / 3        2h/3
Newmark (1/4,1/2)  x_n + h/2 v_n                          v_n + h/2 a_n                    h/2
=================  =====================================  ===============================  ==========

BDF2 (the second-order backward differentiation formula applied to x' = v, M v' = f) takes one
backward Euler step first (and after any change of state or step size). Newmark's average
acceleration rule (beta = 1/4, gamma = 1/2: x_{n+1} = x_n + h v_n + h^2/4 (a_n + a_{n+1}),
v_{n+1} = v_n + h/2 (a_n + a_{n+1})) is the trapezoidal rule: x_{n+1} = x_n + h/2 (v_n + v_{n+1}).
It needs a_n; at the start (and after a change of state) a_0 solves M a_0 = f(x_0) + f_ext - C v_0
on the free components. Newmark conserves the energy of an undamped linear system exactly and is
A-stable but not L-stable (stiff modes are not damped); BDF2 is L-stable and damps high
frequencies, less than backward Euler (Hairer & Wanner, "Solving Ordinary Differential Equations
II"; Hughes, "The Finite Element Method", ch. 9).

An integrator object keeps the history its scheme needs (x_{n-1}, v_{n-1} or a_n) on the device.
The simulator asks it for ``predict(sim)`` -> (x_b, v_hat, s) before a step and calls
``advance(sim, v)`` with the converged velocity after it; nothing is written before the solve
succeeds, so a failed step leaves the state (and the history) as it was.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Integrator", "BackwardEuler", "BDF2", "Newmark", "Static", "INTEGRATOR_NAMES", "make_integrator"]


class Integrator:
    """Base class: an implicit one-step (or two-step) scheme as a velocity-form minimisation.

    It talks to its simulator through a small interface, so the same objects drive the full-space
    simulators (device vec3 arrays) and the reduced one (numpy coordinate vectors):
    ``sim._istate() -> (x, v)``, ``sim._iset_state(x, v)``, ``sim._ivec()`` (a new zero vector),
    ``sim._ilincomb(a, x, b, y, out)`` (out = a x + b y), ``sim.dt`` and, for Newmark,
    ``sim._equation_of_motion_acceleration(out)``."""

    name = "integrator"
    order = 1
    dynamic = True

    def __init__(self):
        self._h = None

    def reset(self):
        """Forget the history (called when positions/velocities are set from outside)."""
        self._h = None

    def predict(self, sim):
        """(x_b, v_hat, s) for the coming step of ``sim`` (read-only for the caller)."""
        raise NotImplementedError

    def advance(self, sim, v, prediction):
        """Accept the converged end-of-step velocity ``v`` of the step ``prediction`` (what
        :meth:`predict` returned): set the simulator's state and the history."""
        raise NotImplementedError

    def __repr__(self):
        return f"{type(self).__name__}()"


class BackwardEuler(Integrator):
    """Backward (implicit) Euler: first order, L-stable; damps a mode of angular frequency w by
    1 / (1 + (w h)^2) in energy per step."""

    name = "backward_euler"
    order = 1

    def predict(self, sim):
        x, v = sim._istate()
        return x, v, sim.dt

    def advance(self, sim, v, prediction):
        xb, _, s = prediction
        x_new = sim._ivec()
        sim._ilincomb(1.0, xb, s, v, x_new)
        sim._iset_state(x_new, v)


class BDF2(Integrator):
    """Second-order backward differentiation formula (first step: backward Euler). L-stable.

    Per step, a linear mode of angular frequency w is multiplied by the root of largest modulus of
    (3/2 - i w h) z^2 - 2 z + 1/2 = 0 (its energy by |z|^2)."""

    name = "bdf2"
    order = 2

    def predict(self, sim):
        x, v = sim._istate()
        if self._h is None or self._h != sim.dt:  # first step, new state or new step size
            self._h = None
            return x, v, sim.dt
        # x_b = x_n + (x_n - x_{n-1}) / 3 (the difference first: keeps float32 round-off small)
        xb, vh = sim._ivec(), sim._ivec()
        sim._ilincomb(1.0, x, -1.0, self._x_prev, xb)
        sim._ilincomb(1.0, x, 1.0 / 3.0, xb, xb)
        sim._ilincomb(1.0, v, -1.0, self._v_prev, vh)
        sim._ilincomb(1.0, v, 1.0 / 3.0, vh, vh)
        return xb, vh, 2.0 * sim.dt / 3.0

    def advance(self, sim, v, prediction):
        xb, _, s = prediction
        x_old, v_old = sim._istate()
        x_new = sim._ivec()
        sim._ilincomb(1.0, xb, s, v, x_new)
        sim._iset_state(x_new, v)
        self._x_prev, self._v_prev = x_old, v_old
        self._h = sim.dt


class Newmark(Integrator):
    """Newmark's average-acceleration rule (beta = 1/4, gamma = 1/2; the trapezoidal rule): second
    order, A-stable, conserves the energy of undamped linear systems, does not damp stiff modes."""

    name = "newmark"
    order = 2

    def predict(self, sim):
        x, v = sim._istate()
        if self._h is None:  # a_0 from the equations of motion
            a = sim._ivec()
            sim._equation_of_motion_acceleration(a)
            self._a, self._h = a, sim.dt
        h = sim.dt
        xb, vh = sim._ivec(), sim._ivec()
        sim._ilincomb(1.0, x, 0.5 * h, v, xb)
        sim._ilincomb(1.0, v, 0.5 * h, self._a, vh)
        return xb, vh, 0.5 * h

    def advance(self, sim, v, prediction):
        xb, vh, s = prediction
        x_new, a_new = sim._ivec(), sim._ivec()
        sim._ilincomb(1.0, xb, s, v, x_new)
        sim._ilincomb(1.0 / s, v, -1.0 / s, vh, a_new)  # a_{n+1} = (v - v_hat) / s
        sim._iset_state(x_new, v)
        self._a = a_new
        self._h = sim.dt


class Static(Integrator):
    """Quasi-static equilibrium each step (no inertia): for scenes, ``type = "static"``."""

    name = "static"
    dynamic = False


INTEGRATOR_NAMES = ("backward_euler", "bdf2", "newmark")
_CLASSES = {"backward_euler": BackwardEuler, "bdf2": BDF2, "newmark": Newmark}


def make_integrator(spec) -> Integrator:
    """An :class:`Integrator` from a name ("backward_euler", "bdf2", "newmark") or an instance
    (returned as is). Raises ValueError naming the choices for anything else."""
    if isinstance(spec, Integrator):
        if not spec.dynamic:
            raise ValueError("the static integrator is run with Simulator.solve_static(), not as a time integrator")
        return spec
    if isinstance(spec, str) and spec in _CLASSES:
        return _CLASSES[spec]()
    raise ValueError(f"integrator must be one of {', '.join(repr(n) for n in INTEGRATOR_NAMES)} or a "
                     f"warpfem.integrators.Integrator, got {spec!r}")


def bdf2_amplification(wh: float) -> complex:
    """The principal root z of (3/2 - i w h) z^2 - 2 z + 1/2 = 0: BDF2's per-step factor on a mode
    e^{i w t} of x'' = -w^2 x (written as the first-order system x' = v, v' = -w^2 x)."""
    roots = np.roots([1.5 - 1j * wh, -2.0, 0.5])
    return complex(roots[np.argmax(np.abs(roots))])


def newmark_amplification(wh: float) -> complex:
    """Trapezoidal rule's per-step factor on e^{i w t}: (1 + i w h / 2) / (1 - i w h / 2), modulus 1."""
    return complex((1 + 0.5j * wh) / (1 - 0.5j * wh))


def backward_euler_amplification(wh: float) -> complex:
    """Backward Euler's per-step factor on e^{i w t}: 1 / (1 - i w h)."""
    return complex(1.0 / (1.0 - 1j * wh))
