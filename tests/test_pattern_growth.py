"""A Hessian pattern that grows: a form coupling two vertices of different elements adds
off-diagonal blocks; the pattern, the value arrays and every linear solver follow.

The coupling form here is a zero-length spring between two distant vertices, written on the host
(numpy) as a user's own form would be: it checks the form interface (weights, the chain factors s
and s^2 of a form of x) and the grown pattern against a dense finite-difference Hessian of the
whole step potential, and the steps of the PCG, direct and AMG solvers against each other.
"""

import numpy as np
import pytest

import warpfem as wf
from warpfem.solvers.forms import Form

K_SPRING = 2.0e3


class PairSpring(Form):
    """k/2 |x_i - x_j - (X_i - X_j)|^2 between two vertices (a function of x)."""

    name = "spring"
    variable = "x"

    def __init__(self, sim, i, j, k=K_SPRING):
        self.sim, self.i, self.j, self.k = sim, int(i), int(j), float(k)
        X = sim.model.rest_positions
        self.rest = X[self.i] - X[self.j]

    def _d(self, x):
        P = x.numpy().astype(np.float64)
        return P[self.i] - P[self.j] - self.rest

    def extra_blocks(self):
        return np.array([[self.i, self.j]])

    def energy(self, y, x, acc):
        d = self._d(x)
        a = acc.numpy()
        a[self.acc_slot] += 0.5 * self.k * d @ d
        acc.assign(a)

    def gradient(self, y, x, scale, g, acc):
        d = self._d(x)
        G = g.numpy()
        G[self.i] += scale * self.k * d
        G[self.j] -= scale * self.k * d
        g.assign(G)

    def hessian(self, y, x, scale, values):
        i, j = self.i, self.j
        pos = self.sim.pattern.pair_index([[i, i], [j, j], [i, j], [j, i]])
        assert np.all(pos >= 0)
        V = values.numpy()
        for p, sign in zip(pos, (1.0, 1.0, -1.0, -1.0)):
            V[p] += sign * scale * self.k * np.eye(3)
        values.assign(V)


def _sim(linear_solver="pcg", **kw):
    mesh = wf.box_tet_mesh(size=(1.0, 0.25, 0.25), cells=(4, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=2e4, poisson_ratio=0.3, density=500.0),
                     gravity=(0.0, 0.0, -9.81))
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    sim = wf.Simulator(model, dt=0.02, integrator="bdf2", damping_mass=0.3, linear_solver=linear_solver, tol=1e-10,
                       cg_tol=1e-12, **kw)
    X = mesh.vertices
    i = int(np.flatnonzero((X[:, 0] > 1 - 1e-9) & (X[:, 2] > 0.25 - 1e-9))[0])  # free end, top
    j = int(np.flatnonzero((X[:, 0] > 0.5 - 1e-9) & (X[:, 0] < 0.5 + 1e-9) & (X[:, 2] < 1e-9))[0])  # middle, bottom
    return sim, i, j


def test_grown_pattern_matches_a_dense_finite_difference_hessian(rng):
    sim, i, j = _sim(project_hessian=False)  # the exact Hessian
    assert not sim.pattern.contains([[i, j]])  # no element holds both: the mesh's pattern has no block
    nnz0 = sim.pattern.nnz
    for _ in range(2):  # a moving state with BDF2 history
        sim.step()
    sim.add_form(PairSpring(sim, i, j))
    pot = sim.potential()
    assert sim.pattern.contains([[i, j]]) and sim.pattern.nnz == nnz0 + 2
    assert sim.linear_solver.analyse_count == 2
    free = (~sim.model.fixed).astype(np.float64)
    y = sim.velocities() + 0.05 * rng.standard_normal(free.shape) * free
    H = sim.pattern.to_scipy(pot.assemble_hessian(sim.new_vector(y), sim.new_matrix_values())).toarray()
    F = free.reshape(-1)
    H = H * F[:, None] * F[None, :]
    eps = 1e-6
    Hfd = np.zeros_like(H)
    gp, gm = sim.new_vector(), sim.new_vector()
    for c in np.flatnonzero(F):
        e = np.zeros(F.size)
        e[c] = eps
        pot.gradient(sim.new_vector(y + e.reshape(-1, 3)), gp)
        pot.gradient(sim.new_vector(y - e.reshape(-1, 3)), gm)
        Hfd[:, c] = (gp.numpy().reshape(-1) - gm.numpy().reshape(-1)) / (2 * eps)
    assert np.abs(H - Hfd).max() <= 1e-6 * np.abs(H).max()
    s = pot.s  # the spring's block (i, j) is -s^2 k I (chain factor of a form of x, weight 1)
    np.testing.assert_allclose(H[3 * i:3 * i + 3, 3 * j:3 * j + 3], -s * s * K_SPRING * np.eye(3), rtol=1e-12)
    # the gradient against central differences of the energy along a random direction
    dirn = rng.standard_normal(free.shape) * free
    g = sim.new_vector()
    pot.gradient(sim.new_vector(y), g)
    fd = (pot.energy(sim.new_vector(y + eps * dirn))[0] - pot.energy(sim.new_vector(y - eps * dirn))[0]) / (2 * eps)
    assert fd == pytest.approx(float((g.numpy() * dirn).sum()), rel=1e-6)


def _run(linear_solver, steps=6):
    sim, i, j = _sim(linear_solver)
    sim.step()
    sim.add_form(PairSpring(sim, i, j))
    for _ in range(steps):
        st = sim.step()
        assert st.converged
    return sim, i, j


def test_every_linear_solver_takes_the_grown_pattern():
    ref, i, j = _run("direct")
    # the direct solver analysed the mesh's pattern and the grown one: one symbolic analysis each
    assert ref.linear_solver.symbolic_count == 2 and ref.linear_solver.analyse_count == 2
    free_ref, _, _ = _sim("direct")
    for _ in range(7):
        free_ref.step()
    X = ref.model.rest_positions
    gap = lambda s: np.linalg.norm(s.positions()[i] - s.positions()[j] - (X[i] - X[j]))  # noqa: E731
    assert gap(ref) < 0.5 * gap(free_ref)  # the spring holds the free end to the middle
    for name in ("pcg", "amg", "multigrid", "auto"):
        sim, _, _ = _run(name)
        assert np.abs(sim.positions() - ref.positions()).max() <= 1e-7, name
