"""Rigid (affine) bodies against soft ones (docs/rigid.md): a rigid ball indents a soft slab as a
very stiff soft ball does, and a soft body dropped onto a stack of rigid boxes never intersects."""

from __future__ import annotations

import numpy as np
import pytest

from warpfem import Body, Model, Plane, RigidBody, Simulator, box_tet_mesh, make_material
from warpfem.mesh.box import icosphere_surface

G = 9.81


def _slab():
    return Body(box_tet_mesh(size=(0.3, 0.04, 0.3), cells=(4, 2, 4), origin=(-0.15, 0.01, -0.15)),
                make_material("stable_neo_hookean", youngs_modulus=3e4, poisson_ratio=0.3, density=500.0), name="slab")


def _rest_indentation(ball):
    """How far the centre of the slab's top sinks below its corners under the ball, damped to
    rest. Both runs get the same barriers: the default stiffness follows the stiffest material,
    and a floor barrier as soft as the slab's default is an elastic foundation that lets the slab
    bend (with the defaults the stiff soft ball's run has a 1e4 times stiffer floor and a third of
    the indentation)."""
    m = Model.from_bodies([_slab(), ball], gravity=(0.0, -G, 0.0))
    sim = Simulator(m, dt=0.01, damping_mass=20.0, linear_solver="direct", require_convergence=True,
                    colliders=[Plane(point=(0, 0, 0), normal=(0, 1, 0), dhat=0.003, stiffness=1e3)])
    sim.set_contact(bodies=True, dhat=0.003, stiffness=2.5e7)
    slab = m.body_vertices("slab")
    rest = np.asarray(m.vertex_rest_positions)[slab]
    on_top = np.abs(rest[:, 1] - 0.05) < 1e-9
    top = slab[np.flatnonzero(on_top & (np.abs(rest[:, 0]) < 1e-9) & (np.abs(rest[:, 2]) < 1e-9))[0]]
    corners = slab[on_top & (np.abs(rest[:, 0]) > 0.149) & (np.abs(rest[:, 2]) > 0.149)]
    for _ in range(100):
        sim.step()
    assert np.abs(sim.vertex_velocities()).max() < 0.01
    X = sim.vertex_positions()
    return X[corners, 1].mean() - X[top, 1], X


def test_a_rigid_ball_indents_a_soft_slab_as_a_very_stiff_soft_ball_does():
    """The same ball (an icosphere, r 5 cm, 1000 kg/m^3) resting on a soft slab (E 3e4) on a floor:
    as a rigid body and as a soft body 1e5 times stiffer than the slab (tetrahedralised), the
    slab's top centre sinks by the same depth within 5 % (measured 1.78 and 1.75 mm: 1.7 % apart)."""
    pytest.importorskip("tetgen")
    from warpfem.mesh.tetrahedralization import tetrahedralize

    V, F = icosphere_surface(0.05, 2)
    V = V + np.array([0.0, 0.111, 0.0])  # 1 cm above the slab, which starts 1 cm above the floor
    rigid = RigidBody((V, F), density=1000.0, name="ball")
    soft = Body(tetrahedralize(V, F), make_material("stable_neo_hookean", youngs_modulus=3e9, poisson_ratio=0.3,
                                                     density=1000.0), name="ball")
    assert soft.mesh.total_volume() == pytest.approx(rigid.mass / 1000.0, rel=1e-9)
    d_rigid, X_rigid = _rest_indentation(rigid)
    d_soft, X_soft = _rest_indentation(soft)
    assert d_rigid > 1e-3  # the ball does press the slab in
    assert d_rigid == pytest.approx(d_soft, rel=0.05)


def test_a_soft_box_dropped_onto_a_stack_of_rigid_boxes_never_intersects():
    """Two rigid boxes stacked on a floor (friction 0.5) and a soft box dropped 2 cm onto them:
    no intersection at any step (IPC Toolkit's test on the vertices), every step converged, the
    stack stays upright (its boxes' A within 1e-2 of the identity) and the soft box ends on top."""
    ipctk = pytest.importorskip("ipctk")
    soft = Body(box_tet_mesh(size=(0.08, 0.04, 0.08), cells=(2, 1, 2), origin=(-0.03, 0.13, -0.05)),
                make_material("stable_neo_hookean", youngs_modulus=5e4, poisson_ratio=0.3, density=300.0), name="soft")
    low = RigidBody(box_tet_mesh(size=(0.12, 0.05, 0.12), cells=(1, 1, 1), origin=(-0.06, 0.002, -0.06)),
                    density=500.0, name="low")
    high = RigidBody(box_tet_mesh(size=(0.1, 0.05, 0.1), cells=(1, 1, 1), origin=(-0.05, 0.056, -0.05)),
                     density=500.0, name="high")
    m = Model.from_bodies([soft, low, high], gravity=(0.0, -G, 0.0))
    sim = Simulator(m, dt=0.01, require_convergence=True,
                    colliders=[Plane(point=(0, 0, 0), normal=(0, 1, 0), friction=0.5)])
    sim.set_contact(bodies=True, friction=0.5)
    F = np.asarray(m.mesh.boundary_faces())
    cm = ipctk.CollisionMesh(np.asarray(m.vertex_rest_positions, dtype=np.float64), ipctk.edges(F), F)
    for _ in range(20):
        sim.step()
        assert not ipctk.has_intersections(cm, np.asfortranarray(sim.vertex_positions()))
    for r in range(2):
        k = int(m.rigid.node_of[r])
        A = sim.positions()[k + 1:k + 4].T
        assert np.abs(A - np.eye(3)).max() < 1e-2
    X = sim.vertex_positions()
    assert X[m.body_vertices("soft"), 1].min() > X[m.body_vertices("high"), 1].max()
    assert X[m.body_vertices("high"), 1].min() > X[m.body_vertices("low"), 1].max()
