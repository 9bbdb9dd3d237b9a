"""The stick/slip-aware Newton step of lagged collider friction (warpfem.contact.friction) and the
friction accuracy it must keep: same steps as the plain Newton direction, far fewer line-search
halvings; a block on a 30 degree incline sticks (mu 0.8) and slides with g (sin - mu cos) (mu 0.2)."""

import math

import numpy as np
import pytest
import warp as wp

from test_contact import G, _incline_drop
from warpfem.contact import Plane
from warpfem.contact import friction as FR
from warpfem.materials import make_material
from warpfem.mesh import box_tet_mesh
from warpfem.model import Model
from warpfem.simulator import Simulator


def _crossing_fraction_np(u, du, eps):
    q = du @ du
    if np.linalg.norm(u) < eps or q <= 0.0:
        return 1.0
    t = -(u @ du) / q
    if t <= 0.0 or t >= 1.0:
        return 1.0
    return t


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_filter_cuts_only_tangential_steps_that_go_past_the_closest_point(precision):
    """The kernel on one vertex in contact with a plane (normal z, lagged force 1, eps 1e-3):
    the tangential part of d is cut to t* exactly when the step goes past its point closest to
    u = 0 (through |u| < eps or near it); the normal part is kept; a step that stops short of that
    point, moves away from it, or starts inside the zone, is untouched."""
    dt = wp.float64 if precision == "float64" else wp.float32
    vec = wp.vec3d if precision == "float64" else wp.vec3f
    npt = np.float64 if precision == "float64" else np.float32
    eps = 1e-3
    rng = np.random.default_rng(3)
    cases = [(np.array([5e-3, 0, 0]), np.array([-1e-2, 0, 0.2])),     # crosses: t* = 0.5
             (np.array([5e-3, 2e-3, 0]), np.array([-1e-2, 0, 0])),    # passes 2 eps away: t* = 0.5
             (np.array([5e-3, 2e-3, 0]), np.array([-4e-3, 0, 0])),    # stops short of that point: kept
             (np.array([5e-4, 0, 0]), np.array([-1e-2, 0, 0])),       # starts sticking: kept
             (np.array([5e-3, 0, 0]), np.array([1e-2, 0, -0.1]))]     # slides on: kept
    for _ in range(20):
        u0 = rng.normal(size=3) * 4e-3
        u0[2] = 0.0
        cases.append((u0, np.append(-u0[:2] * rng.uniform(0.5, 3.0) + rng.normal(size=2) * 5e-4, rng.normal())))
    s = 0.5  # x = x_b + s y: the kernel works on s d
    n_cut = 0
    for u0, dx in cases:
        d_in = dx / s
        arr = lambda a, t=vec: wp.array(np.asarray(a, dtype=npt).reshape(-1, 3), dtype=t, device="cpu")
        d = arr(d_in)
        cuts = wp.zeros(1, dtype=wp.int32, device="cpu")
        tally = wp.array([0.0, 1.0], dtype=wp.float64, device="cpu")  # the cuts are added to tally[1]
        wp.launch(FR.collider_filter_kernel, dim=1, device="cpu", inputs=[
            wp.array([0], dtype=wp.int32, device="cpu"), 1, wp.array(np.ones(1, dtype=npt), dtype=dt, device="cpu"),
            arr([0.0, 0.0, 1.0]), arr([0.0, 0.0, 0.0]), arr(u0), arr([0.0, 0.0, 0.0]), dt(s),
            wp.array(np.array([eps], dtype=npt), dtype=dt, device="cpu"),
            wp.array(np.array([0.5], dtype=npt), dtype=dt, device="cpu"), d, cuts, tally, 1])
        t = _crossing_fraction_np(u0, np.array([dx[0], dx[1], 0.0]), eps)
        expect = np.array([t * d_in[0], t * d_in[1], d_in[2]])
        tol = 1e-12 if precision == "float64" else 1e-5
        np.testing.assert_allclose(d.numpy()[0], expect, rtol=tol, atol=tol * np.abs(d_in).max())
        assert int(cuts.numpy()[0]) == (1 if t < 1.0 else 0)
        assert tally.numpy().tolist() == [0.0, 1.0 + (t < 1.0)]
        n_cut += t < 1.0
    assert n_cut >= 5 and n_cut < len(cases)  # both branches are exercised
    for k in (0, 1):
        assert _crossing_fraction_np(cases[k][0], cases[k][1] * [1.0, 1.0, 0.0], eps) == pytest.approx(0.5)
    assert [_crossing_fraction_np(u, du * [1.0, 1.0, 0.0], eps) for u, du in cases[2:5]] == [1.0, 1.0, 1.0]


