"""Surface contact (body-body and self): pair distances, barrier, derivatives and the CCD step
bound against IPC Toolkit (ipctk) and finite differences; collisions that never intersect
(checked by ipctk.has_intersections), conserve momentum and never gain energy; every linear
solver on the grown pattern; the ``set_contact`` keys."""

import re

import numpy as np
import pytest

from tiny_scenes import soft_box_toml
from warpfem.contact import Plane
from warpfem.contact.surface import pair_terms
from warpfem.materials import make_material
from warpfem.mesh import TetMesh, box_tet_mesh
from warpfem.model import Model
from warpfem.simulator import Simulator

ipctk = pytest.importorskip("ipctk")

DHAT, KAPPA = 0.5, 3.0


def _ipc_reference(kind, x, rest):
    """Distance, energy kappa m b(d^2, dhat^2), gradient and Hessian composed from ipctk's pieces."""
    x = [np.asarray(p, dtype=np.float64) for p in x]
    if kind == "pt":
        d, gd, Hd = (ipctk.point_triangle_distance(*x), ipctk.point_triangle_distance_gradient(*x),
                     ipctk.point_triangle_distance_hessian(*x))
        m, gm, Hm = 1.0, np.zeros(12), np.zeros((12, 12))
    else:
        d, gd, Hd = (ipctk.edge_edge_distance(*x), ipctk.edge_edge_distance_gradient(*x),
                     ipctk.edge_edge_distance_hessian(*x))
        ex = ipctk.edge_edge_mollifier_threshold(*[np.asarray(p, dtype=np.float64) for p in rest])
        m, gm, Hm = (ipctk.edge_edge_mollifier(*x, ex), ipctk.edge_edge_mollifier_gradient(*x, ex),
                     ipctk.edge_edge_mollifier_hessian(*x, ex))
    t = DHAT ** 2
    b, b1, b2 = ipctk.barrier(d, t), ipctk.barrier_first_derivative(d, t), ipctk.barrier_second_derivative(d, t)
    E = KAPPA * m * b
    g = KAPPA * (m * b1 * gd + b * gm)
    H = KAPPA * (m * (b2 * np.outer(gd, gd) + b1 * Hd) + b1 * (np.outer(gm, gd) + np.outer(gd, gm)) + b * Hm)
    return np.sqrt(d), E, g, H


def _cases():
    """Pairs within dhat covering the closest-feature cases (face / edge / vertex interiors)."""
    tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    pts = {"pt-face": [0.2, 0.3, 0.2], "pt-edge": [0.5, -0.2, 0.15], "pt-vertex": [-0.2, -0.1, 0.1],
           "pt-hyp-edge": [0.7, 0.6, -0.1]}
    out = [(name, "pt", np.array([p] + tri), None) for name, p in pts.items()]
    ea = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    eb = {"ee-interior": [[0.4, -0.5, 0.2], [0.6, 0.5, 0.25]], "ee-edge-vertex": [[1.1, -0.5, 0.1], [1.2, 0.5, 0.1]],
          "ee-vertex-vertex": [[1.2, 0.1, 0.1], [1.5, 0.4, 0.1]],
          "ee-near-parallel": [[0.2, 0.05, 0.2], [0.9, 0.051, 0.2003]]}
    for name, e in eb.items():
        x = np.array(ea + e)
        rest = x + np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0.0, 0.1, 0.0]])  # eps_x from the rest shape
        out.append((name, "ee", x, rest))
    return out


