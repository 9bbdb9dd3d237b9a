"""The incremental potential of one implicit step as a sum of terms ("forms", as in PolyFEM).

Every time integrator of :mod:`warpfem.integrators` and the quasi-static solve minimise

    E(y) = sum_f E_f(y),   x(y) = x_b + s y   (static: x = y),

over the per-vertex vec3 unknowns y (the end-of-step velocity for dynamics), with the terms

* :class:`InertiaForm`      a/2 (y - y_hat)^T M (y - y_hat)
* :class:`DampingForm`      1/2 y^T (c_m M + c_k K_n) y        (Rayleigh, K_n frozen at the step start)
* :class:`ElasticForm`      V(x(y)) over the quadrature-point sets and the material
* :class:`LoadForm`         -c y^T f_ext                         (gravity, applied forces, tractions)

Each term adds its energy to float64 accumulators on the device, its gradient to g and its Hessian
into the blocks of the fixed pattern, and reports the magnitude of its terms (the scale of their
round-off). :class:`FullSpacePotential` sums them with one host read-back per energy and one per
gradient, and is the ``problem`` that :func:`warpfem.solvers.nonlinear.newton_solve` minimises.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import fem as FK
from warpfem.kernels import linalg as LK
from warpfem.kernels.generic import launch

__all__ = ["InertiaForm", "DampingForm", "ElasticForm", "LoadForm", "FullSpacePotential", "Workspace"]

# float64 accumulator slots (one small array, read back once per evaluation)
_E_QUAD, _E_ELASTIC, _E_ELASTIC_ABS, _E_WORK = 0, 1, 2, 3
_G_QUAD, _G_FORCE_ABS, _G_NORM = 4, 5, 6
_D_GD, _D_MAX, _Y_MAX, _X_MAX = 7, 8, 9, 10
_E_CONTACT = 12  # contact: energy, pairs at distance <= 0, sum of squared gradient, step bound (12..15)
_SLOTS = 16
_F64_HALF, _F64_ONE = wp.float64(0.5), wp.float64(1.0)


class Workspace:
    """Device buffers a simulator reuses for every solve (no allocation per Newton iteration)."""

    def __init__(self, sim):
        self.acc = wp.zeros(_SLOTS, dtype=wp.float64, device=sim.device)
        self.g, self.d, self.rhs, self.y_try = (sim._vec_array() for _ in range(4))
        self.x, self.tmp, self.tmp2, self.fa = (sim._vec_array() for _ in range(4))
        self.inv_diag = None  # block-Jacobi inverse for the fallback direction, allocated on first use


class InertiaForm:
    """a/2 (y - y_hat)^T M (y - y_hat): gradient a M (y - y_hat), Hessian a M."""

    def __init__(self, sim, y_hat, a=1.0):
        self.sim, self.y_hat, self.a = sim, y_hat, float(a)

    def _apply(self, y, g, acc, gradient, energy):
        sim, pt = self.sim, self.sim._pattern
        launch(LK.bsr_diff_mv_kernel, pt.num_rows, [pt.offsets, pt.columns, sim._mass_values, y, self.y_hat,
                                                    sim._s(self.a), g, acc, _E_QUAD, gradient, energy], sim.device)

    def energy(self, y, x, acc):
        self._apply(y, self.sim._work.tmp, acc, 0, 1)

    def gradient(self, y, x, g, acc):
        self._apply(y, g, acc, 1, 0)

    def hessian(self, y, x, values):
        sim = self.sim
        launch(LK.add_scaled_kernel, sim._pattern.nnz, [sim._mass_values, sim._s(self.a), values], sim.device)


class DampingForm:
    """1/2 y^T (c_m M + c_k K_n) y: Rayleigh damping C = alpha M + beta K_n scaled by the integrator's s."""

    def __init__(self, sim, cm, ck):
        self.sim, self.cm, self.ck = sim, float(cm), float(ck)

    def _apply(self, y, g, acc, gradient, energy):
        sim, pt = self.sim, self.sim._pattern
        for values, c in ((sim._mass_values, self.cm), (sim._kn_values, self.ck)):
            if c != 0.0:
                launch(LK.bsr_diff_mv_kernel, pt.num_rows, [pt.offsets, pt.columns, values, y, sim._zero, sim._s(c), g,
                                                            acc, _E_QUAD, gradient, energy], sim.device)

    def energy(self, y, x, acc):
        self._apply(y, self.sim._work.tmp, acc, 0, 1)

    def gradient(self, y, x, g, acc):
        self._apply(y, g, acc, 1, 0)

    def hessian(self, y, x, values):
        sim = self.sim
        if self.cm != 0.0:
            launch(LK.add_scaled_kernel, sim._pattern.nnz, [sim._mass_values, sim._s(self.cm), values], sim.device)
        if self.ck != 0.0:
            launch(LK.add_scaled_kernel, sim._pattern.nnz, [sim._kn_values, sim._s(self.ck), values], sim.device)


