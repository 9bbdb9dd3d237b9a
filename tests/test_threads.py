"""CPU threads (warpfem.threads, kernels.generic.launch): forces, Hessians and Newton steps are
bit-identical whatever the thread count and run to run; the gather assembly equals the atomic
scatter it replaced; bad thread counts get a one-line error or a clamped count with a warning.

The meshes are tiny, so the chunk and reduction-block sizes are made tiny too (every splittable
launch is split, reductions use several rows of partial sums), and the core count is raised so
that 3 threads run on this 2-core machine."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpfem.threads as TH
from warpfem import Model, Plane, Simulator, box_hex_mesh, box_tet_mesh, make_material, tet10_from_tet4
from warpfem.kernels import fem as FK
from warpfem.kernels import generic
from warpfem.kernels.generic import COUNTERS, launch
from warpfem.solvers import forms


@pytest.fixture
def tiny_chunks(monkeypatch):
    monkeypatch.setattr(generic, "MIN_CHUNK", 1)
    monkeypatch.setattr(generic, "REDUCE_BLOCK_MIN", 4)
    monkeypatch.setattr(forms, "FORCE_ROW_BLOCK", 2)
    monkeypatch.setattr(TH, "available_cores", lambda: 4)
    yield
    TH.set_threads(None)


def _model(mesh, nu=0.3):
    mat = make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=nu, density=1000.0)
    m = Model(mesh, mat, gravity=(0.0, 0.0, -9.81))
    return m


def _force_and_hessian(sim, x, project=True):
    el = sim._elastic
    acc = wp.zeros(64, dtype=wp.float64, device=sim.device)
    el.bind(acc, 8)
    g = sim.ops.new_vector()
    el.gradient(None, x, 1.0, g, acc)
    el.energy(None, x, acc)
    vals = sim.new_matrix_values()
    el.assemble(x, 1.0, vals, project=project)
    return g.numpy(), vals.numpy(), acc.numpy()


def _atomic(sim, x, project=True):
    """The atomic scatter (``slots`` 0) of the same kernels, unsplit: the reference of the gather."""
    el, S = sim._elastic, sim.scalar_type
    g, fa = sim.ops.new_vector(), sim.ops.new_vector()
    vals = sim.new_matrix_values()
    for qs in el.qp_sets:
        launch(FK.qp_force_and_abs_kernel, qs.count, [x, qs.points, qs.material, S(-1.0), g, fa, 0], sim.device)
        launch(FK.qp_hessian_kernel, qs.count, [x, qs.points, qs.material, S(1.0), int(project),
                                                el.pattern.block_indices[getattr(qs, "group", 0)], vals, 0],
               sim.device)
    return g.numpy(), vals.numpy()


@pytest.mark.parametrize("element", ["tet4", "tet10", "hex8"])
def test_gather_assembly_equals_the_atomic_scatter_and_is_identical_for_1_2_3_threads(tiny_chunks, monkeypatch,
                                                                                      element):
    mesh = box_tet_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    if element == "tet10":
        mesh = tet10_from_tet4(mesh)
    elif element == "hex8":
        mesh = box_hex_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    sim = Simulator(_model(mesh), dt=0.01, precision="float64")
    rng = np.random.default_rng(1)
    X = np.asarray(mesh.vertices)
    x = wp.array(X + 0.01 * rng.standard_normal(X.shape), dtype=wp.vec3d)
    out = {}
    # the force: each thread computes the points its vertices gather (one dispatch), or (halo -1)
    # the points are split first and the vertices gathered after (seam -1: never computed twice)
    for T, halo in ((1, 10**9), (2, 10**9), (3, 10**9), (2, -1), (3, -1), (1, 10**9)):
        TH.set_threads(T)
        monkeypatch.setattr(forms, "FORCE_SEAM_MAX_POINTS", halo)
        s0 = COUNTERS["split"]
        g, H, acc = _force_and_hessian(sim, x)
        assert (COUNTERS["split"] > s0) == (T > 1)  # the launches were split (or not, on one thread)
        bounds, _, used_halo = sim._elastic._force_plan(T)
        assert len(bounds) == T + 1 and used_halo == (halo > 0 or T == 1)  # the force was cut in T parts
        got = (g.tobytes(), H.tobytes(), acc.tobytes())
        assert out.setdefault("ref", got) == got, f"{T} threads (halo {halo}) differ from 1"
        el, acc2, g2 = sim._elastic, wp.zeros(64, dtype=wp.float64, device=sim.device), sim.ops.new_vector()
        el.bind(acc2, 8)
        for rep in range(2):  # recorded by the first call, replayed (split) by the second
            acc2.zero_()
            g2.zero_()
            s0 = COUNTERS["split"]
            el.gradient(None, x, 1.0, g2, acc2)
            assert rep == 0 or (COUNTERS["split"] > s0) == (T > 1)
            assert g2.numpy().tobytes() == g.tobytes() and acc2.numpy()[10] == acc[10], f"{T} threads, call {rep}"
    TH.set_threads(1)
    ga, Ha = _atomic(sim, x)
    scale_g, scale_H = np.abs(ga).max(), np.abs(Ha).max()
    assert scale_g > 0 and scale_H > 0
    np.testing.assert_allclose(g, ga, rtol=0, atol=1e-12 * scale_g)
    np.testing.assert_allclose(H, Ha, rtol=0, atol=1e-12 * scale_H)
    np.testing.assert_allclose(acc[8], float(_energy(sim, x)), rtol=1e-12)


def _energy(sim, x):
    return sim._elastic_energy(x)[0]


def _drop(threads, steps=4):
    """A box landing sideways on a frictional plane (collider contact + lagged friction)."""
    TH.set_threads(threads)
    mesh = box_tet_mesh(size=(0.2, 0.2, 0.2), cells=(2, 2, 2))
    sim = Simulator(_model(mesh), dt=1 / 240, precision="float64", max_iters=100)
    sim.add_collider(Plane(point=(0, 0, -0.01), normal=(0, 0, 1), friction=0.3))
    sim.set_velocities(np.tile([0.3, 0.0, -1.0], (sim.num_vertices, 1)))
    newton = 0
    for _ in range(steps):
        st = sim.step()
        assert st.converged
        newton += st.newton_iterations
    return sim.state.x.numpy(), sim.state.v.numpy(), newton


def test_newton_steps_with_contact_and_friction_identical_for_1_2_3_threads_and_run_to_run(tiny_chunks):
    x1, v1, n1 = _drop(1)
    assert n1 >= 4 and -0.01 < x1[:, 2].min() < 0.0  # it landed on the plane (z = -0.01), never through it
    s0 = COUNTERS["split"]
    for T in (2, 3, 1):
        x, v, n = _drop(T)
        assert n == n1
        assert x.tobytes() == x1.tobytes() and v.tobytes() == v1.tobytes(), f"{T} threads differ"
    assert COUNTERS["split"] > s0


def test_multigrid_steps_identical_for_1_and_2_threads(tiny_chunks):
    mesh = box_tet_mesh(size=(1.0, 0.25, 0.25), cells=(8, 2, 2))
    res = []
    for T in (1, 2):
        TH.set_threads(T)
        m = _model(mesh, nu=0.45)
        m.fix(np.nonzero(np.asarray(mesh.vertices)[:, 0] < 1e-9)[0])
        sim = Simulator(m, dt=1 / 60, precision="float64", linear_solver="multigrid",
                        linear_solver_options=dict(max_coarse=30))
        for _ in range(2):
            assert sim.step().converged
        res.append(sim.state.x.numpy().tobytes())
    assert res[0] == res[1]


def test_stiffness_warping_gathered_identical_for_1_and_2_threads_and_equal_to_the_atomic_scatter(tiny_chunks,
                                                                                                    monkeypatch):
    """Stiffness warping's per-tet forces and blocks go to slots gathered per vertex and per block:
    its steps are bit-identical for 1 and 2 threads (the assembly, rotation and gather launches
    split), and its force, force offset and stiffness equal the atomic scatter's to 1e-12."""
    import warpfem.solvers.stiffness_warping as SW

    mesh = box_tet_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    plain, split = SW.launch, set()

    def spy(kernel, dim, inputs, device):
        s0 = COUNTERS["split"]
        plain(kernel, dim, inputs, device)
        if COUNTERS["split"] > s0:
            split.add(kernel.key)

    monkeypatch.setattr(SW, "launch", spy)

    def run(threads):
        TH.set_threads(threads)
        m = _model(mesh)
        m.fix(np.nonzero(np.asarray(mesh.vertices)[:, 0] < 1e-9)[0])
        sim = SW.StiffnessWarpingSimulator(m, dt=0.01, precision="float64", rotation="polar")
        split.clear()
        for _ in range(3):
            assert sim.step().converged
        if threads > 1:
            assert {"warped_assembly_kernel", "element_rotation_kernel", "gather_force_kernel",
                    "gather_blocks_kernel"} <= split, split
        else:
            assert not split
        return sim

    a, b = run(1), run(2)
    assert a.state.x.numpy().tobytes() == b.state.x.numpy().tobytes()
    assert np.abs(a.positions() - np.asarray(mesh.vertices)).max() > 1e-4  # it sagged
    TH.set_threads(1)
    x = a.positions()
    got = (a.elastic_forces(x), a.force_offset(x), a.stiffness_matrix(x).toarray())
    monkeypatch.setattr(SW, "GATHER", False)
    ref = (a.elastic_forces(x), a.force_offset(x), a.stiffness_matrix(x).toarray())
    for g, r in zip(got, ref):
        np.testing.assert_allclose(g, r, rtol=0, atol=1e-12 * np.abs(r).max())


