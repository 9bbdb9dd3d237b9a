"""Fixed-order float64 sums (``kernels.generic.ORDERED_SUMS``), the path of devices other than the
CPU, forced on the CPU with a tiny tree block so that the trees take several passes: the linear
solvers' own reductions (the chunked PCG, its graph-captured form, the multigrid's CG, the dot
products) and a few Newton steps agree with the default path to round-off and repeat bit for bit;
and no kernel of the package adds into a shared scalar or vertex with atomics outside the places
listed here."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np
import pytest

import warpfem as wf
from warpfem import Model, Plane, Simulator, box_tet_mesh, make_material
from warpfem.kernels import generic
from warpfem.transfer import strict_device_mode

sys.path.insert(0, str(Path(__file__).parent))
from test_linear_solvers import _make, _system  # noqa: E402

try:
    import pyamg  # noqa: F401

    HAVE_AMG = True
except ImportError:
    HAVE_AMG = False


@pytest.fixture
def tree4(monkeypatch):
    monkeypatch.setattr(generic, "TREE_BLOCK", 4)
    return monkeypatch


def _solve(name, strict, opts, ordered, monkeypatch):
    monkeypatch.setattr(generic, "ORDERED_SUMS", "always" if ordered else "device")
    with strict_device_mode(strict):
        sim, model, vals, b, Am = _system(cells=(6, 2, 2), h2=1e-2)
        solver = _make(name, sim, model, **opts)
        bd = sim._vec_array(b)
        out = []
        for _ in range(2):  # a second solve replays the recorded (and, strict, graph-captured) chunk
            xd = sim._vec_array()
            res = solver.solve(vals, sim._mask, bd, xd, tol=1e-13, maxiter=500)
            assert res.converged, res
            out.append((xd.numpy().astype(np.float64), res.iterations))
        dot = solver.dot(bd, bd)
    return out, dot, float(b.ravel() @ b.ravel())


SOLVES = [("pcg", False, {"check_every": 3}), ("pcg", True, {"check_every": 3})]
if HAVE_AMG:
    SOLVES.append(("multigrid", False, {"max_coarse": 30}))


@pytest.mark.parametrize("name,strict,opts", SOLVES, ids=lambda c: str(c))
def test_ordered_linear_solves_agree_with_the_default_to_round_off_and_repeat_bit_for_bit(name, strict, opts, tree4):
    ref, dot_ref, bb = _solve(name, strict, opts, False, tree4)
    got, dot_got, _ = _solve(name, strict, opts, True, tree4)
    again, _, _ = _solve(name, strict, opts, True, tree4)
    assert generic._tree_passes(len(ref[0][0]))[0]  # the trees took passes
    for (xr, ir), (xg, ig), (xa, ia) in zip(ref, got, again):
        assert ig == ir and ia == ig
        assert np.abs(xg - xr).max() <= 1e-12 * np.abs(xr).max()
        assert xg.tobytes() == xa.tobytes()
    assert got[0][0].tobytes() == got[1][0].tobytes()  # the replayed chunk: the same bits
    assert abs(dot_got - dot_ref) <= 1e-14 * bb and abs(dot_ref - bb) <= 1e-12 * bb


def _steps(solver, ordered, strict, monkeypatch):
    monkeypatch.setattr(generic, "ORDERED_SUMS", "always" if ordered else "device")
    mat = make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    with strict_device_mode(strict):
        m = Model(box_tet_mesh(size=(0.2, 0.2, 0.2), cells=(2, 2, 2)), mat, gravity=(0.0, 0.0, -9.81))
        sim = Simulator(m, dt=1 / 240, precision="float64", max_iters=100, linear_solver=solver, tol=1e-10,
                        cg_tol=1e-12)
        sim.add_collider(Plane(point=(0, 0, -0.01), normal=(0, 0, 1), friction=0.3))
        sim.set_velocities(np.tile([0.3, 0.0, -1.0], (sim.num_vertices, 1)))
        its = []
        for _ in range(3):
            st = sim.step()
            assert st.converged
            its.append(st.newton_iterations)
        X = m.rest_positions
        f = sim.elastic_forces(X + 0.01 * np.sin(np.arange(X.size).reshape(X.shape)))  # at the same x in every run
        return sim.positions(), its, f


STEPS = [("auto", False), ("pcg", True)] + ([("multigrid", True)] if HAVE_AMG else [])


@pytest.mark.parametrize("solver,strict", STEPS, ids=lambda c: str(c))
def test_ordered_newton_steps_agree_with_the_default_to_round_off_and_repeat_bit_for_bit(solver, strict, tree4):
    (xa, ia, fa), (xb, ib, fb), (xc, ic, fc) = (_steps(solver, o, strict, tree4) for o in (False, True, True))
    assert ia == ib == ic
    assert np.abs(xb - xa).max() <= 1e-12 * np.abs(xa).max()
    assert xb.tobytes() == xc.tobytes() and fb.tobytes() == fc.tobytes()
    assert np.array_equal(fa, fb)  # the gathered force: the one-thread scatter's bits (one point set)


# -- no unlisted atomic sums ---------------------------------------------------------------------
#: (file, function, array) -> why an atomic add there is allowed. Everything else adding into an
#: array with ``wp.atomic_add`` must index it through ``row_stride`` (rows of partial sums: one per
#: block on the CPU, one per index in the fixed-order path).
ALLOWED_ATOMIC_ADDS = {
    ("kernels/linalg.py", "dot_kernel", "out"): "CPU only (linalg.launch_dot: dot_slot_kernel where sums are ordered)",
    ("kernels/fem.py", "qp_force_kernel", "f"): "CPU only (Simulator._add_elastic_force: the gather elsewhere)",
    ("kernels/fem.py", "qp_force_and_abs_kernel", "f"): "slots == 0 only: the scatter, tests and benchmarks",
    ("kernels/fem.py", "qp_force_and_abs_kernel", "f_abs"): "slots == 0 only: the scatter, tests and benchmarks",
    ("kernels/fem.py", "gather_force_kernel", "rows"): "CPU only (forms.ElasticForm._gradient_cpu): a row's vertices "
                                                       "in one chunk, added in index order",
    ("kernels/fem.py", "_put_block", "values"): "slots == 0 only: the Hessian scatter, tests and benchmarks",
    ("kernels/warping.py", "warped_assembly_kernel", "values"): "stiffness_warping.GATHER False only",
    ("contact/kernels.py", "contact_kernel", "values"): "one thread per surface vertex owns its diagonal block",
    ("contact/friction.py", "collider_filter_kernel", "count"): "an integer count: exact in any order",
    ("contact/friction.py", "collider_filter_kernel", "tally"): "an integer count in float64: exact in any order",
    ("contact/friction.py", "collider_pin_kernel", "count"): "an integer count: exact in any order",
    ("contact/surface_kernels.py", "boxes_fit_kernel", "misses"): "an integer count: exact in any order",
    ("contact/surface_kernels.py", "_append", "count"): "the pair list's slots; the list is sorted afterwards",
    ("contact/surface_kernels.py", "_add_pair_hessian", "values"): "contact.surface.GATHER False only",
    ("contact/surface_kernels.py", "pair_kernel", "g"): "contact.surface.GATHER False only",
    ("contact/surface_kernels.py", "friction_kernel", "g"): "contact.surface.GATHER False only",
    ("contact/surface_kernels.py", "friction_kernel", "values"): "contact.surface.GATHER False only",
}


def _atomic_adds():
    root = Path(wf.__file__).parent
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef):
                continue
            rowed = {"row_stride"}  # names whose value depends on row_stride
            for node in ast.walk(fn):
                if isinstance(node, ast.Assign) and {n.id for n in ast.walk(node.value) if isinstance(n, ast.Name)} & rowed:
                    rowed |= {t.id for t in node.targets if isinstance(t, ast.Name)}
            for node in ast.walk(fn):
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and node.func.attr == "atomic_add" and len(node.args) >= 2):
                    names = {n.id for n in ast.walk(node.args[1]) if isinstance(n, ast.Name)}
                    yield (path.relative_to(root).as_posix(), fn.name, ast.unparse(node.args[0])), bool(names & rowed)


def test_no_kernel_adds_into_a_shared_scalar_with_atomics_outside_the_listed_places():
    found = list(_atomic_adds())
    assert len(found) > 20  # the scan sees the kernels
    unlisted = sorted({key for key, rowed in found if not rowed and key not in ALLOWED_ATOMIC_ADDS})
    assert not unlisted, f"atomic adds neither through rows nor listed: {unlisted}"
    stale = sorted(set(ALLOWED_ATOMIC_ADDS) - {key for key, rowed in found if not rowed})
    assert not stale, f"listed but gone: {stale}"