def _box_drop(filt, precision="float64", steps=48):
    mesh = box_tet_mesh(size=(0.2, 0.2, 0.2), cells=(2, 2, 2))
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
              gravity=(0.0, 0.0, -G))
    sim = Simulator(m, dt=1 / 240, precision=precision, max_iters=100, friction_filter=filt)
    sim.add_collider(Plane(point=(0, 0, -0.02), normal=(0, 0, 1), friction=0.3))
    sim.set_velocities(np.tile([0.3, 0.0, -1.0], (m.num_vertices, 1)))  # lands sliding sideways
    halvings = newton = 0
    for _ in range(steps):
        st = sim.step()
        assert st.converged
        halvings += st.line_search_steps
        newton += st.newton_iterations
    return sim, halvings, newton


def test_filter_keeps_the_steps_and_removes_the_halvings():
    """Same trajectory (to the Newton tolerance) with and without the filter; far fewer halvings and
    Newton iterations with it (counts, deterministic)."""
    plain, h0, n0 = _box_drop(False)
    filt, h1, n1 = _box_drop(True)
    assert plain.positions()[:, 2].min() > -0.02 and filt.positions()[:, 2].min() > -0.02
    np.testing.assert_allclose(filt.positions(), plain.positions(), atol=1e-6)
    assert h0 > 20 and h1 <= h0 // 4
    assert n1 < n0


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_incline_30_degrees_sticks_within_half_a_millimetre_and_slides_within_1_percent(precision):
    """A block dropped 1 cm onto a 30 degree incline (h = 0.01 s): with mu 0.8 its centre of mass
    moves < 0.5 mm in the 0.3 s after the landing step (measured: 0.07 mm in float64, 0.36 mm in
    float32, whose default friction velocity is 10x), with mu 0.2 it slides with g (sin - mu cos)
    within 1 % (defaults: friction filter on, one lag update inside the solve)."""
    theta = math.radians(30.0)
    p, _, land = _incline_drop(0.8, theta, 36, precision=precision)
    assert land is not None and land < 6
    assert abs(p[land + 31] - p[land + 1]) < 5e-4  # from the end of the landing step
    mu = 0.2
    _, v, land = _incline_drop(mu, theta, 40, precision=precision)
    a = (v[land + 30] - v[land + 10]) / (20 * 0.01)
    assert a == pytest.approx(G * (math.sin(theta) - mu * math.cos(theta)), rel=0.01)


def test_rocking_block_filtered_and_a_filtered_step_cut_short_falls_back_to_the_plain_direction(monkeypatch):
    """A stiff block (E 1e6) started 1 mm above a 20 degree incline, inside dhat, with mu = 1.5 tan 20:
    the barrier throws it and it lands rocking on one edge. With only the steps through the
    sticking zones cut, the line search cut the filtered step to 2^-2 .. 2^-8 for 30 iterations
    (the contacts passing near their zones were not cut); cutting every step that goes past its
    point closest to u = 0 takes far fewer halvings than the plain direction, to the same motion.
    The fallback for a filtered step that the line search still cuts below 0.3 of its length (the
    unfiltered direction tried as well, taken where it goes lower) is exercised with a filter made
    to overshoot 8x: every step converges, to the same motion (friction lagged from the step start
    only, so that the potential does not depend on the path: the lag update inside the solve takes
    the normal forces at an iterate of the path, here 0.4 mm apart after the first step)."""
    from test_contact import _incline_model
    from warpfem.solvers.forms import IncrementalPotential

    theta = math.radians(20.0)
    m, R = _incline_model(theta, 0.001)

    def run(filt, lags=1):
        sim = Simulator(m, dt=0.01, friction_filter=filt, friction_pin=0.0,  # (the pinned solve: next tests)
                        friction_iterations=lags,
                        colliders=[Plane(point=(0, 0, 0), normal=R[:, 1], friction=1.5 * math.tan(theta))])
        stats = [sim.step() for _ in range(16)]
        assert all(st.converged for st in stats)
        return sim.positions(), sum(st.line_search_steps for st in stats), sum(st.unfiltered_steps for st in stats)

    x_p, h_p, u_p = run(False)
    x_f, h_f, u_f = run(True)
    assert u_p == 0 and h_p > 50 and h_f <= h_p // 4
    np.testing.assert_allclose(x_f, x_p, atol=1e-6)
    filter_direction = IncrementalPotential.filter_direction

    def overshooting(self, y, d):
        filter_direction(self, y, d)
        self.ops.lincomb(8.0, d, 0.0, d, d)

    x_p, _, _ = run(False, lags=0)
    monkeypatch.setattr(IncrementalPotential, "filter_direction", overshooting)
    x_o, _, u_o = run(True, lags=0)
    assert u_o > 20
    np.testing.assert_allclose(x_o, x_p, atol=1e-6)