def test_ordered_sums_from_one_row_per_index_equal_the_row_sums(monkeypatch):
    """The fixed-order reduction used on devices other than the CPU (one row per index, a tree of
    passes of TREE_BLOCK rows, ``generic.ORDERED_SUMS``), forced on the CPU with a tiny block so
    that the tree has several passes: energies, magnitudes and maxima equal the default path's to
    round-off, steps onto a plane with friction (the default solver and PCG, whose dot products are
    recorded launches) take the same Newton iterations to the same states (1e-10), and two
    runs give the same bits."""
    monkeypatch.setattr(generic, "TREE_BLOCK", 4)
    mesh = box_tet_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    sim = Simulator(_model(mesh), dt=0.01, precision="float64")
    rng = np.random.default_rng(2)
    X = np.asarray(mesh.vertices)
    x = wp.array(X + 0.01 * rng.standard_normal(X.shape), dtype=wp.vec3d)
    ref = _force_and_hessian(sim, x)
    monkeypatch.setattr(generic, "ORDERED_SUMS", "always")
    got = _force_and_hessian(sim, x)
    assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])  # (gathered: no sums)
    np.testing.assert_allclose(got[2], ref[2], rtol=1e-13, atol=0)
    assert generic._tree_passes(len(sim._elastic.qp_sets[0].points.weight))[0]  # the tree took passes

    def stepped(ordered, solver="direct"):
        monkeypatch.setattr(generic, "ORDERED_SUMS", "always" if ordered else "device")
        TH.set_threads(1)
        m = _model(box_tet_mesh(size=(0.2, 0.2, 0.2), cells=(2, 2, 2)))
        sim = Simulator(m, dt=1 / 240, precision="float64", max_iters=100, linear_solver=solver)
        sim.add_collider(Plane(point=(0, 0, -0.01), normal=(0, 0, 1), friction=0.3))
        sim.set_velocities(np.tile([0.3, 0.0, -1.0], (sim.num_vertices, 1)))
        n = 0
        for _ in range(3):
            st = sim.step()
            assert st.converged
            n += st.newton_iterations
        return sim.state.x.numpy(), n

    for solver in ("direct", "pcg"):
        (xa, na), (xb, nb), (xc, nc) = stepped(False, solver), stepped(True, solver), stepped(True, solver)
        assert na == nb and np.abs(xa - xb).max() <= 1e-10 and xb.tobytes() == xc.tobytes()
    TH.set_threads(None)


