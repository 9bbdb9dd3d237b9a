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

An integrator object is stateless configuration: the history its scheme needs (x_{n-1}, v_{n-1} or
a_n, and the step size it was taken with) lives in the step's state (``state.history``, a dict), so
one step is a function ``(state_in, dt) -> state_out`` that never writes its input. The simulator
asks ``predict(state, dt, ops, work)`` -> :class:`Prediction` (x_b, v_hat, s) before a step and
calls ``advance(state_in, v, prediction, dt, ops, state_out)`` with the converged velocity after
it; nothing is written before the solve succeeds, so a failed step leaves the state (and the
history) as it was.

Each scheme also owns its reverse, the transposed predict and advance that the adjoint
(``warpfem.solvers.adjoint``) applies to adjoint vectors, so the adjoint has no table of schemes:
``reverse_record(state, dt, host)`` says before a step which variant it takes (e.g. BDF2's first,
backward Euler step), its scale s and the history it reads (host copies);
``reverse_complete(record, state_out, host)`` adds what the step wrote that the reverse needs;
``recorded_v_hat(record)`` is the step's predicted velocity; ``advance_reverse(record, xbar, vbar,
hbar)`` maps the adjoints of the step's output (x_{n+1}, v_{n+1}, history) to those of the converged
velocity, of x_b and of v_hat; ``predict_reverse(record, xb_bar, vhat_bar, xn_bar, vn_bar, ops)``
adds the adjoints of x_b and v_hat into those of x_n, v_n and returns the adjoint of the input
history (Newmark's a_0 goes through ``ops.acceleration_reverse``, the reverse of
``ops.acceleration``). The reverse works on host float64 numpy arrays of shape (n, 3).

``ops`` is the vector algebra of the simulator (:class:`VectorOps`): device vec3 arrays for the
full-space simulators, numpy coordinate vectors for the reduced one. Buffers are taken from
``work`` (the prediction's) and from ``state_out.history`` (the history), each made once with
``ops.new_vector()`` on first use and reused by every later step (no allocation per step).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Integrator", "BackwardEuler", "BDF2", "Newmark", "Static", "INTEGRATOR_NAMES", "make_integrator",
           "Prediction", "VectorOps"]


class Prediction(NamedTuple):
    """What a step's incremental potential needs from the integrator: x = x_b + s v, the
    predicted velocity v_hat (inertia: 1/2 |v - v_hat|_M^2) and the scale s (the weight of the
    damping and load terms and the chain factor of the terms in x)."""

    xb: object
    v_hat: object
    s: float


class VectorOps:
    """The vector algebra an integrator uses (implemented by each simulator):
    ``new_vector()`` (a zero vector, only called on first use of a buffer), ``lincomb(a, x, b, y,
    out)`` (out = a x + b y; out may alias x or y), ``copy(dst, src)``, and for Newmark
    ``acceleration(state, out)`` (M a = f + f_ext - C v on the free components). The reverse
    pass's algebra (the adjoint) provides ``acceleration_reverse(record, a_bar, xn_bar, vn_bar,
    v_hat)``: the adjoint of that solve, added into ``xn_bar`` and ``vn_bar``."""

    def new_vector(self):  # pragma: no cover - interface
        raise NotImplementedError

    def lincomb(self, a, x, b, y, out):  # pragma: no cover - interface
        raise NotImplementedError

    def copy(self, dst, src):  # pragma: no cover - interface
        raise NotImplementedError

    def acceleration(self, state, out):  # pragma: no cover - interface
        raise NotImplementedError


def _buffer(store: dict, name: str, ops):
    """store[name], made with ops.new_vector() on first use."""
    b = store.get(name)
    if b is None:
        b = store[name] = ops.new_vector()
    return b