@pytest.mark.parametrize("name,kind,x,rest", _cases(), ids=[c[0] for c in _cases()])
def test_pair_barrier_and_derivatives_match_ipctk(name, kind, x, rest):
    d, E, g, H = _ipc_reference(kind, list(x), list(rest if rest is not None else x))
    assert d < DHAT
    o = pair_terms(kind, x, dhat=DHAT, kappa=KAPPA, rest=rest)
    assert o["distance"] == pytest.approx(d, rel=1e-12)
    assert o["energy"] == pytest.approx(E, rel=1e-10)
    assert np.abs(o["gradient"] - g).max() <= 1e-10 * np.abs(g).max()
    assert np.abs(o["hessian"] - H).max() <= 1e-9 * np.abs(H).max()
    w, V = np.linalg.eigh(0.5 * (H + H.T))  # the per-pair PSD projection
    assert np.abs(o["hessian_psd"] - (V * np.maximum(w, 0.0)) @ V.T).max() <= 1e-9 * np.abs(H).max()
    if name == "ee-near-parallel":
        assert ipctk.edge_edge_mollifier(*x, ipctk.edge_edge_mollifier_threshold(*rest)) < 0.9  # mollified


@pytest.mark.parametrize("kind", ["pt", "ee"])
def test_pair_derivatives_match_finite_differences_in_both_precisions(kind, rng):
    x = _cases()[0 if kind == "pt" else 4][2]
    o = pair_terms(kind, x, dhat=DHAT, kappa=KAPPA)
    h = 1e-6
    gfd, Hfd = np.zeros(12), np.zeros((12, 12))
    for c in range(12):
        e = np.zeros(12)
        e[c] = h
        p = pair_terms(kind, x + e.reshape(4, 3), dhat=DHAT, kappa=KAPPA)
        m = pair_terms(kind, x - e.reshape(4, 3), dhat=DHAT, kappa=KAPPA)
        gfd[c] = (p["energy"] - m["energy"]) / (2 * h)
        Hfd[:, c] = (p["gradient"] - m["gradient"]) / (2 * h)
    assert np.abs(o["gradient"] - gfd).max() <= 1e-6 * np.abs(gfd).max()
    assert np.abs(o["hessian"] - Hfd).max() <= 1e-6 * np.abs(Hfd).max()
    o32 = pair_terms(kind, x, dhat=DHAT, kappa=KAPPA, precision="float32")
    assert o32["energy"] == pytest.approx(o["energy"], rel=1e-4)
    assert np.abs(o32["gradient"] - o["gradient"]).max() <= 1e-4 * np.abs(o["gradient"]).max()


def test_ccd_step_bound_is_below_ipctk_time_of_impact(rng):
    """Approaching pairs: the additive-CCD bound never passes ipctk's collision-free step and
    keeps at least 0.2 of the gap; pairs that do not collide get most of the step."""
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    n_hit = 0
    for trial in range(12):
        kind = "pt" if trial % 2 == 0 else "ee"
        if kind == "pt":
            x = np.vstack([[0.2 + 0.3 * rng.random(), 0.2 * rng.random(), 0.3], tri])
            V, F, E = x, np.array([[1, 2, 3]]), None
        else:
            x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, -0.5, 0.3], [0.5 + 0.2 * rng.random(), 0.5, 0.3]])
            V, F, E = x, np.zeros((0, 3), dtype=int), np.array([[0, 1], [2, 3]])
        d = 0.3 * rng.standard_normal((4, 3))
        d[0 if kind == "pt" else 2:, 2] += -0.8 if kind == "ee" else 0.0
        if kind == "pt":
            d[0, 2] -= 0.8
        mesh = ipctk.CollisionMesh(V, ipctk.edges(F) if E is None else E, F)
        t_ipc = ipctk.compute_collision_free_stepsize(mesh, V, V + d)
        o = pair_terms(kind, x, dhat=DHAT, kappa=KAPPA, direction=d)
        t = o["step"]
        assert 0.0 < t <= t_ipc + 1e-12
        d_end = pair_terms(kind, x + t * d, dhat=DHAT, kappa=KAPPA)["distance"]
        if t < 1.0:  # stopped where the gap reached 0.2 of its start (whether or not the pair collides)
            assert d_end >= 0.2 * o["distance"] * 0.999
        if t_ipc < 1.0:
            n_hit += 1
            assert t >= 0.4 * t_ipc  # not needlessly short (the gap is 0.2 of its start there)
        else:
            assert pair_terms(kind, x + d, dhat=DHAT, kappa=KAPPA)["distance"] > 0.0
    assert n_hit >= 6  # most of these pairs collide within the step


