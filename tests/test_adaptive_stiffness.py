"""Adaptive barrier stiffness (``stiffness = "auto"``, warpfem.contact.stiffness): its bounds and
initial value against IPC Toolkit's (``ipctk.initial_barrier_stiffness``, with this project's
energy being 1/s^2 of the paper's), the doubling rule, and runs with it: a heavy block resting on
a floor collider (kappa doubles while its gap shrinks below 0.01 dhat; the contact forces carry
m g) and two boxes colliding (never intersecting, momentum conserved). The measured effect on
iterations: docs/contact.md, "Adaptive barrier stiffness"."""

import numpy as np
import pytest

import warpfem as wf
from tiny_scenes import soft_box_toml
from warpfem.contact.stiffness import (MAX_FACTOR, SHRINK_FRACTION, AdaptiveStiffness, barrier_second_derivative,
                                       min_stiffness, parse_stiffness)

ipctk = pytest.importorskip("ipctk")


def test_barrier_curvature_and_initial_stiffness_match_ipctk():
    b = ipctk.ClampedLogBarrier()
    for d, dh in ((0.3, 1.0), (1e-6, 2e-3), (0.9e-3, 1e-3)):
        assert barrier_second_derivative(d, dh) == pytest.approx(b.second_derivative(d, dh), rel=1e-12)
    rng = np.random.default_rng(3)
    diag, dhat, mass, s = 0.7, 4e-3, 0.02, 1.0 / 120.0
    g_b = rng.standard_normal(60) * 1e-6
    for scale in (1e-9, 1e-3, 1e3):  # balance below, inside and above the bounds
        g_e = -scale * g_b + 1e-8 * rng.standard_normal(60)
        ours = AdaptiveStiffness(mass, diag, dhat, squared=True)
        ours.initial(s)
        k = ours.begin_step(s, 0.5 * dhat, g_e, g_b)  # a contact starts
        # IPC Toolkit's potential is s^2 x ours: its gradient of the rest is s^2 g_e, its kappa s^2 ours
        k_ipc, k_max = ipctk.initial_barrier_stiffness(diag, b, dhat, mass, s * s * g_e, g_b)
        assert k * s * s == pytest.approx(k_ipc, rel=1e-9)
        assert ours.kappa_max * s * s == pytest.approx(k_max, rel=1e-9)
    assert ours.kappa_max == pytest.approx(MAX_FACTOR * min_stiffness(mass, diag, dhat, s, squared=True))
    # the collider barrier on the distance itself: kappa_min b''(d0) = 1e11 m / s^2 at d0 = 1e-8 diagonal
    kc = min_stiffness(mass, diag, dhat, s, squared=False)
    assert kc * barrier_second_derivative(1e-8 * diag, dhat) * s * s == pytest.approx(1e11 * mass, rel=1e-12)


def test_doubling_rule_and_contact_episodes():
    a = AdaptiveStiffness(0.01, 1.0, 1e-3, squared=False)
    kmin = a.initial(0.01)
    assert a.begin_step(0.01, 2e-3) == kmin  # no contact
    g_b = np.array([0.0, -1.0, 0.0])
    k0 = a.begin_step(0.01, 5e-4, np.array([0.0, 10.0 * kmin, 0.0]), g_b)  # a contact starts: balanced
    assert k0 == pytest.approx(10.0 * kmin)
    eps = SHRINK_FRACTION * 1e-3
    assert not a.update(2.0 * eps)            # above the threshold: kept
    assert a.update(0.9 * eps) and a.kappa == 2.0 * k0   # below it and shrinking: doubled
    assert not a.update(0.95 * eps)           # below it but growing: kept
    assert a.update(0.5 * eps) and a.kappa == 4.0 * k0
    for _ in range(10):
        a.update(a.d_prev * 0.5)
    assert a.kappa == a.kappa_max             # capped
    # the contact goes on: kept, even if the balance would ask for more
    assert a.begin_step(0.01, 1e-4, np.array([0.0, 1e6 * kmin, 0.0]), g_b) == a.kappa_max
    a.kappa = 3.0 * kmin
    assert a.begin_step(0.01, 1e-4, np.array([0.0, 1e6 * kmin, 0.0]), g_b) == 3.0 * kmin
    assert a.begin_step(0.01, 5e-3) == 3.0 * kmin  # the last step touched: kept one more step
    assert a.begin_step(0.01, 5e-3) == kmin         # a step without contact: back to kappa_min
    assert parse_stiffness("auto") == (True, None) and parse_stiffness(None) == (False, None)
    assert parse_stiffness(5) == (False, 5.0)
    for bad in ("stiff", -1.0, float("nan")):
        with pytest.raises(ValueError, match="stiffness"):
            parse_stiffness(bad)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_heavy_block_on_floor_adaptive_kappa_doubles_and_carries_the_weight(precision):
    L, rho = 0.1, 20000.0
    mesh = wf.box_tet_mesh(size=(L, L, L), cells=(2, 2, 2), origin=(0.0, 0.008, 0.0))  # above dhat: kappa_min
    m = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e6, poisson_ratio=0.3, density=rho),
                 gravity=(0.0, -9.81, 0.0))
    sim = wf.Simulator(m, dt=0.01, precision=precision, damping_mass=20.0, max_iters=100)
    sim.add_collider(wf.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0), stiffness="auto", name="floor"))
    a = sim.contact.stiffness[0]
    dhat = float(sim.contact.dhat[0])
    adaptations = 0
    for _ in range(40):
        st = sim.step()
        assert st.converged
        assert sim.contact.distances().min() > 0.0
        assert a.kappa_min <= sim.contact.kappa[0] <= a.kappa_max
        adaptations += st.adaptations
    assert a.doublings >= 1 and adaptations >= 1
    assert sim.contact.kappa[0] > a.kappa_min
    # at rest, the contact forces (with the final kappa) carry the weight
    f = sim.contact.forces().sum(axis=0)
    weight = rho * L ** 3 * 9.81
    assert f[1] == pytest.approx(weight, rel=5e-3)
    assert abs(f[0]) < 1e-3 * weight and abs(f[2]) < 1e-3 * weight
    assert 0.0 < sim.contact.distances().min() < 5.0 * SHRINK_FRACTION * dhat  # measured 0.019 dhat


