"""``Model.from_bodies`` with rigid bodies: the two spaces of such a model (docs/rigid.md).

* the **unknown** (DOF space, q): the soft bodies' vertices, then four vec3 nodes per rigid body
  (p, a_1, a_2, a_3: the centre of mass and the columns of A). This is what the simulator steps
  (``model.num_vertices``, ``rest_positions``, ``mass``, ``fixed``, its states' x and v).
* the **vertices** (vertex space, X = E q): every body's vertices in body order
  (``body_offsets``, ``mesh``), a rigid body's at p + A X_i; what the contact forms and outputs see.

Soft bodies come first, so a soft vertex has the same index in both spaces. numpy only (the device
side is :mod:`warpfem.rigid.embedding`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

from warpfem.rigid.body import RigidBody

__all__ = ["RigidLayout", "attach_rigid"]


class RigidLayout:
    """Where the rigid bodies of a model are in the two spaces, and the map E between them.

    Attributes: ``bodies`` (the :class:`RigidBody` objects), ``num_soft`` (soft vertices: the
    first rows of both spaces), ``num_dofs`` (nodes of the unknown), ``num_positions`` (vertices),
    ``node_of`` (per rigid body its first node), ``vertex_of`` (per rigid body its first vertex),
    ``names``; per vertex ``vertex_node`` (its node: itself for a soft vertex, p of its body for a
    rigid one), ``vertex_local`` (X, zero for soft vertices) and ``vertex_rigid``."""

    def __init__(self, rigid_bodies, names, num_soft, vertex_offsets):
        self.bodies, self.names = list(rigid_bodies), list(names)
        self.num_soft = int(num_soft)
        k = len(self.bodies)
        self.node_of = self.num_soft + 4 * np.arange(k, dtype=np.int64)
        self.vertex_of = np.asarray(vertex_offsets[-k - 1:-1], dtype=np.int64) if k else np.zeros(0, np.int64)
        self.num_dofs = self.num_soft + 4 * k
        self.num_positions = int(vertex_offsets[-1])
        n = self.num_positions
        self.vertex_node = np.arange(n, dtype=np.int64)
        self.vertex_local = np.zeros((n, 3))
        self.vertex_rigid = np.zeros(n, dtype=bool)
        self.vertex_body = np.full(n, -1, dtype=np.int64)  # rigid body index, -1 for soft vertices
        for r, b in enumerate(self.bodies):
            lo = int(self.vertex_of[r])
            hi = lo + len(b.local_positions)
            self.vertex_node[lo:hi] = self.node_of[r]
            self.vertex_local[lo:hi] = b.local_positions
            self.vertex_rigid[lo:hi] = True
            self.vertex_body[lo:hi] = r

    # -- the map ------------------------------------------------------------------------------------
    def vertex_weights(self):
        """(n, 4) nodes and (n, 4) weights of each vertex: x_v = sum_a w_a q[node_a] (a soft vertex:
        one node of weight 1, the other three -1 / 0; a rigid one: p, a_1, a_2, a_3 with 1, X)."""
        n = self.num_positions
        nodes = np.full((n, 4), -1, dtype=np.int64)
        w = np.zeros((n, 4))
        nodes[:, 0] = self.vertex_node
        w[:, 0] = 1.0
        r = self.vertex_rigid
        nodes[r, 1:] = self.vertex_node[r, None] + np.arange(1, 4)
        w[r, 1:] = self.vertex_local[r]
        return nodes, w

    def matrix(self):
        """E as a scipy CSR matrix (3 n_vertices x 3 n_dofs): X = E q (flat, xyz per vertex)."""
        nodes, w = self.vertex_weights()
        keep = nodes >= 0
        v = np.repeat(np.arange(self.num_positions), 4).reshape(-1, 4)[keep]
        a, wa = nodes[keep], w[keep]
        rows = (3 * v[:, None] + np.arange(3)).ravel()
        cols = (3 * a[:, None] + np.arange(3)).ravel()
        vals = np.repeat(wa, 3)
        return scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(3 * self.num_positions, 3 * self.num_dofs))

    def positions(self, q):
        """(n_vertices, 3) vertex positions (or velocities) of the unknown's values q (n_dofs, 3)."""
        q = np.asarray(q, dtype=np.float64)
        out = np.empty((self.num_positions, 3))
        out[:self.num_soft] = q[:self.num_soft]
        r = self.vertex_rigid
        base = self.vertex_node[r]
        X = self.vertex_local[r]
        out[r] = q[base] + X[:, 0:1] * q[base + 1] + X[:, 1:2] * q[base + 2] + X[:, 2:3] * q[base + 3]
        return out

    def pull_back(self, g):
        """E^T g: the gradient (n_dofs, 3) in the unknown of a function of the vertex positions
        whose gradient there is ``g`` (n_vertices, 3); e.g. a loss on ``sim.vertex_positions()``
        for :meth:`warpfem.solvers.adjoint.Recording.backward`."""
        g = np.asarray(g, dtype=np.float64).reshape(self.num_positions, 3)
        out = np.zeros((self.num_dofs, 3))
        out[:self.num_soft] = g[:self.num_soft]
        for r, b in enumerate(self.bodies):
            lo, k = int(self.vertex_of[r]), int(self.node_of[r])
            gr = g[lo:lo + len(b.local_positions)]
            out[k] = gr.sum(axis=0)
            out[k + 1:k + 4] = b.local_positions.T @ gr  # a_j: sum_i X_ij g_i
        return out

    def initial_velocity_gradients(self, v_bar):
        """((k, 3), (k, 3)): the gradients of each rigid body's ``initial_velocity`` and
        ``initial_angular_velocity`` given ``v_bar`` (n_dofs, 3), the gradient of the initial node
        velocities (p-dot = v, a_j-dot = w x e_j, so d/dw = sum_j e_j x v_bar[a_j])."""
        v_bar = np.asarray(v_bar, dtype=np.float64).reshape(self.num_dofs, 3)
        k = self.node_of
        lin = v_bar[k].copy() if len(k) else np.zeros((0, 3))
        ang = np.zeros((len(k), 3))
        for j, e in enumerate(np.eye(3)):
            ang += np.cross(e, v_bar[k + 1 + j])
        return lin, ang

    def pose(self, q, body):
        """(p, A) of rigid body ``body`` (index among the rigid bodies) in the unknown's values q."""
        k = int(self.node_of[body])
        q = np.asarray(q, dtype=np.float64)
        return q[k].copy(), np.stack([q[k + 1], q[k + 2], q[k + 3]], axis=1)

    # -- model hooks ----------------------------------------------------------------------------------
    def check_vertices(self, idx):
        """Refuse vertex indices of rigid bodies (fixed components, targets)."""
        idx = np.asarray(idx, dtype=np.int64)
        bad = idx[(idx >= self.num_soft) & (idx < self.num_positions)]
        if bad.size:
            r = int(self.vertex_body[int(bad[0])])
            raise ValueError(f"vertex {int(bad[0])} belongs to rigid body {self.names[r]!r}: a rigid body cannot have "
                             "fixed components or targets (only soft bodies can)")

    def add_force(self, forces, indices, f):
        """forces (the unknown's, (n_dofs, 3)) += E^T of the force f on each vertex of ``indices``
        (vertex space): a soft vertex's own row; a rigid vertex adds f to p and X_k f to a_k (the
        generalised force of f at x = p + A X: its resultant and its moment about the centre of mass)."""
        idx = np.atleast_1d(np.asarray(indices))
        if idx.size and idx.dtype.kind not in "iu":
            raise TypeError(f"vertex indices must be integers, got dtype {idx.dtype}")
        idx = idx.astype(np.int64).ravel()
        bad = idx[(idx < 0) | (idx >= self.num_positions)]
        if bad.size:
            raise IndexError(f"vertex index {int(bad[0])} out of range [0, {self.num_positions}) ({bad.size} bad)")
        nodes, w = self.vertex_weights()
        for v in idx:
            for a in range(4):
                if nodes[v, a] >= 0:
                    forces[nodes[v, a]] += w[v, a] * f

    def initial_velocities(self, soft_velocities):
        """(n_dofs, 3) node velocities at t = 0: the soft bodies' then each rigid body's
        (p-dot, a_k-dot = w x e_k), or None when all are zero."""
        v = np.concatenate([np.asarray(soft_velocities, dtype=np.float64).reshape(-1, 3)]
                           + [b.initial_node_velocities() for b in self.bodies])
        return v if np.any(v != 0.0) else None

    def dof_rest(self):
        """(4 k, 3) rest values of the rigid nodes: p = the centre of mass, A = I."""
        return np.concatenate([np.vstack([b.center_of_mass, np.eye(3)]) for b in self.bodies]) if self.bodies \
            else np.zeros((0, 3))