def _two_boxes(cells=2, gap=0.02, E=1e5, offset=(0.03, 0.0, 0.02)):
    a = box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(cells,) * 3, origin=(0.0, 0.0, 0.0))
    b = box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(cells,) * 3, origin=(offset[0], 0.1 + gap, offset[2]))
    V = np.concatenate([a.vertices, b.vertices])
    T = np.concatenate([a.tets, b.tets + len(a.vertices)])
    return TetMesh(V, T), len(a.vertices)


def _collision_mesh(mesh):
    F = np.asarray(mesh.boundary_faces())
    return ipctk.CollisionMesh(np.asarray(mesh.vertices, dtype=np.float64), ipctk.edges(F), F)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_two_boxes_collide_in_free_space_momentum_conserved_never_intersecting(precision):
    mesh, na = _two_boxes()
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
              gravity=(0.0, 0.0, 0.0))
    sim = Simulator(m, dt=0.01, integrator="newmark", precision=precision, tol=1e-8, max_iters=100)
    sc = sim.set_contact()
    assert sc.bodies and not sc.self_contact and sc.surface.num_groups == 2
    v = np.zeros((m.num_vertices, 3))
    v[na:, 1] = -1.0
    v[na:, 0] = 0.3
    sim.set_velocities(v)
    M = m.lumped_mass
    P0 = (M[:, None] * v).sum(axis=0)
    cm = _collision_mesh(mesh)
    touched = 0
    for _ in range(8):
        st = sim.step()
        assert st.converged
        x = sim.positions()
        assert not ipctk.has_intersections(cm, np.asfortranarray(x))
        P = (M[:, None] * sim.velocities()).sum(axis=0)
        tol = 1e-9 if precision == "float64" else 2e-4
        assert np.abs(P - P0).max() <= tol * np.abs(P0).max()
        touched += sc.num_pairs > 0
    assert touched >= 2
    vb = sim.velocities()[na:, 1].mean()
    va = sim.velocities()[:na, 1].mean()
    assert va < -0.3 and vb > -0.7  # the lower box was pushed, the upper one slowed: they did collide


def test_box_dropped_on_box_on_floor_energy_never_grows_backward_euler():
    mesh, na = _two_boxes(gap=0.01, offset=(0.02, 0.0, 0.01))
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=2e4, poisson_ratio=0.3, density=1000.0),
              gravity=(0.0, -9.81, 0.0))
    sim = Simulator(m, dt=0.01, precision="float64", tol=1e-10, max_iters=100,
                    colliders=[Plane(point=(0.0, -0.001, 0.0), normal=(0.0, 1.0, 0.0), name="floor")])
    sc = sim.set_contact(friction=0.0)
    v = np.zeros((m.num_vertices, 3))
    v[na:, 1] = -0.5
    sim.set_velocities(v)
    cm = _collision_mesh(mesh)

    def energy():
        return sim.total_energy() + sim.contact.barrier_energy() + sc.barrier_energy()

    e = [energy()]
    for _ in range(12):
        assert sim.step().converged
        assert not ipctk.has_intersections(cm, np.asfortranarray(sim.positions()))
        e.append(energy())
    e = np.array(e)
    assert np.all(np.diff(e) <= 1e-9 * np.abs(e).max())
    assert sc.min_distance() < sc.dhat  # the boxes are in contact at the end


