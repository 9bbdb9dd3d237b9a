"""Several bodies in contact as scenes and at rest: the stack's rest heights from
the weights, the [contact] table of a [[body]] scene reaching the simulator, the example scenes'
contact set-up, and no intersection (IPC Toolkit as the independent judge)."""

import os

import numpy as np
import pytest

import warpfem as wf

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
H, E, RHO, G = 0.2, 1e5, 1000.0, 9.81


def _no_intersection(positions, model):
    ipctk = pytest.importorskip("ipctk")
    faces = np.asarray(model.mesh.boundary_faces(), dtype=np.int64)
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    cm = ipctk.CollisionMesh(np.asarray(model.rest_positions, dtype=np.float64), edges, faces)
    return not ipctk.has_intersections(cm, np.asarray(positions, dtype=np.float64))


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_stack_rest_heights_from_the_weights(precision):
    """Two equal cubes (side H, E 1e5, nu 0.3) stacked on a floor with friction 0.5, settled under
    mass damping. A column under its own weight shortens by rho g H^2 / (2 E); the lower cube also
    carries the upper one's weight m g over its area: + (m g / H^2) H / E. Measured: the upper cube
    to 0.2 %, the lower to 5 % (the contact pressure is not uniform), both precisions."""
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=E, poisson_ratio=0.3, density=RHO)
    box = wf.box_tet_mesh(size=(H, H, H), cells=(3, 3, 3))
    model = wf.Model.from_bodies([wf.Body(box, mat, name="lower", offset=(0.0, 0.0, 0.01)),
                                  wf.Body(box, mat, name="upper", offset=(0.0, 0.0, H + 0.025))], gravity=(0.0, 0.0, -G))
    sim = wf.Simulator(model, precision=precision, dt=0.05, damping_mass=5.0, max_iters=100)
    sim.add_collider(type="plane", point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), friction=0.5)
    sim.set_contact(friction=0.5)
    for _ in range(40):
        st = sim.step()
    assert st.converged
    x, X, off = sim.positions(), model.rest_positions, model.body_offsets
    heights = []
    for b in range(2):
        xb, Xb = x[off[b]:off[b + 1]], X[off[b]:off[b + 1]]
        top, bottom = Xb[:, 2] > Xb[:, 2].max() - 1e-9, Xb[:, 2] < Xb[:, 2].min() + 1e-9
        heights.append(xb[top, 2].mean() - xb[bottom, 2].mean())
    self_weight = RHO * G * H ** 2 / (2.0 * E)
    on_top = (RHO * H ** 3 * G / H ** 2) * H / E
    assert H - heights[1] == pytest.approx(self_weight, rel=0.02)
    assert H - heights[0] == pytest.approx(self_weight + on_top, rel=0.08)
    assert np.abs(sim.velocities()).max() < 1e-3  # at rest
    assert x[off[1]:, 2].min() > x[:off[1], 2].max() - 1e-9  # the upper cube on top, not beside
    assert _no_intersection(x, model)


def test_contact_table_of_a_bodies_scene_reaches_the_simulator(tmp_path):
    from warpfem.scenes import load_scene

    text = open(os.path.join(ROOT, "examples", "scenes", "stack.toml")).read()
    p = tmp_path / "stack.toml"
    p.write_text(text.replace("[contact]\nfriction = 0.5", "[contact]\nfriction = 0.35\ndhat = 0.004\n"
                                                             "friction_lag_below = 0.1"))
    scene = load_scene(str(p))
    assert scene.spec.contact["friction"] == 0.35
    assert "contact: bodies = default, self = False, friction = 0.35, dhat = 0.004" in scene.describe()
    run = scene.build()
    c = run.sim.surface_contact
    assert c.friction == 0.35 and c.dhat == 0.004 and c.bodies and not c.self_contact
    assert run.sim.friction_lag_below == 0.1 and run.sim.friction_update_tol == 0.0
    assert load_scene(os.path.join(ROOT, "examples", "scenes", "stack.toml")).build().sim.friction_lag_below is None
    for bad, says in (("1.5", "friction_lag_below must be in (0, 1)"), ("0.0", "friction_lag_below")):
        p.write_text(text.replace("[contact]\nfriction = 0.5", f"[contact]\nfriction = 0.5\nfriction_lag_below = {bad}"))
        with pytest.raises(Exception, match=r"\[contact\]") as err:
            load_scene(str(p)).build()
        assert says in str(err.value) and "\n" not in str(err.value).strip()


@pytest.mark.parametrize("name,bodies,self_contact", [("stack", 2, False), ("ball_bowl", 2, False),
                                                     ("bunny_octopus", 2, True), ("twisted_bar", 1, True)])
def test_example_contact_scenes_set_up_contact(name, bodies, self_contact):
    from warpfem.scenes import load_scene

    run = load_scene(os.path.join(ROOT, "examples", "scenes", f"{name}.toml")).build()
    assert run.model.num_bodies == bodies
    c = run.sim.surface_contact
    assert c is not None and c.self_contact == self_contact and c.bodies == (bodies > 1)
    assert _no_intersection(run.sim.positions(), run.model)  # the start (the runs: docs/contact.md)
    assert c.min_distance() > 0.0
    if name == "bunny_octopus":  # its scanned surfaces: 3,784 self pairs closer than dhat at rest, step bound only
        assert c.num_ccd_pairs == 3784 and c.min_distance() >= c.dhat