class Integrator:
    """Base class: an implicit one-step (or two-step) scheme as a velocity-form minimisation.

    Stateless: the history is in ``state.history`` (see the module docstring), so one instance
    may drive any number of simulators."""

    name = "integrator"
    order = 1
    dynamic = True

    def reset(self):
        """Kept for compatibility: the history lives in the state (clear ``state.history``)."""

    def predict(self, state, dt, ops, work) -> Prediction:
        """(x_b, v_hat, s) for a step of ``dt`` from ``state`` (read-only for the caller)."""
        raise NotImplementedError

    def advance(self, state_in, v, prediction, dt, ops, state_out):
        """Write the end-of-step state of the converged velocity ``v`` into ``state_out`` (its x,
        v and history); ``state_in`` is only read."""
        raise NotImplementedError

    def _end_state(self, v, prediction, ops, state_out):
        xb, _, s = prediction
        ops.lincomb(1.0, xb, s, v, state_out.x)
        ops.copy(state_out.v, v)

    # -- reverse (the adjoint of a step: warpfem.solvers.adjoint) -----------------------------------
    #: whether the scheme provides its reverse (the reverse_* / *_reverse methods below)
    reversible = False

    def reverse_record(self, state, dt, host):
        """(variant, s, history) of a step of ``dt`` from ``state``: the name of the variant of the
        scheme the step takes, its scale s and host copies (``host(array)``) of the history it reads."""
        raise NotImplementedError(f"{type(self).__name__} has no reverse (gradients)")

    def reverse_complete(self, record, state_out, host):
        """Keep on ``record`` what the step wrote that the reverse needs (nothing by default)."""

    def recorded_v_hat(self, record):
        """The predicted velocity v_hat of the recorded step (host)."""
        raise NotImplementedError(f"{type(self).__name__} has no reverse (gradients)")

    def advance_reverse(self, record, xbar, vbar, hbar):
        """The transposed advance: from the adjoints of x_{n+1} = x_b + s y, v_{n+1} = y and of the
        output history ``hbar`` (a dict), (ybar, xb_bar, vhat_bar, xn_bar, vn_bar): the adjoints of
        the converged velocity y, of x_b and v_hat, and what the output history adds to those of x_n
        and v_n. The base class is the end state shared by every scheme (no history)."""
        n = xbar.shape[0]
        return vbar + record.s * xbar, xbar.copy(), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))

    def predict_reverse(self, record, xb_bar, vhat_bar, xn_bar, vn_bar, ops) -> dict:
        """The transposed predict: add the adjoints of x_b and v_hat into ``xn_bar`` and ``vn_bar``
        (in place) and return the adjoint of the input history (a dict). ``ops`` is the adjoint's
        algebra (``acceleration_reverse``)."""
        raise NotImplementedError(f"{type(self).__name__} has no reverse (gradients)")

    def __repr__(self):
        return f"{type(self).__name__}()"


class BackwardEuler(Integrator):
    """Backward (implicit) Euler: first order, L-stable; damps a mode of angular frequency w by
    1 / (1 + (w h)^2) in energy per step."""

    name = "backward_euler"
    order = 1

    def predict(self, state, dt, ops, work):
        return Prediction(state.x, state.v, dt)

    def advance(self, state_in, v, prediction, dt, ops, state_out):
        self._end_state(v, prediction, ops, state_out)
        state_out.history.clear()

    reversible = True

    def reverse_record(self, state, dt, host):
        return "be", dt, {}

    def recorded_v_hat(self, record):
        return record.v

    def predict_reverse(self, record, xb_bar, vhat_bar, xn_bar, vn_bar, ops):
        xn_bar += xb_bar  # x_b = x_n, v_hat = v_n
        vn_bar += vhat_bar
        return {}