def _u_shape(cells=(6, 4, 1)):
    """A U of two arms on a base (one connected body), arms 0.1 apart, meshed from a box."""
    box = box_tet_mesh(size=(0.3, 0.4, 0.05), cells=cells)
    X, T = np.asarray(box.vertices), np.asarray(box.tets)
    c = X[T].mean(axis=1)
    keep = ~((c[:, 0] > 0.1) & (c[:, 0] < 0.2) & (c[:, 1] > 0.1))  # cut the slot between the arms
    T = T[keep]
    used = np.unique(T)
    remap = -np.ones(len(X), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return TetMesh(X[used], remap[T])


@pytest.mark.parametrize("self_on", [True, False])
def test_u_folded_onto_itself_never_intersects_with_self_contact(self_on):
    mesh = _u_shape()
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
              gravity=(0.0, 0.0, 0.0))
    X = np.asarray(mesh.vertices)
    sim = Simulator(m, dt=0.01, precision="float64", tol=1e-8, max_iters=100, damping_mass=1.0)
    sc = sim.set_contact(**{"self": self_on})
    if not self_on:
        assert sc is None  # one body, no self contact: nothing to do
    else:
        assert sc.self_contact and not sc.bodies and sc.surface.num_groups == 1
    v = np.zeros_like(X)
    arm = X[:, 1] > 0.15
    v[arm & (X[:, 0] < 0.15), 0] = 3.0 * (X[arm & (X[:, 0] < 0.15), 1] - 0.1)  # the arms swing towards each other
    v[arm & (X[:, 0] > 0.15), 0] = -3.0 * (X[arm & (X[:, 0] > 0.15), 1] - 0.1)
    sim.set_velocities(v)
    cm = _collision_mesh(mesh)
    crossed = False
    for _ in range(8):
        sim.step()
        crossed = crossed or ipctk.has_intersections(cm, np.asfortranarray(sim.positions()))
        if self_on:
            assert not crossed
    if self_on:
        assert sc.min_distance() < sc.dhat  # the arms met
    else:
        assert crossed  # without self contact the arms pass through each other


def test_every_linear_solver_takes_the_contact_blocks():
    def run(solver):
        mesh, na = _two_boxes()
        m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                  gravity=(0.0, 0.0, 0.0))
        sim = Simulator(m, dt=0.01, integrator="backward_euler", linear_solver=solver, tol=1e-10, cg_tol=1e-12,
                        max_iters=100)
        sim.set_contact()
        nnz0 = sim.pattern.nnz
        v = np.zeros((m.num_vertices, 3))
        v[na:, 1] = -1.5
        sim.set_velocities(v)
        for _ in range(3):
            assert sim.step().converged
        assert sim.pattern.nnz > nnz0  # contact blocks between the boxes entered the pattern
        return sim.positions()

    ref = run("direct")
    for name in ("pcg", "amg", "multigrid", "auto"):
        assert np.abs(run(name) - ref).max() <= 1e-6, name


def test_set_contact_keys_are_checked():
    mesh, _ = _two_boxes()
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0))
    sim = Simulator(m, dt=0.01)
    with pytest.raises(TypeError, match="unknown key.*selff"):
        sim.set_contact(selff=True)
    with pytest.raises(ValueError, match="dhat must be > 0"):
        sim.set_contact(dhat=-1.0)
    with pytest.raises(ValueError, match="friction must be >= 0"):
        sim.set_contact(friction=-0.1)
    assert sim.set_contact(bodies=False) is None and sim.surface_contact is None
    sc = sim.set_contact(dhat=1e-3, stiffness=5.0, friction=0.2)
    assert (sc.dhat, sc.kappa, sc.friction, sc.bodies) == (1e-3, 5.0, 0.2, True)
    with pytest.raises(ValueError, match="surface contact"):
        sim.solve_static()
    from warpfem.contact import CollisionError

    touching, _ = _two_boxes(gap=0.0)  # the upper box's base on the lower box's top: pairs at distance 0
    sim2 = Simulator(Model(touching, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3,
                                                   density=1000.0)), dt=0.01)
    with pytest.raises(CollisionError, match=r"surface pairs touch now .*distance 0"):
        sim2.set_contact()
    assert sim2.surface_contact is None and not sim2.system.listeners