def test_friction_update_only_when_the_normal_forces_change_keeps_the_landing_and_saves_iterations():
    """friction_update_tol = 0.25 (off by default): the lag update inside the solve is made only when
    a normal force at the iterate differs from the lagged one by more than 25 % of the largest. A
    block dropped 1 cm onto a 30 degree incline (mu 0.8, float64, 36 steps of 0.01 s): the landing
    steps still update (the block keeps still: < 0.2 mm in the 0.31 s from the landing step's end;
    measured 0.088 mm, as with an update in every step, against about 2 mm lagged once from the
    step start), the 30 resting steps keep their start's lag (4 updates against 34), and the run
    takes fewer Newton iterations than with an update in every step (measured 96 against 111)."""
    from test_contact import _incline_model

    theta = math.radians(30.0)
    m, R = _incline_model(theta, 0.01)
    t = -R[:, 0]
    Mv = m.lumped_mass / m.lumped_mass.sum()
    runs = {}
    for tol in (0.25, 0.0):
        sim = Simulator(m, dt=0.01, max_iters=200, friction_update_tol=tol,
                        colliders=[Plane(point=(0, 0, 0), normal=R[:, 1], friction=0.8)])
        assert sim.friction_update_tol == tol
        pos, stats, land = [], [], None
        for k in range(36):
            stats.append(sim.step())
            pos.append(float((Mv[:, None] * sim.positions()).sum(axis=0) @ t))
            if land is None and sim.contact.distances().min() < sim.contact.dhat[0]:
                land = k
        assert land is not None and land < 6 and all(st.converged for st in stats)
        runs[tol] = (np.array(pos), stats, land, sim)
    (p1, st1, land1, sim), (p0, st0, land0, _) = runs[0.25], runs[0.0]
    assert land1 == land0
    assert abs(p1[land1 + 31] - p1[land1]) < 2e-4 and abs(p0[land0 + 31] - p0[land0]) < 2e-4
    assert sum(st.friction_kept for st in st0) == 0
    assert sum(st.friction_iterations for st in st1[land1:land1 + 2]) >= 1  # the impact updates its lag
    assert sum(st.friction_kept for st in st1) >= 20  # resting steps keep it
    n1, n0 = sum(st.newton_iterations for st in st1), sum(st.newton_iterations for st in st0)
    assert n1 <= n0 - 10
    # a kept step's lag is its start's, and consistent with its end to the tolerance
    start = sim.contact.lag_candidate(sim.state.x)
    st = sim.step()
    assert st.friction_kept == 1 and st.friction_iterations == 0
    lagged = sim.contact.normal_forces()
    assert lagged.max() > 0.0 and np.array_equal(lagged, start)
    end = sim.contact.lag_candidate(sim.state.x)
    assert np.abs(end - lagged).max() <= 0.25 * max(end.max(), lagged.max())
    with pytest.raises(ValueError, match="friction_update_tol"):
        Simulator(m, dt=0.01, friction_update_tol=1.0)
    assert Simulator(m, dt=0.01).friction_update_tol == 0.0  # off by default (docs/contact.md: why)


