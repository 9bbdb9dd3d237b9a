"""The Newton step test (``NewtonOptions.step_tol``): a solve also stops after a full step whose
Newton direction moves no vertex faster than step_tol body diagonals per second, never before
friction's lag update; off by default."""

import numpy as np
import pytest

from test_contact import G
from warpfem.contact import Plane
from warpfem.materials import make_material
from warpfem.mesh import box_tet_mesh
from warpfem.model import Model
from warpfem.simulator import Simulator
from warpfem.solvers.nonlinear import NewtonOptions

STEPS = 24
DT = 1 / 240


def _drop(step_tol, steps=STEPS):
    """A soft box landing sliding on a floor with friction (lands in step ~3): per step (Newton
    iterations, reason, lag updates) and the final positions."""
    mesh = box_tet_mesh(size=(0.2, 0.2, 0.2), cells=(2, 2, 2))
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
              gravity=(0.0, 0.0, -G))
    sim = Simulator(m, dt=DT, max_iters=100, step_tol=step_tol)
    sim.add_collider(Plane(point=(0, 0, -0.02), normal=(0, 0, 1), friction=0.3))
    sim.set_velocities(np.tile([0.3, 0.0, -1.0], (m.num_vertices, 1)))
    out = []
    for _ in range(steps):
        st = sim.step()
        assert st.converged
        out.append((st.newton_iterations, st.reason, st.friction_iterations))
    return out, sim.positions(), float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))


def test_step_tol_must_be_non_negative():
    with pytest.raises(ValueError, match="step_tol must be >= 0"):
        NewtonOptions(step_tol=-1e-3).validate()
    assert NewtonOptions().step_tol == 0.0  # off by default


def test_step_test_stops_after_the_lag_update_and_stays_close():
    """With step_tol = 1e-2 L/s some steps stop by the step test (fewer Newton iterations in all);
    (measured: 8 of 24 steps, 108 Newton iterations against 117); every such step made its
    friction lag update first; and the positions after 0.1 s differ from the default's by less than
    one step's limit step_tol x L x h (measured 6.4e-7 m against 1.4e-5 m); off (0, the default),
    no step stops by it."""
    base, x0, L = _drop(0.0)
    assert not any("step_tol" in r for _, r, _ in base)
    tol_v = 1e-2
    test, x1, _ = _drop(tol_v)
    by_step = [(n, lag) for n, r, lag in test if "step_tol" in r]
    assert len(by_step) >= 3
    assert all(lag >= 1 for _, lag in by_step)  # never before the lag update
    assert sum(n for n, _, _ in test) < sum(n for n, _, _ in base)
    assert np.abs(x1 - x0).max() < tol_v * L * DT