def _block_on_slab(mu, theta, steps):
    """A block dropped from 2 cm (above dhat) onto a fixed slab (two components of one mesh) under
    gravity tilted by theta: the slab is the incline. The block centre's position and velocity
    down the slope per step, and the first step in contact."""
    slab = box_tet_mesh(size=(0.5, 0.1, 0.3), cells=(2, 1, 1), origin=(-0.1, 0.0, -0.1))
    block = box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(0.0, 0.12, 0.0))
    ns = len(slab.vertices)
    mesh = TetMesh(np.concatenate([slab.vertices, block.vertices]), np.concatenate([slab.tets, block.tets + ns]))
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0),
              gravity=(9.81 * np.sin(theta), -9.81 * np.cos(theta), 0.0))
    m.fix(np.arange(ns))
    sim = Simulator(m, dt=0.01, max_iters=200)
    sc = sim.set_contact(friction=mu)
    assert sc.min_distance() > sc.dhat
    w = m.lumped_mass[ns:] / m.lumped_mass[ns:].sum()
    pos, vel, land = [], [], None
    for k in range(steps):
        sim.step()
        pos.append(float(w @ sim.positions()[ns:, 0]))
        vel.append(float(w @ sim.velocities()[ns:, 0]))
        if land is None and sc.num_friction > 0:
            land = k
    assert land is not None and sc.min_distance() > 0.0
    return np.array(pos), np.array(vel), land


def test_block_on_slab_friction_sticks_and_slides_with_coulomb_acceleration():
    theta = np.radians(30.0)
    p, _, land = _block_on_slab(0.8, theta, 58)
    assert land <= 7 and abs(p[land + 50] - p[land]) < 2e-3  # 0.5 s after landing
    mu = 0.3
    _, v, land = _block_on_slab(mu, theta, 40)
    a = (v[land + 30] - v[land + 10]) / 0.2
    assert a == pytest.approx(9.81 * (np.sin(theta) - mu * np.cos(theta)), rel=0.02)


_SCENE = soft_box_toml() + """[integrator]
type = "{integrator}"
[output]
frames = 1
{contact}
"""


def _scene(tmp_path, contact, integrator="backward_euler"):
    from warpfem.scenes import load_scene

    p = tmp_path / "s.toml"
    p.write_text(_SCENE.format(integrator=integrator, contact=contact))
    return load_scene(p)


def test_scene_contact_table_sets_the_simulator_and_is_validated(tmp_path):
    from warpfem.scenes import SceneError

    scene = _scene(tmp_path, "[contact]\nself = true\nfriction = 0.2\ndhat = 1e-3\nfriction_iterations = 2\n")
    assert "contact: bodies = default, self = True, friction = 0.2, dhat = 0.001" in scene.describe()
    run = scene.build()
    sc = run.sim.surface_contact
    assert sc.self_contact and not sc.bodies and (sc.friction, sc.dhat) == (0.2, 1e-3)  # one body: bodies off
    assert run.sim.friction_iterations == 2
    assert _scene(tmp_path, "").build().sim.surface_contact is None  # no [contact]: one body, nothing to do
    for text, where, what in [("[contact]\nselff = true\n", "[contact].selff", "did you mean 'self'"),
                              ("[contact]\nfriction = -1.0\n", "[contact].friction", ">= 0"),
                              ("[contact]\nbodies = 1\n", "[contact].bodies", "true or false")]:
        with pytest.raises(SceneError, match=rf"{re.escape(where)}.*{what}"):
            _scene(tmp_path, text)
    with pytest.raises(SceneError, match=r"\[contact\].*full-space dynamic integrator"):
        _scene(tmp_path, "[contact]\nself = true\n", integrator="static")