def attach_rigid(model, rigid, offsets, soft_mass):
    """The rigid bodies' part of a model's construction (``warpfem.model``, after its soft bodies:
    ``model.rest_positions`` / ``lumped_mass`` / ``gravity_mass`` hold theirs; ``offsets``: every
    body's first vertex, then the total): the layout, the unknown's four nodes per rigid body
    appended, each body's nodes as one 4-node "element" of the Hessian's pattern. Returns the mass
    matrices of the unknown's blocks (``soft_mass`` and each rigid body's 4 x 4) and every body's
    vertices at rest (``Model.vertex_rest_positions``)."""
    n_soft = len(model.rest_positions)
    layout = RigidLayout(rigid, [b.name for b in rigid], n_soft, offsets)
    model.rigid = layout
    model.dof_offsets = np.concatenate([offsets[:len(offsets) - len(rigid)],
                                        n_soft + 4 * np.arange(1, len(rigid) + 1)]).astype(np.int64)
    vertex_rest = np.concatenate([model.rest_positions] + [b.local_positions + b.center_of_mass for b in rigid])
    model.rest_positions = np.concatenate([model.rest_positions, layout.dof_rest()])
    model.extra_element_groups = [(np.asarray([np.arange(k, k + 4) for k in layout.node_of], dtype=np.int64).ravel(), 4)]
    rigid_lumped = np.concatenate([[b.mass, 0.0, 0.0, 0.0] for b in rigid])
    model.lumped_mass = np.concatenate([model.lumped_mass, rigid_lumped])
    model.gravity_mass = np.concatenate([model.gravity_mass, rigid_lumped])
    return list(soft_mass) + [scipy.sparse.csr_matrix(b.dof_mass_matrix()) for b in rigid], vertex_rest