# -- bad input -----------------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["0", "-3", "1.5", "two", ""])
def test_bad_env_thread_count_is_a_one_line_error_naming_the_variable(monkeypatch, value):
    TH.set_threads(None)
    monkeypatch.setenv("WARPFEM_THREADS", value)
    if value == "":  # unset in effect: every core
        assert TH.get_threads() == TH.available_cores()
        return
    with pytest.raises(TH.ThreadsError) as e:
        TH.get_threads()
    msg = str(e.value)
    assert "WARPFEM_THREADS" in msg and "\n" not in msg and "positive integer" in msg


def test_thread_count_above_the_cores_is_clamped_with_a_warning(monkeypatch):
    monkeypatch.setattr(TH, "available_cores", lambda: 2)
    with pytest.warns(RuntimeWarning, match="more than the 2 cores"):
        assert TH.set_threads(5) == 2
    with pytest.raises(TH.ThreadsError, match="threads=0"):
        TH.set_threads(0)
    assert TH.get_threads() == 2  # a refused count leaves the one in use
    monkeypatch.setenv("WARPFEM_THREADS", "9")
    with pytest.warns(RuntimeWarning, match="WARPFEM_THREADS=9"):
        TH.set_threads(None)
        assert TH.get_threads() == 2


def test_cli_threads_option(tmp_path, capsys, monkeypatch):
    from warpfem.cli import EXIT_INVALID, main

    monkeypatch.delenv("WARPFEM_THREADS", raising=False)
    scene = str(tmp_path / "missing.toml")
    assert main(["run", scene, "--threads", "0"]) == EXIT_INVALID
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["warpfem: error: --threads 0: the thread count must be a positive integer (at least 1)"]
    main(["run", scene, "--threads", "2", "--device", "cuda"])
    err = capsys.readouterr().err
    assert "warpfem: note: --threads 2 ignored: the kernels run on cuda" in err
    monkeypatch.setenv("WARPFEM_THREADS", "x")
    assert main(["run", scene]) == EXIT_INVALID
    assert capsys.readouterr().err.strip() == ("warpfem: error: WARPFEM_THREADS='x': the thread count must be a "
                                               "positive integer")