def test_bodies_of_a_multi_body_model_collide_without_intersecting():
    """Model.from_bodies: two bodies (groups from body_offsets), contact on by default; bodies that
    touch at the start are refused naming them."""
    from warpfem.contact import CollisionError
    from warpfem.model import Body

    mat = make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    cube = box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2))
    m = Model.from_bodies([Body(cube, mat, name="low"),
                           Body(cube, mat, name="high", offset=(0.02, 0.12, 0.01), initial_velocity=(0.0, -1.0, 0.0))])
    sim = Simulator(m, dt=0.01, integrator="newmark", tol=1e-8, max_iters=100)
    sc = sim.set_contact()
    assert sc.bodies and sc.surface.num_groups == 2
    F = np.asarray(m.mesh.boundary_faces())
    cm = ipctk.CollisionMesh(np.asarray(m.rest_positions, dtype=np.float64), ipctk.edges(F), F)
    for _ in range(5):
        assert sim.step().converged
        assert not ipctk.has_intersections(cm, np.asfortranarray(sim.positions()))
    lo = slice(int(m.body_offsets[0]), int(m.body_offsets[1]))
    assert sim.velocities()[lo, 1].mean() < -0.2  # the lower body was hit
    touching = Model.from_bodies([Body(cube, mat, name="low"), Body(cube, mat, name="high", offset=(0.02, 0.1, 0.01))])
    with pytest.raises(CollisionError, match="touch now between bodies 'high' and 'low'|touch now between bodies 'low' "
                                             "and 'high'"):
        Simulator(touching, dt=0.01).set_contact()


def test_a_start_through_itself_is_refused_naming_the_body_and_the_crossing():
    """The U's right arm pushed 0.13 m left through the left arm (positions set before set_contact):
    with self contact the start is refused, naming the body and an edge / triangle that ipctk agrees
    cross; the same U at rest is accepted, and without self contact nothing is checked."""
    import warpfem.mesh.intersect as I
    from warpfem.contact import CollisionError

    mesh = _u_shape()
    X = np.asarray(mesh.vertices)
    mat = make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    x = X.copy()
    x[(X[:, 0] > 0.15) & (X[:, 1] > 0.15)] += (-0.13, 0.013, 0.01)  # off the grid: crossings inside triangles
    faces = np.asarray(mesh.boundary_faces(), dtype=np.int64)
    assert ipctk.has_intersections(_collision_mesh(mesh), np.asfortranarray(x))
    c = I.self_crossing(x, faces)
    assert c is not None and not set(c.edge) & set(c.triangle)
    assert ipctk.is_edge_intersecting_triangle(x[c.edge[0]], x[c.edge[1]], *x[list(c.triangle)])
    assert sorted(faces[c.triangle_index]) == sorted(c.triangle)
    assert I.self_crossing(X, faces) is None
    m = Model(mesh, mat, gravity=(0.0, 0.0, 0.0))
    sim = Simulator(m, dt=0.01)
    sim.set_positions(x)
    with pytest.raises(CollisionError, match=re.escape(f"passes through itself: its edge {list(c.edge)}") + ".*"
                       + re.escape(f"crosses its triangle {c.triangle_index} {list(c.triangle)}")):
        sim.set_contact(**{"self": True})
    assert sim.surface_contact is None and not sim.system.listeners
    # two bodies, the second through itself: named, its own vertex indices
    from warpfem.model import Body

    two = Model.from_bodies([Body(mesh, mat, name="left", offset=(-1.0, 0.0, 0.0)), Body(mesh, mat, name="right")],
                            gravity=(0.0, 0.0, 0.0))
    sim2 = Simulator(two, dt=0.01)
    x2 = np.asarray(two.rest_positions).copy()
    x2[len(X):] = x
    sim2.set_positions(x2)
    with pytest.raises(CollisionError, match=r"body 'right' passes through itself: its edge " + re.escape(str(list(c.edge)))):
        sim2.set_contact(**{"self": True})
    assert sim2.set_contact() is not None  # bodies only: no self check