class ElasticForm:
    """V(x) summed over the simulator's quadrature-point sets; dx/dy = s: gradient s dV/dx,
    Hessian s^2 d2V/dx2 (SPD-projected per point if the options say so)."""

    def __init__(self, sim, s):
        self.sim, self.s = sim, float(s)

    def energy(self, y, x, acc):
        sim = self.sim
        for qs in sim._qp_sets:
            launch(FK.qp_energy_sum_kernel, qs.count, [x, qs.points, qs.material, acc, _E_ELASTIC], sim.device)

    def gradient(self, y, x, g, acc):
        sim = self.sim
        fa = sim._work.fa
        fa.zero_()
        for qs in sim._qp_sets:
            launch(FK.qp_force_and_abs_kernel, qs.count, [x, qs.points, qs.material, sim._s(-self.s), g, fa], sim.device)
        launch(LK.dot_slot_kernel, sim.num_vertices, [fa, fa, _F64_ONE, acc, _G_FORCE_ABS], sim.device)

    def hessian(self, y, x, values):
        self.sim._assemble_stiffness(x, self.s * self.s, values)


class LoadForm:
    """-c y^T f_ext (c = s times the load scale of the solve)."""

    def __init__(self, sim, c):
        self.sim, self.c = sim, float(c)

    def energy(self, y, x, acc):
        sim = self.sim
        launch(LK.dot_slot_kernel, sim.num_vertices, [y, sim._fext, _F64_ONE, acc, _E_WORK], sim.device)

    def gradient(self, y, x, g, acc):
        pass  # -c f_ext is added by FullSpacePotential.gradient's last pass (with the mask and the norm)

    def hessian(self, y, x, values):
        pass


