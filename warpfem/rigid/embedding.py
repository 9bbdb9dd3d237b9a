"""Rigid bodies in a simulator: the map E from the unknown to the vertices on the device, the
vertex space the contact forms see, and the orthogonality form (docs/rigid.md).

A model with rigid bodies (:mod:`warpfem.rigid.model`) is stepped in its unknown q (soft vertices,
then four nodes p, a_1, a_2, a_3 per rigid body); the time integrators act on q unchanged (they
are linear in it). The contact forms are written for vertex positions: each is built on a
:class:`VertexSpace` (what a form asks of "the simulator": model, ops, system, x, time, ... in
vertex space) and put in the potential wrapped in an :class:`EmbeddedForm`, which evaluates it at
X = E x, maps its gradient back as E^T g_v and its Hessian blocks H_ij as sum_ab w_ia w_jb H_ij
into the unknown's pattern, and bounds the line search along E d. E is linear, so x_b, s, y and d
map the same way. Without rigid bodies none of this exists (no pass, no buffer).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels.generic import launch
from warpfem.rigid import kernels as RK
from warpfem.solvers.forms import Form, StepContext
from warpfem.solvers.sparse import BlockPattern, HessianSystem
from warpfem.solvers.state import DeviceVectors, State
from warpfem.transfer import read, to_device

__all__ = ["RigidSystem", "VertexSpace", "EmbeddedForm", "OrthogonalityForm", "attach"]


def _i32(a, device):
    return to_device(np.ascontiguousarray(a, dtype=np.int32).ravel(), wp.int32, device)


class RigidSystem:
    """A simulator's rigid bodies: the device map E (``embed``, ``gather``), the vertex space of
    the contact forms (``space``) and the orthogonality form (``form``)."""

    def __init__(self, sim, layout):
        self.sim, self.layout = sim, layout
        dev, ops = sim.device, sim.ops
        self.device = dev
        n_v, n_q = layout.num_positions, layout.num_dofs
        self._node = _i32(layout.vertex_node, dev)
        self._rigid = _i32(layout.vertex_rigid, dev)
        self._local = to_device(layout.vertex_local.astype(ops.np_dtype), ops.vec, dev)
        start = np.arange(n_q, dtype=np.int64)
        count = np.ones(n_q, dtype=np.int64)
        comp = np.zeros(n_q, dtype=np.int64)
        for r, b in enumerate(layout.bodies):
            k = int(layout.node_of[r])
            start[k:k + 4] = layout.vertex_of[r]
            count[k:k + 4] = len(b.local_positions)
            comp[k:k + 4] = np.arange(4)
        self._start, self._count, self._comp = _i32(start, dev), _i32(count, dev), _i32(comp, dev)
        self.num_positions, self.num_dofs = n_v, n_q
        self.space = VertexSpace(sim, self)
        self.form = OrthogonalityForm(sim, layout)
        self._hmap = None  # (vertex pattern, unknown pattern, device arrays) of the Hessian map
        self.space.system.listeners.append(self._vertex_pattern_grew)

    # -- the map --------------------------------------------------------------------------------------
    def embed(self, q, out):
        """out (vertex space) := E q."""
        launch(RK.embed_kernel, self.num_positions, [q, self._node, self._rigid, self._local, out], self.device)
        return out

    def gather(self, gv, g):
        """g (unknown) += E^T gv (a fixed-order sum per node)."""
        launch(RK.gather_kernel, self.num_dofs, [gv, self._start, self._count, self._comp, self._local, g], self.device)

    def _node_pairs(self, rows, cols):
        """(k, 4, 4) node pairs and weight products of vertex blocks (rows, cols)."""
        nodes, w = self._weights()
        A = np.broadcast_to(nodes[rows][:, :, None], (len(rows), 4, 4))
        B = np.broadcast_to(nodes[cols][:, None, :], (len(rows), 4, 4))
        W = w[rows][:, :, None] * w[cols][:, None, :]
        return A, B, W

    def _weights(self):
        if getattr(self, "_w", None) is None:
            self._w = self.layout.vertex_weights()
        return self._w

    def _vertex_pattern_grew(self, pattern):
        """The vertex space's pattern grew (contact pairs): the unknown's pattern gets the node pairs
        the new blocks map to."""
        p = pattern.extra_pairs
        if len(p):
            A, B, _ = self._node_pairs(p[:, 0], p[:, 1])
            ok = (A >= 0) & (B >= 0)
            self.sim.system.ensure_blocks(np.stack([A[ok], B[ok]], axis=1))

    def map_hessian(self, hv, values):
        """values (the unknown's pattern) += the vertex-space blocks hv mapped through E."""
        pv, pq = self.space.system.pattern, self.sim.system.pattern
        if self._hmap is None or self._hmap[0] is not pv or self._hmap[1] is not pq:
            A, B, W = self._node_pairs(pv.rows_np.astype(np.int64), pv.cols_np.astype(np.int64))
            src = np.broadcast_to(np.arange(pv.nnz)[:, None, None], A.shape)
            ok = (A >= 0) & (B >= 0)
            pos = pq.pair_index(np.stack([A[ok], B[ok]], axis=1))
            if np.any(pos < 0):
                raise RuntimeError("rigid bodies: a contact block maps outside the Hessian's pattern")
            order = np.argsort(pos, kind="stable")
            pos, src, W = pos[order], src[ok][order], W[ok][order]
            targets, first = np.unique(pos, return_index=True)
            start = np.append(first, len(pos))
            dev, ops = self.device, self.sim.ops
            self._hmap = (pv, pq, len(targets), _i32(targets, dev), _i32(start, dev), _i32(src, dev),
                          to_device(W.astype(ops.np_dtype), ops.scalar, dev))
        _, _, k, t, st, src, w = self._hmap
        launch(RK.hessian_map_kernel, k, [hv, t, st, src, w, values], self.device)

    # -- contact forms --------------------------------------------------------------------------------
    def wrap(self, form):
        """A vertex-space form (built on :attr:`space`) as a form of the unknown."""
        return None if form is None else EmbeddedForm(form, self)

    def vertex_positions(self, q=None):
        """(n_vertices, 3) numpy: every body's vertices (rigid ones at p + A X) of the unknown's
        values q (device array or numpy; default the simulator's current positions)."""
        q = self.sim.x if q is None else q
        return self.layout.positions(read(q) if hasattr(q, "numpy") else q)


class _VertexModel:
    """The vertex-space view of a model with rigid bodies (what the contact set-up reads)."""

    def __init__(self, model, layout):
        self._model = model
        self.mesh, self.rest_positions = model.mesh, model.vertex_rest_positions
        self.material, self.total_mass = model.material, model.total_mass
        self.num_vertices = layout.num_positions
        self.body_offsets, self.body_names, self.bodies = model.body_offsets, model.body_names, model.bodies
        self.quadratures = list(model.quadratures)
        self.quadrature = model.quadrature
        self._layout = layout

    @property
    def fixed(self):
        """(vertices, 3) fixed components in vertex space, from the model's current ones: a soft
        vertex's own, a rigid body's vertex all three when a node of the body is fixed (a kinematic
        body, prescribed each step)."""
        lay = self._layout
        f = np.zeros((self.num_vertices, 3), dtype=bool)
        f[:lay.num_soft] = self._model.fixed[:lay.num_soft]
        for r, b in enumerate(lay.bodies):
            k, lo = int(lay.node_of[r]), int(lay.vertex_of[r])
            if self._model.fixed[k:k + 4].any():
                f[lo:lo + len(b.local_positions)] = True
        return f

    def vertex_bodies(self):
        return self.mesh.vertex_bodies()

    def boundary_edges(self):
        return self.mesh.boundary_edges()

    @property
    def num_bodies(self):
        return len(self.body_names)


class VertexSpace:
    """The vertex space of a simulator with rigid bodies, seen by the contact forms as their
    simulator: ``model`` (vertex-space mesh, rest positions, material, mass), ``device``,
    ``precision``, ``dt``, ``num_vertices``, ``ops``, ``system`` (a vertex-space Hessian pattern:
    its diagonal blocks and the contact pairs), ``x`` (E of the simulator's positions), ``time``
    and ``positions()``."""

    def __init__(self, sim, rigid):
        self.sim, self.rigid = sim, rigid
        ops = sim.ops
        self.device, self.precision = sim.device, sim.precision
        self.num_vertices = n = rigid.num_positions
        self.ops = DeviceVectors(n, sim.device, (ops.scalar, ops.vec, ops.mat, ops.np_dtype))
        self.model = _VertexModel(sim.model, rigid.layout)
        self.system = HessianSystem(BlockPattern(np.zeros(0, dtype=np.int64), 1, n, device=sim.device, block_type=ops.mat))
        self.system.new_values("hessian")
        self._x = self.ops.new_vector()

    @property
    def dt(self):
        return self.sim.dt

    @property
    def time(self):
        return self.sim.time

    @property
    def x(self):
        """E x of the simulator's current state (a buffer of this space, recomputed on each access)."""
        return self.rigid.embed(self.sim.x, self._x)

    def positions(self):
        return read(self.x).astype(np.float64)


class EmbeddedForm(Form):
    """A form of vertex positions (a contact form built on a :class:`VertexSpace`) as a form of
    the unknown: evaluated at X = E x (and E y, E x_b: E is linear), gradient E^T g_v, Hessian
    blocks mapped through E, line-search bound along E d. Friction's direction filter is not
    applied through E (the Newton direction is kept as it is)."""

    variable = "x"

    def __init__(self, inner, rigid):
        self.inner, self.rigid = inner, rigid
        self.name, self.order = inner.name, getattr(inner, "order", 100)
        self.weight = getattr(inner, "weight", 1.0)
        self.newton_iterations = getattr(inner, "newton_iterations", None)
        self.lag_below = getattr(inner, "lag_below", Form.lag_below)
        ops = rigid.space.ops
        self._xv, self._yv, self._dv, self._gv = (ops.new_vector() for _ in range(4))
        self._sx, self._sv, self._sxb, self._sf = (ops.new_vector() for _ in range(4))
        self._ctx = None

    @property
    def contact(self):
        return self.inner.contact

    def _map(self, q, buf):
        return None if q is None else self.rigid.embed(q, buf)

    def bind(self, acc, slot):
        self.acc_slot = int(slot)
        self.inner.bind(acc, slot)

    def enabled(self):
        return self.inner.enabled()

    def read(self, row):
        return self.inner.read(row)

    def gradient_magnitude(self, row, scale):
        return self.inner.gradient_magnitude(row, scale)

    def energy(self, y, x, acc):
        self.inner.energy(self._map(y, self._yv), self._map(x, self._xv), acc)

    def gradient(self, y, x, scale, g, acc):
        gv = self._gv
        gv.zero_()
        self.inner.gradient(self._map(y, self._yv), self._map(x, self._xv), scale, gv, acc)
        self.rigid.gather(gv, g)

    def hessian(self, y, x, scale, values):
        hv = self.rigid.space.system.hessian_values
        hv.zero_()
        self.inner.hessian(self._map(y, self._yv), self._map(x, self._xv), scale, hv)
        self.rigid.map_hessian(self.rigid.space.system.hessian_values, values)

    def max_step(self, x, d, s, acc):
        self.inner.max_step(self._map(x, self._xv), self._map(d, self._dv), s, acc)

    def begin_step(self, ctx):
        if getattr(self.inner, "adaptive_stiffness", None) is not None and self.inner.adaptive_stiffness():
            raise ValueError(f"{self.name}: stiffness 'auto' is not available with rigid bodies; give a number")
        st = ctx.state
        vstate = State(self.rigid.embed(st.x, self._sx), self.rigid.embed(st.v, self._sv), dict(st.history), st.time)
        space = self.rigid.space
        self._ctx = StepContext(state=vstate, t0=ctx.t0, t1=ctx.t1, dt=ctx.dt,
                                xb=self._map(ctx.xb, self._sxb), s=ctx.s,
                                fixed=self._map(ctx.fixed, self._sf), mask=None, ops=space.ops,
                                static=ctx.static, label=ctx.label)
        self.inner.begin_step(self._ctx)

    def check_start(self, x, ctx):
        self.inner.check_start(self._map(x, self._xv), self._ctx)

    def uses_lagging(self):
        return self.inner.uses_lagging()

    def update_lagging(self, x, **kw):
        return self.inner.update_lagging(self._map(x, self._xv), **kw)

    def state_dict(self):
        return self.inner.state_dict()

    def load_state_dict(self, state):
        self.inner.load_state_dict(state)

    def static_error(self):
        return self.inner.static_error()


class OrthogonalityForm(Form):
    """kappa V ||A^T A - I||_F^2 per rigid body, a form of x (the nodes a_1, a_2, a_3 = A's columns;
    ||A^T A - I|| = ||A A^T - I||). Gradient 4 kappa V A C (C = A^T A - I); Hessian blocks
    4 kappa V (C+_mn I + delta_mn A A^T + a_n a_m^T): the Gauss-Newton part (PSD) plus the
    curvature term with C clamped to its PSD part C+, so the sum is PSD (docs/rigid.md)."""

    name = "rigid"
    variable = "x"
    order = 5  # after the elastic form, before contact

    def __init__(self, sim, layout):
        dev, ops = sim.device, sim.ops
        self.sim, self.layout, self.device, self.ops = sim, layout, dev, ops
        self.num_bodies = len(layout.bodies)
        self._node = _i32(layout.node_of, dev)
        kv = np.array([b.stiffness * b.volume for b in layout.bodies])
        self._kv = to_device(kv.astype(ops.np_dtype), ops.scalar, dev)
        self.project = True
        self._pattern = None
        self._blocks = None

    def _block_positions(self):
        pt = self.sim.system.pattern
        if self._pattern is not pt:
            m, n = np.meshgrid(np.arange(1, 4), np.arange(1, 4), indexing="ij")
            k = self.layout.node_of[:, None, None]
            pos = pt.pair_index(np.stack([(k + m).ravel(), (k + n).ravel()], axis=1))
            if np.any(pos < 0):
                raise RuntimeError("rigid bodies: the Hessian's pattern lacks a rigid body's blocks")
            self._blocks, self._pattern = _i32(pos, self.device), pt
        return self._blocks

    def energy(self, y, x, acc):
        launch(RK.orthogonality_energy_kernel, self.num_bodies, [x, self._node, self._kv, acc, self.acc_slot], self.device)

    def gradient(self, y, x, scale, g, acc):
        launch(RK.orthogonality_gradient_kernel, self.num_bodies,
               [x, self._node, self._kv, self.ops.scalar(scale), g, acc, self.acc_slot + 2], self.device)

    def hessian(self, y, x, scale, values):
        launch(RK.orthogonality_hessian_kernel, self.num_bodies,
               [x, self._node, self._kv, self.ops.scalar(scale), self._block_positions(), int(self.project), values],
               self.device)

    def gradient_magnitude(self, row, scale):
        return float(np.sqrt(max(float(row[2]), 0.0)))

    def static_error(self):
        return ("solve_static does not handle rigid bodies (a rigid body's motion is held only by its inertia); "
                "use a time integrator")


def attach(sim):
    """The :class:`RigidSystem` of a simulator whose model has rigid bodies; its orthogonality
    form joins the potential (``sim.add_form``)."""
    rs = RigidSystem(sim, sim.model.rigid)
    sim.add_form(rs.form)
    return rs