def test_self_pairs_closer_than_dhat_at_rest_get_the_step_bound_but_no_barrier(monkeypatch):
    """The U's arms are 0.1 apart; with dhat = 0.12 every pair across the slot starts inside dhat.
    Those self pairs get no barrier (energy 0 at rest, every barrier pair >= dhat apart), but the
    step bound still holds them: moving the right arm 0.15 through the left one is cut to a step
    with no intersection (ipctk), where the barrier pairs' bound alone is not. Without the rule
    (REST_GAP = 0) the same start has barrier energy: the rest shape would be pushed apart."""
    import warp as wp

    import warpfem.contact.surface as S
    from warpfem.contact import surface_kernels as SK

    mesh = _u_shape()
    X = np.asarray(mesh.vertices)
    mat = make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    sim = Simulator(Model(mesh, mat, gravity=(0.0, 0.0, 0.0)), dt=0.01)
    sc = sim.set_contact(**{"self": True}, dhat=0.12)
    assert sc.rest_gap == 0.12 and sc.num_ccd_pairs > 0
    assert sc.min_distance() >= 0.12 and sc.barrier_energy() == 0.0
    d = np.zeros_like(X)
    d[(X[:, 0] > 0.15) & (X[:, 1] > 0.15)] = (-0.15, 0.0, 0.013)
    dv = sim.ops.new_vector()
    dv.assign(d.astype(sim.ops.np_dtype))
    sc.update_pairs(sim.x, dv, 1.0)
    acc = wp.zeros(4, dtype=wp.float64)
    acc.fill_(1.0)
    sc.run(SK.MODE_MAX_STEP, sim.x, scale=1.0, d=dv, acc=acc)
    a_barrier = float(acc.numpy()[3])
    sc.run_ccd(sim.x, scale=1.0, d=dv, acc=acc)
    alpha = float(acc.numpy()[3])
    cm = _collision_mesh(mesh)
    assert ipctk.has_intersections(cm, np.asfortranarray(X + d))
    # the barrier pairs' bound alone (measured 0.71) lets the arm through; with the CCD-only pairs
    # (0.53; ipctk's collision-free step, tight-inclusion CCD: 0.67) it stays out
    assert ipctk.has_intersections(cm, np.asfortranarray(X + a_barrier * d))
    assert 0.3 < alpha < a_barrier and not ipctk.has_intersections(cm, np.asfortranarray(X + alpha * d))
    monkeypatch.setattr(S, "REST_GAP", 0.0)
    sc0 = sim.set_contact(**{"self": True}, dhat=0.12)
    assert sc0.num_ccd_pairs == 0 and sc0.min_distance() < 0.05 and sc0.barrier_energy() > 0.0  # 0.033: not only the slot


def test_the_pattern_grows_only_for_pairs_that_can_come_within_dhat(monkeypatch):
    """Two boxes colliding (Newmark, direct solver): at every Hessian evaluation each pair within
    dhat has its blocks in the pattern; some candidates never get blocks; the motion equals that of
    a run whose pattern takes every candidate's blocks (the former growth) to 1e-9 m."""
    import warpfem.contact.surface as S
    from warpfem.contact import surface_kernels as SK

    def run(eager):
        mesh, na = _two_boxes(cells=3)
        m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                  gravity=(0.0, 0.0, 0.0))
        sim = Simulator(m, dt=0.01, integrator="newmark", linear_solver="direct", tol=1e-10, max_iters=100)
        sc = sim.set_contact()
        if eager:
            monkeypatch.setattr(sc, "_grow_near", lambda x, d, s: sc._ensure(sc.pairs_np) if sc.num_pairs else None)
        active = []
        hess = S.SurfaceContactForm.hessian

        def checked(form, y, x, scale, values):
            form.contact.run(SK.MODE_DISTANCE, x)
            near = form.contact._dist.numpy()[:form.contact.num_pairs] < form.contact.dhat
            assert form.contact._has_blocks[near].all()
            active.append(int(near.sum()))
            return hess(form, y, x, scale, values)

        monkeypatch.setattr(S.SurfaceContactForm, "hessian", checked)
        v = np.zeros((m.num_vertices, 3))
        v[na:, 1] = -1.5
        sim.set_velocities(v)
        for _ in range(5):
            assert sim.step().converged
        monkeypatch.setattr(S.SurfaceContactForm, "hessian", hess)
        return sim.positions(), sc, max(active)

    x_lazy, sc, most = run(False)
    assert most > 0 and not sc._has_blocks.all()  # in contact, and some candidates without blocks
    x_eager, sc_e, _ = run(True)
    assert sc_e._has_blocks.all() and sc_e.sim.pattern.nnz > sc.sim.pattern.nnz
    assert np.abs(x_lazy - x_eager).max() <= 1e-9


