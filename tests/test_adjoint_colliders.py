"""Gradients through box and mesh colliders, rotating colliders and friction on spheres, boxes and
meshes (``warpfem.solvers.adjoint_contact``: complex-step derivatives of the host contact
gradient) against central finite differences, float64, over 10 steps with the barrier active in
every step (asserted): the collider's translation (its geometry shifted), its rotation angle
(``rotation_angle`` about ``rotation_axis``, ramped: the per-step ``collider_rotations`` chained
by the schedule), its friction coefficient and the body's initial velocity.

The body is the 12-vertex tet box of tests/test_adjoint.py, thrown at a collider below it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import warpfem as wf
from gradient_checks import assert_central_differences
from warpfem.solvers.adjoint import Recording

STEPS, DT = 10, 0.01
MESH = wf.box_tet_mesh(size=(0.2, 0.1, 0.1), cells=(2, 1, 1))
N = MESH.num_vertices
RNG = np.random.default_rng(5)
W = RNG.standard_normal((STEPS + 1, N, 3))
SOLVER = dict(linear_solver="direct", linear_solver_options={"backend": "superlu"}, tol=1e-12, max_iters=300)

# a valley of four triangles under the body (slopes 0.05 meeting along x = 0.1)
_VX = np.array([[-0.3, -0.3, 0.008], [0.1, -0.3, -0.012], [0.5, -0.3, 0.008],
                [-0.3, 0.4, 0.008], [0.1, 0.4, -0.012], [0.5, 0.4, 0.008]])
_VT = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])

CASES = {
    # name: (collider keywords given a shift of its geometry, rotation axis, angle (deg), initial velocity)
    "box": (lambda sh: dict(type="box", box_min=tuple(np.array([-0.3, -0.3, -0.3]) + sh),
                            box_max=tuple(np.array([0.5, 0.4, -0.012]) + sh)),
            (0.3, 0.2, 1.0), 3.0, (0.4, 0.1, -0.3)),
    # the same, its top ending under the body (x = 0.19): the vertices at x = 0.2 meet its edge
    "box_edge": (lambda sh: dict(type="box", box_min=tuple(np.array([-0.3, -0.3, -0.3]) + sh),
                                 box_max=tuple(np.array([0.19, 0.4, -0.008]) + sh)),
                 (0.3, 0.2, 1.0), 3.0, (-0.05, 0.1, -0.3)),
    "sphere": (lambda sh: dict(type="sphere", center=tuple(np.array([0.1, 0.0, -0.207]) + sh), radius=0.2),
               (0.0, 0.3, 1.0), 10.0, (0.2, 0.1, -0.3)),
    "mesh": (lambda sh: dict(type="mesh", vertices=_VX, triangles=_VT, offset=tuple(sh)),
             (0.1, 0.0, 1.0), 5.0, (0.3, 0.1, -0.3)),
}


def go(case, shift=np.zeros(3), angle=None, mu=0.3, dv=np.zeros((N, 3)), grads=False):
    geom, axis, angle0, v0 = CASES[case]
    angle = angle0 if angle is None else angle
    model = wf.Model(MESH, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, 0.0, -9.81))
    # friction_iterations=0: friction lagged once from the step start, as recorded steps do
    sim = wf.Simulator(model, dt=DT, integrator="backward_euler", friction_iterations=0, **SOLVER)
    sim.set_velocities(np.tile(v0, (N, 1)) + dv)
    sim.add_collider(**geom(shift), stiffness=1e4, dhat=0.01, friction=mu, rotation_axis=axis, rotation_angle=angle,
                     ramp_time=STEPS * DT, name=case)
    xs, active, edge_steps = [sim.positions()], [], 0
    rec = Recording(sim)
    with rec if grads else _null():
        for _ in range(STEPS):
            assert sim.step().converged
            xs.append(sim.positions())
            active.append(sim.contact.barrier_energy() > 0.0)  # a vertex within dhat of the collider
            if case == "box_edge":  # a vertex within dhat of the top's edge, beyond the face (local frame)
                R, p = sim.contact.colliders[0].pose(sim.time)
                q = (xs[-1] - p) @ R
                near = (q[:, 0] > 0.19) & (np.hypot(q[:, 0] - 0.19, q[:, 2] + 0.008) < 0.01)
                edge_steps += bool(near.any())
    loss = float(sum(np.sum(w * x) for w, x in zip(W, xs)))
    if not grads:
        return loss
    assert all(active), active  # contact in every step
    assert case != "box_edge" or edge_steps >= 3, edge_steps  # the box's edge region acts too
    return loss, rec.backward({k: W[k] for k in range(STEPS + 1)})


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        pass


@pytest.mark.parametrize("case", list(CASES))
def test_collider_pose_and_friction_gradients_match_central_differences(case):
    _, g = go(case, grads=True)
    axis = np.asarray(CASES[case][1], dtype=np.float64)
    axis /= np.linalg.norm(axis)
    d3, D = np.array([0.3, -0.2, 1.0]), RNG.standard_normal((N, 3))
    # the pose at the end of step k is rotated by f_k x angle (f_k = (k + 1) / STEPS, the ramp): d/d(angle in deg)
    rot = sum(((k + 1) / STEPS) * math.radians(1.0) * float(np.dot(axis, r[case]))
              for k, r in g["collider_rotations"].items() if case in r)
    assert g["collider_friction"][case] != 0.0 and rot != 0.0
    checks = {
        "translation": (sum(float(np.dot(t[case], d3)) for t in g["collider_translations"].values() if case in t),
                        lambda h: go(case, shift=h * d3), 3e-7),
        "rotation_angle": (rot, lambda h: go(case, angle=CASES[case][2] + h), 1e-4),
        "friction": (g["collider_friction"][case], lambda h: go(case, mu=0.3 + h), 1e-5),
        "initial_velocities": (float(np.sum(g["initial_velocities"] * D)), lambda h: go(case, dv=h * D), 1e-6),
    }
    assert_central_differences(checks, case)
