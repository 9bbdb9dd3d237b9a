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


def test_direction_max_is_the_max_of_the_direction_it_is_given(monkeypatch):
    """The step test's max |d| is the one read with d's direction check (no read-back of its own in
    the Newton loop: at every call it is d's max |d| exactly); read afresh, the same Newton iterates
    bit for bit with one more read-back per call. Given another vector, or after another vector's
    direction check, it is that vector's max |d| (the one asked for)."""
    from warpfem import transfer
    from warpfem.solvers.forms import IncrementalPotential

    original = IncrementalPotential.direction_max
    seen = []

    def kept(self, y, g, d, limit=float("inf")):  # the normal flow: d's own check is kept
        assert self._checked is not None and self._checked[0] is d
        seen.append((self._checked[1], float(np.abs(d.numpy()).max())))
        return original(self, y, g, d, limit)

    def fresh(self, y, g, d, limit=float("inf")):  # d read again at every call
        self._written()
        return original(self, y, g, d, limit)

    runs = []
    for wrapper in (kept, fresh):
        monkeypatch.setattr(IncrementalPotential, "direction_max", wrapper)
        reads = transfer.COUNTERS["reads"]
        out, x, _ = _drop(1e-2, steps=8)
        runs.append((out, x, transfer.COUNTERS["reads"] - reads))
    monkeypatch.setattr(IncrementalPotential, "direction_max", original)
    (out0, x0, r0), (out1, x1, r1) = runs
    assert any("step_tol" in r for _, r, _ in out0)
    assert len(seen) >= 20 and all(a == b for a, b in seen)
    assert np.array_equal(x0, x1) and out0 == out1
    assert r1 - r0 == len(seen)

    sim = Simulator(Model(box_tet_mesh(size=(0.2, 0.2, 0.2), cells=(1, 1, 1)), make_material(
        "stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)), dt=DT, step_tol=1e-2)
    sim.step()
    p = sim._potential
    g, d, y = p.vectors()
    other = p.new_vector()
    vals = np.zeros((other.shape[0], 3))
    vals[1] = (0.1, -0.7, 0.2)
    other.assign(vals)
    d.assign(0.25 * vals)
    p.direction_check(y, g, d)
    assert p.direction_max(y, g, other, 0.0) == 0.7  # (limit 0: the unfiltered direction is not asked)
    p.direction_check(y, g, d)
    p.direction_check(y, g, other)  # a check of another vector between d's check and the step test
    assert p.direction_max(y, g, d, 0.0) == 0.25 * 0.7
