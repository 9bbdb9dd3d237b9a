"""A form's life cycle (warpfem.solvers.forms): a term written by a user, added with
``Simulator.add_form``, is started, checked, bounded, lagged and refused by the static solve
through its hooks alone, as the built-in contact forms are; the simulator does not know it.

The term here is a frictionless barrier against a moving plane, written in numpy in this file
(the built-in collider contact's formulas: b(d) = -(d - dhat)^2 ln(d / dhat), the step bound
keeping each vertex at least 1 - eta of its distance): it must keep every vertex above the plane
and move the body as the built-in ``Plane`` collider does.
"""

import numpy as np
import pytest

import warpfem as wf
from warpfem.solvers.forms import Form, InfeasibleStart, lagged_change
from warpfem.solvers.nonlinear import SolveFailed

ETA = 0.2  # the step bound's fraction, as the built-in contact's (warpfem.contact.contact.STEP_ETA)
DHAT, KAPPA = 4e-3, 5e3


def _barrier(d, dhat):
    t = d - dhat
    lg = np.log(d / dhat)
    return -t * t * lg, -2.0 * t * lg - t * t / d, -2.0 * lg - 4.0 * t / d + t * t / (d * d)


class PlaneBarrier(Form):
    """kappa sum_v b(n.(x_v - p(t1))) over the surface vertices, p(t) = p0 + velocity t: the plane's
    position at the end of each step (set by begin_step), a form of x; counts its hook calls."""

    name = "plane_barrier"
    variable = "x"

    def __init__(self, sim, point, normal, velocity=(0.0, 0.0, 0.0), dhat=DHAT, kappa=KAPPA):
        self.sim = sim
        self.surface = np.unique(np.asarray(sim.model.mesh.boundary_faces()))
        self.p0, self.velocity = np.asarray(point, float), np.asarray(velocity, float)
        self.n = np.asarray(normal, float) / np.linalg.norm(normal)
        self.point = self.p0.copy()
        self.dhat, self.kappa = float(dhat), float(kappa)
        self.calls = {"begin_step": 0, "check_start": 0, "max_step": 0, "energy": 0}
        self.contexts = []

    # -- life cycle ------------------------------------------------------------------------------------
    def begin_step(self, ctx):
        self.calls["begin_step"] += 1
        self.contexts.append((ctx.t0, ctx.t1, ctx.dt, ctx.s, ctx.static))
        self.point = self.p0 + self.velocity * ctx.t1

    def check_start(self, x, ctx):
        self.calls["check_start"] += 1
        d = self.distances(x)
        if d.min() <= 0.0:
            raise InfeasibleStart(f"plane barrier: {int((d <= 0).sum())} vertices behind the plane at t = {ctx.t1:g}",
                                  reason="plane moved into the body")

    def max_step(self, x, d, s, acc):
        self.calls["max_step"] += 1
        dist = self.distances(x)
        rate = -(s * d.numpy().astype(np.float64)[self.surface]) @ self.n
        pos = (dist > 0.0) & (rate > 0.0)
        alpha = np.min((1.0 - ETA) * dist[pos] / rate[pos], initial=1.0)
        if np.any(dist <= 0.0):
            alpha = 0.0
        a = acc.numpy()
        a[self.acc_slot + 3] = min(a[self.acc_slot + 3], alpha)
        acc.assign(a)

    # -- evaluation ------------------------------------------------------------------------------------
    def distances(self, x):
        return (x.numpy().astype(np.float64)[self.surface] - self.point) @ self.n

    def energy(self, y, x, acc):
        self.calls["energy"] += 1
        d = self.distances(x)
        a = acc.numpy()
        near = (d > 0.0) & (d < self.dhat)
        a[self.acc_slot] += self.kappa * _barrier(d[near], self.dhat)[0].sum()
        a[self.acc_slot + 1] += float((d <= 0.0).sum())
        acc.assign(a)

    def read(self, row):
        return float(row[0]), float(row[0]), not (row[1] > 0)

    def gradient(self, y, x, scale, g, acc):
        d = self.distances(x)
        near = (d > 0.0) & (d < self.dhat)
        gv = np.zeros((len(d), 3))
        gv[near] = (self.kappa * _barrier(d[near], self.dhat)[1])[:, None] * self.n
        G = g.numpy()
        G[self.surface] += (scale * gv).astype(G.dtype)
        g.assign(G)
        a = acc.numpy()
        a[self.acc_slot + 2] += float((gv * gv).sum()) * scale * scale
        acc.assign(a)

    def gradient_magnitude(self, row, scale):
        return float(np.sqrt(row[2]))

    def hessian(self, y, x, scale, values):
        d = self.distances(x)
        near = (d > 0.0) & (d < self.dhat)
        V = values.numpy()
        diag = np.asarray(self.sim.pattern.diag_index)[self.surface[near]]
        b2 = self.kappa * _barrier(d[near], self.dhat)[2]
        V[diag] += (scale * b2[:, None, None] * np.outer(self.n, self.n)).astype(V.dtype)
        values.assign(V)