class BDF2(Integrator):
    """Second-order backward differentiation formula (first step: backward Euler). L-stable.

    Per step, a linear mode of angular frequency w is multiplied by the root of largest modulus of
    (3/2 - i w h) z^2 - 2 z + 1/2 = 0 (its energy by |z|^2)."""

    name = "bdf2"
    order = 2

    def predict(self, state, dt, ops, work):
        hist = state.history
        if hist.get("h") != dt or "x_prev" not in hist:  # first step, new state or step size: backward Euler
            return Prediction(state.x, state.v, dt)
        # x_b = x_n + (x_n - x_{n-1}) / 3 (the difference first: keeps float32 round-off small)
        xb, vh = _buffer(work, "xb", ops), _buffer(work, "v_hat", ops)
        ops.lincomb(1.0, state.x, -1.0, hist["x_prev"], xb)
        ops.lincomb(1.0, state.x, 1.0 / 3.0, xb, xb)
        ops.lincomb(1.0, state.v, -1.0, hist["v_prev"], vh)
        ops.lincomb(1.0, state.v, 1.0 / 3.0, vh, vh)
        return Prediction(xb, vh, 2.0 * dt / 3.0)

    def advance(self, state_in, v, prediction, dt, ops, state_out):
        hist = state_out.history
        xp, vp = _buffer(hist, "x_prev", ops), _buffer(hist, "v_prev", ops)
        ops.copy(xp, state_in.x)
        ops.copy(vp, state_in.v)
        self._end_state(v, prediction, ops, state_out)
        hist["h"] = dt

    reversible = True

    def reverse_record(self, state, dt, host):
        hist = state.history
        if hist.get("h") != dt or "x_prev" not in hist:  # as predict: a backward Euler step
            return "bdf2_first", dt, {}
        return "bdf2", 2.0 * dt / 3.0, {"x_prev": host(hist["x_prev"]), "v_prev": host(hist["v_prev"])}

    def recorded_v_hat(self, record):
        if record.kind == "bdf2_first":
            return record.v
        return record.v + (record.v - record.hist["v_prev"]) / 3.0

    def advance_reverse(self, record, xbar, vbar, hbar):
        ybar, xb_bar, vhat_bar, xn_bar, vn_bar = super().advance_reverse(record, xbar, vbar, hbar)
        xn_bar += hbar.get("x_prev", 0.0)  # the output history is (x_n, v_n)
        vn_bar += hbar.get("v_prev", 0.0)
        return ybar, xb_bar, vhat_bar, xn_bar, vn_bar

    def predict_reverse(self, record, xb_bar, vhat_bar, xn_bar, vn_bar, ops):
        if record.kind == "bdf2_first":
            xn_bar += xb_bar
            vn_bar += vhat_bar
            return {}
        # x_b = 4/3 x_n - 1/3 x_{n-1}, v_hat = 4/3 v_n - 1/3 v_{n-1}
        xn_bar += (4.0 / 3.0) * xb_bar
        vn_bar += (4.0 / 3.0) * vhat_bar
        return {"x_prev": -xb_bar / 3.0, "v_prev": -vhat_bar / 3.0}


class Newmark(Integrator):
    """Newmark's average-acceleration rule (beta = 1/4, gamma = 1/2; the trapezoidal rule): second
    order, A-stable, conserves the energy of undamped linear systems, does not damp stiff modes."""

    name = "newmark"
    order = 2

    def predict(self, state, dt, ops, work):
        hist = state.history
        if "a" in hist:
            a = hist["a"]
        else:  # a_0 from the equations of motion (into the work buffer: the state is not written)
            a = _buffer(work, "a0", ops)
            ops.acceleration(state, a)
        xb, vh = _buffer(work, "xb", ops), _buffer(work, "v_hat", ops)
        ops.lincomb(1.0, state.x, 0.5 * dt, state.v, xb)
        ops.lincomb(1.0, state.v, 0.5 * dt, a, vh)
        return Prediction(xb, vh, 0.5 * dt)

    def advance(self, state_in, v, prediction, dt, ops, state_out):
        _, vh, s = prediction
        a_new = _buffer(state_out.history, "a", ops)
        ops.lincomb(1.0 / s, v, -1.0 / s, vh, a_new)  # a_{n+1} = (v - v_hat) / s
        self._end_state(v, prediction, ops, state_out)
        state_out.history["h"] = dt

    reversible = True

    def reverse_record(self, state, dt, host):
        hist = state.history
        if "a" in hist:
            return "newmark", 0.5 * dt, {"a": host(hist["a"])}
        return "newmark_a0", 0.5 * dt, {}  # a_0 from the equations of motion at x_n

    def reverse_complete(self, record, state_out, host):
        record.v_hat = record.y - record.s * host(state_out.history["a"])  # a_{n+1} = (y - v_hat) / s

    def recorded_v_hat(self, record):
        return record.v_hat

    def advance_reverse(self, record, xbar, vbar, hbar):
        ybar, xb_bar, vhat_bar, xn_bar, vn_bar = super().advance_reverse(record, xbar, vbar, hbar)
        if "a" in hbar:  # a_{n+1} = (y - v_hat) / s
            ybar = ybar + hbar["a"] / record.s
            vhat_bar -= hbar["a"] / record.s
        return ybar, xb_bar, vhat_bar, xn_bar, vn_bar

    def predict_reverse(self, record, xb_bar, vhat_bar, xn_bar, vn_bar, ops):
        h = record.dt  # x_b = x_n + h/2 v_n, v_hat = v_n + h/2 a
        xn_bar += xb_bar
        vn_bar += 0.5 * h * xb_bar + vhat_bar
        a_bar = 0.5 * h * vhat_bar
        if record.kind == "newmark":
            return {"a": a_bar}
        # a_0 from M a_0 = f(x_n) + c f_ext - alpha M v_n (free components)
        ops.acceleration_reverse(record, a_bar, xn_bar, vn_bar, self.recorded_v_hat(record))
        return {}


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