def test_a_kept_lag_is_updated_after_all_when_the_solve_stalls():
    """IncrementalPotential's lag hook with friction_update_tol (no kernels: a stand-in form whose
    candidate lag changes by 10 % of its scale): below the tolerance the lag is kept (no new
    potential, no further check), and a solve not converged LAG_KEPT_STALL accepted iterations
    later makes the update after all, once, from an iterate a full step reached below lag_below."""
    from types import SimpleNamespace

    from warpfem.solvers.forms import LAG_BELOW, LAG_KEPT_STALL, IncrementalPotential

    calls = []

    class Lagging:
        lag_below = LAG_BELOW

        def uses_lagging(self):
            return True

        def update_lagging(self, x, keep_below=0.0):
            calls.append(keep_below)
            return (0.1, 1.0, False) if 0.1 <= keep_below else (0.1, 1.0)

    pot = SimpleNamespace(forms=[Lagging()], adaptive_forms=lambda: [], _x_of=lambda y: y)
    for name in ("set_lag_updates", "after_iteration"):
        setattr(pot, name, getattr(IncrementalPotential, name).__get__(pot))
    pot.set_lag_updates(1, 0.01, 0.25)
    assert pot.after_iteration("y", 1.0, residual=0.5) is False and calls == []  # not near the solution yet
    assert pot.after_iteration("y", 1.0, residual=1e-3) is False  # checked at iteration 2: kept
    assert calls == [0.25] and pot.lags_kept == 1 and pot.lag_updates == 0
    changed = [pot.after_iteration("y", 1.0, residual=1e-3) for _ in range(LAG_KEPT_STALL)]
    assert changed == [False] * (LAG_KEPT_STALL - 1) + [True]  # iteration 2 + LAG_KEPT_STALL: updated
    assert calls == [0.25, 0.0] and pot.lag_updates == 1
    assert [pot.after_iteration("y", 1.0, residual=1e-3) for _ in range(3)] == [False] * 3 and len(calls) == 2
    pot.set_lag_updates(1, 0.01, 0.0)  # friction_update_tol 0: the update at the first check
    assert pot.after_iteration("y", 1.0, residual=1e-3) is True and calls[-1] == 0.0 and pot.lags_kept == 0
def test_pinned_solve_keeps_the_steps_with_fewer_newton_iterations():
    """``friction_pin``: the stiff block landing rocking on the 20 degree incline (the case above),
    whose filtered steps the line search cut short: with the filter's cut contacts pinned in a
    second Newton solve every step converges to the same motion (1e-6 m) with fewer Newton
    iterations and line-search halvings (measured: 94 -> 80 iterations, 50 -> 4 halvings).
    The pin's gate (the filter's cut count read with the step bound, no pin in an iteration that
    cut nothing) gives bit-identical positions and iterations with fewer host read-backs than the
    pin kernel launched and its count read in every filtered iteration."""
    from test_contact import _incline_model

    from warpfem import transfer
    from warpfem.solvers.forms import IncrementalPotential

    theta = math.radians(20.0)
    m, R = _incline_model(theta, 0.001)
    runs = {}
    assert IncrementalPotential.pin_gate
    try:
        for pin, gate in ((0.0, True), (3.0, True), (3.0, False)):
            IncrementalPotential.pin_gate = gate
            sim = Simulator(m, dt=0.01, friction_pin=pin,
                            colliders=[Plane(point=(0, 0, 0), normal=R[:, 1], friction=1.5 * math.tan(theta))])
            reads = transfer.COUNTERS["reads"]
            stats = [sim.step() for _ in range(16)]
            assert all(st.converged for st in stats)
            runs[pin, gate] = (sim.positions(), sum(st.newton_iterations for st in stats),
                               sum(st.line_search_steps for st in stats), transfer.COUNTERS["reads"] - reads,
                               sum(st.newton_syncs for st in stats), [st.linear_iterations for st in stats])
    finally:
        IncrementalPotential.pin_gate = True
    (x0, n0, h0, *_), (x1, n1, h1, r1, s1, lin1) = runs[0.0, True], runs[3.0, True]
    assert np.abs(x1 - x0).max() < 1e-6
    assert n1 <= n0 - 8 and h1 <= h0 // 4
    x2, n2, h2, r2, s2, lin2 = runs[3.0, False]
    assert np.array_equal(x1, x2) and (n1, h1, lin1) == (n2, h2, lin2)
    # one read-back saved per filtered Newton iteration that cut nothing (measured: 69 of the 80)
    assert r2 - r1 == s2 - s1 >= 40
    with pytest.raises(ValueError, match="friction_pin"):
        Simulator(m, dt=0.01, friction_pin=-1.0)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_pin_kernel_adds_a_tangential_spring_only_where_the_filter_cuts(precision):
    """``collider_pin_kernel`` on one vertex against a plane (normal z, eps 1e-3): where the
    unfiltered step goes past its point closest to u = 0, k (I - n n^T) is added to the vertex's block (k =
    weight x its mean diagonal) and k (I - n n^T) d to the right-hand side; elsewhere nothing."""
    dt = wp.float64 if precision == "float64" else wp.float32
    vec = wp.vec3d if precision == "float64" else wp.vec3f
    mat = wp.mat33d if precision == "float64" else wp.mat33f
    npt = np.float64 if precision == "float64" else np.float32
    s, eps, weight = 0.5, 1e-3, 3.0
    block = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.5], [0.0, 0.5, 6.0]])
    tol = 1e-12 if precision == "float64" else 1e-5
    for u0, dx, crosses in [((5e-3, 0, 0), (-1e-2, 0, 0.2), True), ((5e-3, 2e-3, 0), (-1e-2, 0, 0), True),
                            ((5e-3, 2e-3, 0), (-4e-3, 0, 0), False), ((5e-3, 0, 0), (1e-2, 0, 0), False)]:
        arr = lambda a, t=vec: wp.array(np.asarray(a, dtype=npt).reshape(-1, 3), dtype=t, device="cpu")
        d_raw = np.asarray(dx) / s
        d_cut = np.array([0.1, -0.2, 0.3])
        values = wp.array(block[None].astype(npt), dtype=mat, device="cpu")
        rhs = arr([1.0, 2.0, 3.0])
        count = wp.zeros(1, dtype=wp.int32, device="cpu")
        wp.launch(FR.collider_pin_kernel, dim=1, device="cpu", inputs=[
            wp.array([0], dtype=wp.int32, device="cpu"), 1, wp.array(np.ones(1, dtype=npt), dtype=dt, device="cpu"),
            arr([0.0, 0.0, 1.0]), arr([0.0, 0.0, 0.0]), arr(u0), arr([0.0, 0.0, 0.0]), dt(s),
            wp.array(np.array([eps], dtype=npt), dtype=dt, device="cpu"),
            wp.array(np.array([0.5], dtype=npt), dtype=dt, device="cpu"), arr(d_raw), arr(d_cut),
            wp.array([0], dtype=wp.int32, device="cpu"), values, rhs, dt(weight), count])
        k = weight * np.trace(block) / 3.0 if crosses else 0.0
        P = np.diag([1.0, 1.0, 0.0])
        np.testing.assert_allclose(values.numpy()[0], block + k * P, rtol=tol, atol=tol)
        np.testing.assert_allclose(rhs.numpy()[0], np.array([1.0, 2.0, 3.0]) + k * P @ d_cut, rtol=tol, atol=tol)
        assert int(count.numpy()[0]) == int(crosses)