class LagCounter(Form):
    """A zero term that lags: update_lagging returns the scripted (change, scale) pairs in turn
    (called inside the Newton solve, from iterates near the solution)."""

    name = "lag_counter"
    variable = "x"

    def __init__(self, script, lagging=True):
        self.script, self.lagging, self.updates = list(script), lagging, 0

    def uses_lagging(self):
        return self.lagging

    def update_lagging(self, x):
        self.updates += 1
        return self.script.pop(0)


class VelocityTerm(Form):
    """A form of y (the step's velocity): dynamic only by default."""

    name = "velocity_term"


def _block(origin=(0.0, 0.006, 0.0), gravity=(0.0, -9.81, 0.0)):
    mesh = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=origin)
    return wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0), gravity=gravity)


def _drop(custom, steps=18, lift=0.02, T=1.0, **kw):
    """A block thrown down at a plane rising at ``lift`` m/s: the custom form, or the built-in collider."""
    sim = wf.Simulator(_block(), dt=0.01, tol=1e-10, max_iters=100, **kw)
    sim.set_velocities(np.tile([0.0, -0.6, 0.0], (sim.num_vertices, 1)))
    if custom:
        form = sim.add_form(PlaneBarrier(sim, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), velocity=(0.0, lift, 0.0)))
    else:
        form = None
        sim.add_collider(wf.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0), dhat=DHAT, stiffness=KAPPA,
                                  translation=(0.0, lift * T, 0.0), ramp_time=T))
    lowest, iters = [], []
    for _ in range(steps):
        st = sim.step()
        assert st.converged
        iters.append(st.newton_iterations)
        lowest.append(sim.positions()[:, 1].min() - lift * sim.time)  # the height above the plane
    return sim, form, np.array(lowest), iters


def test_a_custom_barrier_form_plugs_in_and_matches_the_builtin_plane():
    ref, _, low_ref, _ = _drop(False)
    sim, form, low, iters = _drop(True)
    # the barrier acted (the block, thrown 11 cm down over the run, stayed within dhat of the plane)
    # and no vertex ever crossed the moving plane
    assert low.min() > 0.0 and low.max() < DHAT
    # the same motion as the built-in frictionless collider (the same barrier, bound and poses)
    assert np.abs(sim.positions() - ref.positions()).max() <= 1e-9
    assert np.abs(sim.velocities() - ref.velocities()).max() <= 1e-9
    np.testing.assert_allclose(low, low_ref, atol=1e-9)
    # the hooks were called: one begin_step and one start check per step, with the step's times
    assert form.calls["begin_step"] == 18 and form.calls["check_start"] == 18
    assert form.calls["max_step"] >= sum(iters)  # the feasible start's bound and one before each line search
    t0, t1, dt, s, static = form.contexts[4]
    assert (t0, t1, dt, s, static) == (pytest.approx(0.04), pytest.approx(0.05), 0.01, 0.01, False)
    # the form is in the potential, placed by its order (after the load: the default 100)
    assert [f.name for f in sim.potential().forms] == ["inertia", "elastic", "load", "plane_barrier"]


def test_a_custom_form_fails_an_infeasible_start_and_leaves_the_state():
    sim = wf.Simulator(_block(gravity=(0.0, 0.0, 0.0)), dt=0.01)
    form = sim.add_form(PlaneBarrier(sim, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), velocity=(0.0, 0.5, 0.0)))
    x0 = sim.positions()
    sim.step()  # the plane rises 5 mm: 1 mm short of the body
    x1 = sim.positions()
    assert x1[:, 1].min() > 0.005
    with pytest.raises(SolveFailed, match=r"step 1: plane barrier: 9 vertices behind the plane at t = 0.02; state "
                                          r"left unchanged") as err:
        sim.step()  # 10 mm: through the body's base within the step
    assert err.value.stats.reason == "plane moved into the body"
    assert sim.time == pytest.approx(0.01) and np.array_equal(sim.positions(), x1) and not np.array_equal(x0, x1)
    assert form.calls["check_start"] == 2


@pytest.mark.parametrize("iterations,script,updates", [
    (3, [(1.0, 1.0)] * 3, 3),  # taken again three times in the solve (each change above the tolerance)
    (3, [(0.005, 1.0)] * 3, 1),  # a change below friction_tol x scale: consistent, no further update
    (1, [(1.0, 1.0)] * 3, 1),  # at most friction_iterations updates
    (0, [], 0)])  # 0: lagged once, from the step start
