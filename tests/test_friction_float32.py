"""float32 impacts with friction converge with the float32 default friction velocity.

With eps_v = 1e-3 body diagonals per second (float64's default) the sticking force's round-off
in float32 sits above the Newton loop's floor at impacts: a soft box dropped on a floor with
mu = 0.3 had 3 of 20 steps stop at max_iters (docs/contact.md, "Friction in float32"). float32's
default is 1e-2, and every step converges."""

import numpy as np
import pytest

import warpfem as wf
from warpfem.contact.contact import FRICTION_VELOCITY, default_friction_velocity


def test_float32_default_friction_velocity_is_ten_times_float64s():
    assert default_friction_velocity(2.0, "float32") == pytest.approx(10 * default_friction_velocity(2.0, "float64"))
    assert FRICTION_VELOCITY["float64"] == 1e-3


def test_float32_impact_with_friction_converges_every_step():
    mesh = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(6, 6, 6))
    model = wf.Model(mesh, wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.4, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    sim = wf.Simulator(model, dt=1 / 240, integrator="newmark", precision="float32", max_iters=100)
    x = sim.positions()
    floor_y = float(x[:, 1].min()) - 5e-4
    sim.add_collider(wf.Plane(point=(0.0, floor_y, 0.0), normal=(0.0, 1.0, 0.0), friction=0.3, name="floor"))
    sim.set_velocities(np.tile([0.3, -1.4, 0.0], (len(x), 1)))
    contact_steps = 0
    for k in range(20):
        st = sim.step()
        assert st.converged, (k, st.reason, st.newton_iterations)
        x = sim.positions()
        assert x[:, 1].min() > floor_y  # never inside the floor
        contact_steps += int(x[:, 1].min() - floor_y < float(sim.contact.dhat[0]))
    assert contact_steps >= 4  # the impact steps are in the run