def test_split_pcg_identical_for_1_2_3_threads_and_close_to_the_serial_solve(tiny_chunks, monkeypatch):
    import warpfem.solvers.linear.pcg as P

    mesh = box_tet_mesh(size=(1.0, 0.25, 0.25), cells=(8, 2, 2))

    def run(split_rows):
        monkeypatch.setattr(P, "SPLIT_ROWS", split_rows)
        m = _model(mesh, nu=0.45)
        m.fix(np.nonzero(np.asarray(mesh.vertices)[:, 0] < 1e-9)[0])
        sim = Simulator(m, dt=1 / 60, precision="float64", linear_solver="pcg")
        for _ in range(2):
            assert sim.step().converged
        assert sim.linear_solver.cpu_split == (split_rows == 1)
        return sim.state.x.numpy()

    out = {}
    for T in (1, 2, 3):
        TH.set_threads(T)
        out[T] = run(1)
    assert out[1].tobytes() == out[2].tobytes() == out[3].tobytes()
    TH.set_threads(1)
    serial = run(10**9)
    scale = np.abs(serial - np.asarray(mesh.vertices)).max()  # the sag over two steps
    assert scale > 1e-4 and np.abs(out[1] - serial).max() <= 1e-8 * scale + 1e-12


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")
def test_pool_works_in_a_forked_child(monkeypatch):
    """A forked process (a process-pool executor) has none of the parent's pool threads: its pool
    starts empty instead of waiting on threads that do not exist."""
    import os

    monkeypatch.setattr(TH, "available_cores", lambda: 4)
    TH.set_threads(3)
    out = []
    TH.run_chunks([lambda: out.append(1), lambda: out.append(2), lambda: out.append(3)])
    assert sorted(out) == [1, 2, 3]
    pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        got = []
        TH.run_chunks([lambda: got.append(1), lambda: got.append(2), lambda: got.append(3)])
        os._exit(0 if sorted(got) == [1, 2, 3] else 1)
    _, status = os.waitpid(pid, 0)
    TH.set_threads(None)
    assert os.waitstatus_to_exitcode(status) == 0