class FullSpacePotential:
    """E(y) = sum of forms over the mesh's vertices, x = x_b + s y (``xb=None``: x = y).

    The ``problem`` of :func:`~warpfem.solvers.nonlinear.newton_solve`: device vectors, a masked
    block-sparse Newton system solved by the simulator's linear solver."""

    def __init__(self, sim, *, xb, s, quadratic=(), elastic=None, load=None, contact=None):
        self.sim, self.xb, self.s = sim, xb, float(s)
        self.contact = contact  # a warpfem.contact.ContactForm (barrier + friction, bounds the step) or None
        self.quadratic = tuple(quadratic)  # forms whose gradient norm forms the "quadratic" magnitude
        self.elastic, self.load = elastic, load
        self.mask, self.n = sim._mask, sim.num_vertices
        self.eps = float(np.finfo(sim._np).eps)
        self.gradient_test_below = 0.0  # see newton_solve (the reduced problem uses it)
        self._x_of_y = None

    # -- vectors ----------------------------------------------------------------------------------
    def new_vector(self):
        return self.sim._vec_array()

    def vectors(self):
        """(g, d, y_try): the simulator's work vectors for the Newton loop."""
        w = self.sim._work
        return w.g, w.d, w.y_try

    def _x_of(self, y):
        if self.xb is None:
            return y
        sim = self.sim
        x = sim._work.x
        if self._x_of_y is y:  # x already holds x_b + s y (see assign)
            return x
        launch(LK.lincomb_kernel, self.n, [sim._s(1.0), self.xb, sim._s(self.s), y, x], sim.device)
        self._x_of_y = y
        return x

    def trial(self, y, alpha, d, out):
        sim = self.sim
        launch(LK.lincomb_kernel, self.n, [sim._s(1.0), y, sim._s(alpha), d, out], sim.device)
        if self._x_of_y is out:
            self._x_of_y = None

    def assign(self, dst, src):
        wp.copy(dst, src)
        # x = x_b + s src is still in the work buffer: it is now x of dst
        self._x_of_y = dst if self._x_of_y is src else None

    # -- value, gradient, Hessian -------------------------------------------------------------------
    def energy(self, y):
        """(E, the sum of the magnitudes of its terms): one host read-back."""
        acc = self.sim._work.acc
        acc.zero_()
        x = self._x_of(y)
        for f in self.quadratic:
            f.energy(y, x, acc)
        if self.elastic is not None:
            self.elastic.energy(y, x, acc)
        if self.load is not None:
            self.load.energy(y, x, acc)
        if self.contact is not None:
            self.contact.energy(y, x, acc)
        a = acc.numpy()
        quad, V, Vabs = float(a[_E_QUAD]), float(a[_E_ELASTIC]), float(a[_E_ELASTIC_ABS])
        work = self.load.c * float(a[_E_WORK]) if self.load is not None else 0.0
        if a[_E_CONTACT + 1] > 0:  # a vertex on or inside a collider: outside the barrier's domain
            return float("inf"), float("inf")
        Ec = float(a[_E_CONTACT])
        return quad + V - work + Ec, abs(quad) + Vabs + abs(work) + Ec

    def gradient(self, y, g):
        """g = P grad E(y); returns (the sum of the norms of its terms, ||g||): one host read-back."""
        sim = self.sim
        acc = sim._work.acc
        acc.zero_()
        g.zero_()
        x = self._x_of(y)
        for f in self.quadratic:
            f.gradient(y, x, g, acc)
        if self.quadratic:
            launch(LK.dot_slot_kernel, self.n, [g, g, _F64_ONE, acc, _G_QUAD], sim.device)
        if self.elastic is not None:
            self.elastic.gradient(y, x, g, acc)
        if self.load is not None:
            self.load.gradient(y, x, g, acc)
        if self.contact is not None:
            self.contact.gradient(y, x, g, acc)
        c = self.load.c if self.load is not None else 0.0
        launch(LK.gradient_finish_kernel, self.n, [g, sim._fext, sim._s(c), self.mask, acc, _G_NORM], sim.device)
        a = acc.numpy()
        mag = np.sqrt(a[_G_QUAD]) + np.sqrt(a[_G_FORCE_ABS])
        if self.load is not None:
            mag += abs(self.load.c) * sim._fext_norm
        if self.contact is not None:
            mag += np.sqrt(a[_E_CONTACT + 2])
        return float(mag), float(np.sqrt(a[_G_NORM]))

    def assemble_hessian(self, y, values):
        values.zero_()
        x = self._x_of(y)
        for f in self.quadratic:
            f.hessian(y, x, values)
        if self.elastic is not None:
            self.elastic.hessian(y, x, values)
        if self.contact is not None:
            self.contact.hessian(y, x, values)
        return values

    def max_step(self, y, d):
        """The largest step length <= 1 along d that keeps every surface vertex outside the
        colliders (continuous collision bound; 1 without contact): one read-back."""
        if self.contact is None:
            return 1.0
        acc = self.sim._work.acc
        acc.fill_(1.0)
        self.contact.max_step(self._x_of(y), d, acc)
        return float(acc.numpy()[_E_CONTACT + 3])

    # -- Newton system ------------------------------------------------------------------------------
    def solve_newton_system(self, y, g, d, opts):
        """d ~ -H(y)^-1 g on the free components (the simulator's linear solver); returns its result
        (``iterations``, ``host_syncs``, ...)."""
        sim = self.sim
        values = self.assemble_hessian(y, sim._hess_values)
        rhs = sim._work.rhs
        launch(LK.scale_copy_kernel, self.n, [g, sim._s(-1.0), rhs], sim.device)
        return sim._linear_solve(values, rhs, d, opts)

    def fallback_direction(self, g, d):
        """d = -B^-1 g, B the (masked) block diagonal of the last Newton system: a descent direction
        whatever linear solver produced the rejected one."""
        sim = self.sim
        pt, w = sim._pattern, sim._work
        if w.inv_diag is None:
            w.inv_diag = wp.zeros(self.n, dtype=sim._mat, device=sim.device)
        launch(LK.block_jacobi_setup_kernel, self.n, [pt.offsets, pt.columns, sim._hess_values, self.mask, w.inv_diag],
               sim.device)
        launch(LK.scale_copy_kernel, self.n, [g, sim._s(-1.0), w.rhs], sim.device)
        launch(LK.block_apply_kernel, self.n, [w.inv_diag, w.rhs, d], sim.device)

    def direction_check(self, y, g, d):
        """(g . d, whether the step d is below the resolution of y and of x = x_b + s y): one read-back."""
        sim = self.sim
        acc = sim._work.acc
        acc.zero_()
        use_xb = self.xb is not None
        launch(LK.newton_check_kernel, self.n, [g, d, y, self.xb if use_xb else y, sim._s(self.s), int(use_xb), acc,
                                                _D_GD], sim.device)
        a = acc.numpy()
        scale = a[_Y_MAX] + (a[_X_MAX] / abs(self.s) if self.s != 0.0 else 0.0)
        negligible = bool(a[_D_MAX] <= 8.0 * self.eps * scale)
        return float(a[_D_GD]), negligible