def test_lagging_forms_are_updated_like_friction(iterations, script, updates):
    sim = wf.Simulator(_block(), dt=0.02, friction_iterations=iterations, friction_tol=0.01, tol=1e-12)
    x = sim.positions()
    sim.set_positions(x + 0.01 * np.random.default_rng(1).standard_normal(x.shape))  # a solve of several iterations
    lag = sim.add_form(LagCounter(script))
    idle = sim.add_form(LagCounter([], lagging=False))
    st = sim.step()
    assert st.converged and st.newton_iterations > 6
    assert lag.updates == updates and st.friction_iterations == updates and idle.updates == 0


def test_static_solve_refuses_dynamic_only_forms_and_runs_the_others():
    mesh = wf.box_tet_mesh(size=(0.4, 0.05, 0.05), cells=(8, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=2e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    free_sim = wf.Simulator(model)
    assert free_sim.solve_static().converged
    sag = free_sim.positions()[:, 1].min()
    assert sag < -0.01  # without the plane the free end sags below y = -0.01
    sim = wf.Simulator(model)
    term = sim.add_form(VelocityTerm())
    with pytest.raises(ValueError, match="solve_static does not handle the form 'velocity_term'"):
        sim.solve_static()
    sim.remove_form(term)
    plane = sim.add_form(PlaneBarrier(sim, (0.0, -0.01, 0.0), (0.0, 1.0, 0.0), dhat=2e-3, kappa=1e3))
    st = sim.solve_static()
    assert st.converged
    low = sim.positions()[:, 1].min()
    assert -0.01 < low < -0.01 + 2e-3  # held by the barrier, within its dhat
    assert plane.calls["begin_step"] == 1 and plane.contexts[0][4] is True and plane.calls["check_start"] == 1
    sim.step()  # and the dynamic potential still has its forms in their slots
    assert sim.positions()[:, 1].min() > -0.01


def test_builtin_contact_forms_are_added_forms():
    from warpfem.contact import ContactForm

    sim = wf.Simulator(_block(), dt=0.01)
    sim.add_collider(wf.Plane(name="floor"))
    assert [type(f) for f in sim.forms] == [ContactForm] and sim.forms[0].contact is sim.contact
    early = sim.add_form(LagCounter([], lagging=False))
    early.order = 5  # between the elastic form (0) and the colliders' contact (10)
    sim.step()
    assert [f.name for f in sim.potential().forms] == ["inertia", "elastic", "lag_counter", "contact", "load"]
    sim.contact = None  # drops the colliders' form
    assert [f.name for f in sim.potential().forms] == ["inertia", "elastic", "lag_counter", "load"]
    assert lagged_change(np.ones(3), np.array([1.0, 3.0, 1.0])) == (2.0, 3.0)
    assert lagged_change(np.ones(3), np.ones(2)) == (float("inf"), 1.0)


def test_max_iters_default_follows_the_forms_and_a_given_value_wins(tmp_path):
    """Contact asks for 100 Newton iterations per solve (Form.newton_iterations): a simulator or a
    scene whose max_iters was not given gets it when contact is added; a given value is kept, and a
    simulator without contact keeps the default 30. A user's form can ask the same way."""
    model = wf.Model(wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1), origin=(0.0, 0.01, 0.0)),
                     wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    sim = wf.Simulator(model, dt=0.01)
    assert sim.options.max_iters == 30
    sim.add_collider(type="plane", point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0))
    assert sim.options.max_iters == 100
    sim.options.max_iters = 12  # assigned later: the user's, kept through the steps
    sim.step()
    assert sim.options.max_iters == 12
    given = wf.Simulator(model, dt=0.01, max_iters=7)
    given.add_collider(type="plane", point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0))
    assert given.options.max_iters == 7

    class Asks(PlaneBarrier):
        newton_iterations = 150

    own = wf.Simulator(model, dt=0.01)
    own.add_form(Asks(own, point=(0.0, -1.0, 0.0), normal=(0.0, 1.0, 0.0)))
    assert own.options.max_iters == 150

    from warpfem.scenes import load_scene

    base = ('gravity = [0.0, -9.81, 0.0]\n[mesh]\ngenerator = "box"\nsize = [0.1, 0.1, 0.1]\ncells = [1, 1, 1]\n'
            'origin = [0.0, 0.01, 0.0]\n[material]\nmodel = "stable_neo_hookean"\nyoungs_modulus = 1e5\n'
            'poisson_ratio = 0.3\ndensity = 1000.0\n')
    floor = '[[collider]]\ntype = "plane"\npoint = [0.0, 0.0, 0.0]\nnormal = [0.0, 1.0, 0.0]\n'
    for text, want in ((base, 30), (base + floor, 100), (base + floor + "[integrator]\nmax_iters = 40\n", 40)):
        p = tmp_path / "s.toml"
        p.write_text(text)
        assert load_scene(str(p)).build().sim.options.max_iters == want