def test_two_boxes_collide_with_adaptive_stiffness_never_intersecting():
    a = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(0.0, 0.0, 0.0))
    b = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(0.02, 0.105, 0.01))
    na = len(a.vertices)
    mesh = wf.TetMesh(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.tets, b.tets + na]))
    m = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                 gravity=(0.0, 0.0, 0.0))
    sim = wf.Simulator(m, dt=0.01, integrator="newmark", tol=1e-8, max_iters=100)
    sc = sim.set_contact(stiffness="auto")
    assert sc.adaptive and sc.kappa == pytest.approx(sc.stiffness.kappa_min)
    v = np.zeros((m.num_vertices, 3))
    v[na:, 1] = -1.0
    sim.set_velocities(v)
    M = m.lumped_mass
    P0 = (M[:, None] * v).sum(axis=0)
    F = np.asarray(mesh.boundary_faces())
    cm = ipctk.CollisionMesh(np.asarray(mesh.vertices, dtype=np.float64), ipctk.edges(F), F)
    for _ in range(6):
        assert sim.step().converged
        assert not ipctk.has_intersections(cm, np.asfortranarray(sim.positions()))
        P = (M[:, None] * sim.velocities()).sum(axis=0)
        assert np.abs(P - P0).max() <= 1e-9 * np.abs(P0).max()
        assert sc.stiffness.kappa_min <= sc.kappa <= sc.stiffness.kappa_max
    assert sim.velocities()[:na, 1].mean() < -0.3  # they collided


_SCENE = soft_box_toml(origin=(0.0, 0.01, 0.0)) + """[[collider]]
type = "plane"
name = "floor"
normal = [0.0, 1.0, 0.0]
stiffness = {collider}
[contact]
self = true
stiffness = {contact}
[output]
frames = 1
"""


def test_scene_stiffness_auto_reaches_both_contacts_and_bad_values_are_named(tmp_path):
    from warpfem.scenes import SceneError, load_scene

    p = tmp_path / "s.toml"
    p.write_text(_SCENE.format(collider='"auto"', contact='"auto"'))
    scene = load_scene(str(p))
    assert "barrier stiffness adaptive" in scene.describe()
    run = scene.build()
    assert run.sim.surface_contact.adaptive and run.sim.contact.stiffness[0] is not None
    p.write_text(_SCENE.format(collider="2000.0", contact="1e6"))
    run = load_scene(str(p)).build()
    assert not run.sim.surface_contact.adaptive and run.sim.surface_contact.kappa == 1e6
    assert run.sim.contact.stiffness == [None] and run.sim.contact.kappa[0] == 2000.0
    p.write_text(_SCENE.format(collider='"soft"', contact='"auto"'))
    with pytest.raises(SceneError, match="stiffness"):
        load_scene(str(p))


def test_a_failed_step_leaves_the_adaptive_stiffness_as_it_was():
    from warpfem.solvers.nonlinear import SolveFailed

    L = 0.1
    mesh = wf.box_tet_mesh(size=(L, L, L), cells=(2, 2, 2), origin=(0.0, 0.008, 0.0))
    m = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e6, poisson_ratio=0.3, density=20000.0),
                 gravity=(0.0, -9.81, 0.0))
    sim = wf.Simulator(m, dt=0.01, damping_mass=20.0, max_iters=100, require_convergence=True)
    sim.add_collider(wf.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0), stiffness="auto", name="floor"))
    a = sim.contact.stiffness[0]
    for _ in range(4):
        sim.step()
    before, x0, k0 = a.state(), sim.positions(), float(sim.contact.kappa[0])
    sim.options.max_iters = 2  # the landing step (kappa doubles in it) cannot converge
    with pytest.raises(SolveFailed):
        sim.step()
    assert a.doublings >= 1  # it doubled during the failed solve ...
    assert a.state() == before and float(sim.contact.kappa[0]) == k0  # ... and was restored with the state
    assert np.array_equal(sim.positions(), x0)
    sim.options.max_iters = 100
    assert sim.step().adaptations == 1 and sim.contact.kappa[0] == 2.0 * k0