def test_an_iteration_whose_filter_cut_nothing_reads_no_unfiltered_direction(monkeypatch):
    """With the pin's gate (the default), the filter's cut count is read with the step bound; in an
    iteration where it cut nothing, d is the unfiltered direction, so neither the fallback to it
    (a filtered step cut below 0.3 of its length) nor the step test (``step_tol``) checks it again:
    the same positions and counts bit for bit, one read-back fewer per such check (measured: with
    step_tol 1e-2 over 8 steps 9 of the step test's and fallback's 10 checks, 280 read-backs against
    289; the sliding box drop now makes one fallback check in 48 steps, in an iteration whose filter
    did cut, so both ways read back the same 1644)."""
    import test_step_tol

    from warpfem import transfer
    from warpfem.solvers.forms import IncrementalPotential

    pinned, check = IncrementalPotential._pinned_solve, IncrementalPotential.direction_check
    raw_checks = [0]

    def counted(self, y, g, d):
        raw_checks[0] += getattr(self.work, "d_raw", None) is d
        return check(self, y, g, d)

    def keeps_raw(self, *args):  # the unfiltered direction kept whatever the cut count (as before)
        lin = pinned(self, *args)
        self._raw_kept = True
        return lin

    monkeypatch.setattr(IncrementalPotential, "direction_check", counted)
    for case in (lambda: _box_drop(True), lambda: test_step_tol._drop(1e-2, steps=8)):
        runs = []
        for solve in (keeps_raw, pinned):
            monkeypatch.setattr(IncrementalPotential, "_pinned_solve", solve)
            reads, raw_checks[0] = transfer.COUNTERS["reads"], 0
            out = case()
            runs.append((out, transfer.COUNTERS["reads"] - reads, raw_checks[0]))
        (a, r0, c0), (b, r1, c1) = runs
        if isinstance(a[0], Simulator):  # the box drop: (sim, halvings, Newton iterations)
            assert np.array_equal(a[0].positions(), b[0].positions()) and a[1:] == b[1:]
            assert c1 <= c0
        else:  # the step_tol drop: (per-step counts and reasons, positions, L)
            assert a[0] == b[0] and np.array_equal(a[1], b[1])
            assert c0 - c1 >= 9
        assert r0 - r1 == c0 - c1