def test_connected_labels_are_scipy_csgraph_components():
    """The bodies' labelling of surface contact (numpy root hooking and pointer jumping) gives the
    components of scipy.sparse.csgraph, numbered alike, on random graphs, a long shuffled path and
    isolated vertices."""
    import scipy.sparse
    import scipy.sparse.csgraph

    from warpfem.contact.surface import connected_labels

    rng = np.random.default_rng(7)
    cases = [(1, np.zeros(0, int), np.zeros(0, int))]
    for n, m in ((12, 6), (500, 400), (3000, 2990), (4000, 8000)):
        cases.append((n, rng.integers(0, n, m), rng.integers(0, n, m)))
    perm = rng.permutation(5000)
    cases.append((5000, perm[:-1], perm[1:]))
    for n, r, c in cases:
        A = scipy.sparse.coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
        k, ref = scipy.sparse.csgraph.connected_components(A, directed=False)
        got = connected_labels(n, r, c)
        assert np.array_equal(got, ref) and got.max() + 1 == k


def test_a_kinematic_box_moved_into_a_soft_block_within_one_step_fails_the_step_and_keeps_the_state():
    """A soft box held by its targets (a kinematic handle, every vertex fixed) 10 mm above a soft
    block: moved onto the block's top in one step (its bottom face on the top face: pairs at
    distance 0) or 5 mm into it (edges through triangles, every pair distance > 0), the step fails
    with a one-line error naming the bodies and a pair or an edge and a triangle, and positions,
    velocities and time are bit-identical to before the call; moved 5 mm towards it, the step
    converges (the check does not fire), and afterwards a move within the gap converges too."""
    from warpfem import Body
    from warpfem.solvers.nonlinear import SolveFailed

    mat = make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    m = Model.from_bodies([Body(box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2)), mat, name="block"),
                           Body(box_tet_mesh(size=(0.04, 0.04, 0.04), cells=(1, 1, 1), origin=(0.03, 0.03, 0.11)), mat,
                                name="box")], gravity=(0.0, 0.0, 0.0))
    box = m.body_vertices("box")
    m.fix(box)
    sim = Simulator(m, dt=0.01)
    sim.set_contact()
    X = sim.positions()

    def fails(dz, what):
        x, v, t = sim.positions(), sim.velocities(), sim.time
        sim.set_targets(box, X[box] + [0.0, 0.0, dz])
        with pytest.raises(SolveFailed) as e:
            sim.step()
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(f"step {sim.step_count}: surface contact: a kinematic body or handle "
                                                  "moved into a soft body within one step: ")
        assert re.search(what, msg) and msg.endswith("; use smaller steps or a slower motion; state left unchanged")
        assert e.value.stats.reason == "kinematic body moved into a soft body"
        assert np.array_equal(sim.positions(), x) and np.array_equal(sim.velocities(), v) and sim.time == t

    fails(-0.01, r"surface pairs at distance <= 0: \d+ \(first: (vertex-triangle|edge-edge) pair, model vertices "
                 r"\[\d+, \d+, \d+, \d+\] between bodies '(block|box)' and '(block|box)', distance 0 m\)")
    assert sim.step_count == 0
    sim.set_targets(box, X[box] + [0.0, 0.0, -0.005])
    assert sim.step().converged
    fails(-0.015, r"edge \[\d+, \d+\] of body '(block|box)' crosses triangle \[\d+, \d+, \d+\] of body '(block|box)' "
                  r"at \(.*\) m \(model vertex indices\)")
    assert sim.step_count == 1
    sim.set_targets(box, X[box] + [0.0, 0.0, -0.007])
    assert sim.step().converged and sim.surface_contact.min_distance() > 0.0