def test_friction_lag_below_takes_the_lag_earlier_with_fewer_newton_iterations():
    """Simulator(friction_lag_below=0.1) (default None: 1e-2, ``forms.LAG_BELOW``): the lag update
    inside the solve is made from the first full-step iterate whose relative gradient is at most 0.1.
    The potential's hook honours the setting over a form's own ``lag_below`` (stand-in form, no
    kernels); on the sliding box drop (48 steps, float64) the run takes fewer Newton iterations
    (measured 185 against 207) and ends within 0.1 mm of the default's positions (measured 0.055
    mm: the normal forces are taken at another iterate); bad values are refused."""
    from types import SimpleNamespace

    from warpfem.solvers.forms import LAG_BELOW, IncrementalPotential

    class Lagging:
        lag_below = LAG_BELOW
        updates = 0

        def uses_lagging(self):
            return True

        def update_lagging(self, x, keep_below=0.0):
            Lagging.updates += 1
            return (1.0, 1.0)

    pot = SimpleNamespace(forms=[Lagging()], adaptive_forms=lambda: [], _x_of=lambda y: y)
    for name in ("set_lag_updates", "after_iteration"):
        setattr(pot, name, getattr(IncrementalPotential, name).__get__(pot))
    pot.set_lag_updates(1, 0.01, 0.0)  # the form's own 1e-2
    assert pot.after_iteration("y", 1.0, residual=0.05) is False and Lagging.updates == 0
    pot.set_lag_updates(1, 0.01, 0.0, below=0.1)
    assert pot.after_iteration("y", 0.5, residual=0.05) is False  # a shortened step: not near enough
    assert pot.after_iteration("y", 1.0, residual=0.2) is False and Lagging.updates == 0
    assert pot.after_iteration("y", 1.0, residual=0.05) is True and Lagging.updates == 1

    default, _, n_default = _box_drop(True)
    orig = Simulator.__init__

    def early(self, *a, **kw):
        orig(self, *a, friction_lag_below=0.1, **kw)

    Simulator.__init__ = early
    try:
        sim, _, n_early = _box_drop(True)
    finally:
        Simulator.__init__ = orig
    assert sim.friction_lag_below == 0.1 and Simulator(sim.model, dt=0.01).friction_lag_below is None
    assert n_early <= n_default - 10
    assert np.abs(sim.positions() - default.positions()).max() < 1e-4
    assert sim.positions()[:, 2].min() > -0.02
    for bad in (0.0, 1.0, -0.1, float("nan"), "x"):
        with pytest.raises(ValueError, match="friction_lag_below"):
            Simulator(sim.model, dt=0.01, friction_lag_below=bad)


def test_pinned_solve_starts_from_the_filtered_direction():
    """``friction_pin``'s second solve is warm-started from the filtered direction
    (``forms.PIN_WARM_START``), to the residual a solve from zero would leave: on the sliding box
    drop (48 steps, PCG) the same Newton iterations and positions (to 1e-8 m) with fewer CG
    iterations (measured 1698 against 1741 in float64; the bunny's impact: 462 against 717 in its
    pinned solves); with a factorisation (the box's default solver here) nothing changes, bit for
    bit, and no read-back is added."""
    import warpfem.solvers.forms as F

    def run(warm, solver):
        F.PIN_WARM_START = warm
        try:
            mesh = box_tet_mesh(size=(0.2, 0.2, 0.2), cells=(2, 2, 2))
            m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                      gravity=(0.0, 0.0, -G))
            sim = Simulator(m, dt=1 / 240, max_iters=100, linear_solver=solver)
            sim.add_collider(Plane(point=(0, 0, -0.02), normal=(0, 0, 1), friction=0.3))
            sim.set_velocities(np.tile([0.3, 0.0, -1.0], (m.num_vertices, 1)))
            stats = [sim.step() for _ in range(48)]
        finally:
            F.PIN_WARM_START = True
        assert all(st.converged for st in stats)
        return (sim.positions(), sum(st.newton_iterations for st in stats), sum(st.linear_iterations for st in stats),
                sum(st.newton_syncs for st in stats))

    (xw, nw, lw, _), (xc, nc, lc, _) = run(True, "pcg"), run(False, "pcg")
    assert nw == nc and np.abs(xw - xc).max() < 1e-8
    assert lw <= lc - 20
    (xw, nw, lw, sw), (xc, nc, lc, sc) = run(True, "direct"), run(False, "direct")
    assert np.array_equal(xw, xc) and (nw, lw, sw) == (nc, lc, sc)
