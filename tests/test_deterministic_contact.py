"""Surface contact (body-body and self, with friction) assembled without atomics: every pair writes
its gradient and Hessian blocks to slots of its own, gathered per vertex and per block in a fixed
order over a pair list sorted into a canonical order. Steps are bit-identical for 1 and 2 threads
(the pair, friction and gather kernels split into chunks) and run to run; the gathered forces,
Hessians and energies equal the atomic scatter they replaced.

As in test_threads.py, the chunk and reduction-block sizes are made tiny so that every splittable
launch of these tiny scenes is split, and the core count is raised."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpfem.contact.surface as S
import warpfem.threads as TH
from warpfem.contact import surface_kernels as SK
from warpfem.kernels import generic
from warpfem.kernels.generic import COUNTERS
from warpfem.materials import make_material
from warpfem.mesh import TetMesh, box_tet_mesh
from warpfem.model import Model
from warpfem.simulator import Simulator


@pytest.fixture
def tiny_chunks(monkeypatch):
    monkeypatch.setattr(generic, "MIN_CHUNK", 1)
    monkeypatch.setattr(generic, "REDUCE_BLOCK_MIN", 4)
    monkeypatch.setattr(TH, "available_cores", lambda: 4)
    yield
    TH.set_threads(None)


def _material(E=1e5):
    return make_material("stable_neo_hookean", youngs_modulus=E, poisson_ratio=0.3, density=1000.0)


def _boxes_sim():
    """A box dropped with a sideways velocity onto another (body contact, friction 0.4)."""
    a = box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2))
    b = box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(0.03, 0.104, 0.02))
    na = len(a.vertices)
    mesh = TetMesh(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.tets, b.tets + na]))
    m = Model(mesh, _material(), gravity=(0.0, -9.81, 0.0))
    m.fix(np.flatnonzero(np.asarray(mesh.vertices)[:, 1] < 1e-9))
    sim = Simulator(m, dt=0.01, precision="float64", max_iters=100)
    sim.set_contact(friction=0.4)
    v = np.zeros((m.num_vertices, 3))
    v[na:] = (0.4, -0.6, 0.0)
    sim.set_velocities(v)
    return sim


def _u_sim():
    """A U whose arms swing into each other (self contact, friction 0.3)."""
    box = box_tet_mesh(size=(0.3, 0.4, 0.05), cells=(6, 4, 1))
    X, T = np.asarray(box.vertices), np.asarray(box.tets)
    c = X[T].mean(axis=1)
    T = T[~((c[:, 0] > 0.1) & (c[:, 0] < 0.2) & (c[:, 1] > 0.1))]
    used = np.unique(T)
    remap = -np.ones(len(X), dtype=np.int64)
    remap[used] = np.arange(len(used))
    mesh = TetMesh(X[used], remap[T])
    X = np.asarray(mesh.vertices)
    sim = Simulator(Model(mesh, _material(), gravity=(0.0, 0.0, 0.0)), dt=0.01, precision="float64", max_iters=100,
                    damping_mass=1.0)
    sim.set_contact(**{"self": True}, friction=0.3)
    v = np.zeros_like(X)
    arm = X[:, 1] > 0.15
    left = arm & (X[:, 0] < 0.15)
    right = arm & (X[:, 0] > 0.15)
    v[left, 0] = 4.0 * (X[left, 1] - 0.1)
    v[right, 0] = -4.0 * (X[right, 1] - 0.1)
    sim.set_velocities(v)
    return sim


SCENES = {"bodies": (_boxes_sim, 4), "self": (_u_sim, 5)}


def _run(scene, threads, monkeypatch=None):
    """The scene stepped on ``threads`` threads: positions, velocities (bytes), Newton iterations,
    whether friction acted, and how many pair / friction / gather launches were split."""
    TH.set_threads(threads)
    make, steps = SCENES[scene]
    sim = make()
    sc = sim.surface_contact
    split = {}
    if monkeypatch is not None:
        plain = S.launch

        def spy(kernel, dim, inputs, device):
            s0 = COUNTERS["split"]
            plain(kernel, dim, inputs, device)
            key = getattr(kernel, "key", str(kernel))
            split[key] = split.get(key, 0) + (COUNTERS["split"] > s0)

        monkeypatch.setattr(S, "launch", spy)
    newton, friction = 0, 0
    for _ in range(steps):
        st = sim.step()
        assert st.converged
        newton += st.newton_iterations
        friction += sc.num_friction
    assert np.array_equal(sc.pairs_np, sc.pairs_np[S.canonical_order(sc.pairs_np, read_kinds(sc))])
    return sim.state.x.numpy().tobytes(), sim.state.v.numpy().tobytes(), newton, friction, split


def read_kinds(sc):
    return sc._kinds.numpy()[:sc.num_pairs]


@pytest.mark.parametrize("scene", ["bodies", "self"])
def test_contact_steps_identical_for_1_and_2_threads_and_run_to_run(tiny_chunks, monkeypatch, scene):
    x1, v1, n1, f1, _ = _run(scene, 1)
    assert f1 > 0 and n1 >= 8  # friction pairs were lagged: the scene is in (frictional) contact
    x2, v2, n2, f2, split = _run(scene, 2, monkeypatch)
    # the pair kernel's gradient and Hessian, friction's and both gathers ran in chunks
    for k in ("pair_kernel", "friction_kernel", "gather_vec_kernel", "gather_mat_kernel"):
        assert split.get(k, 0) > 0, f"{k} was not split: {split}"
    assert (n2, f2) == (n1, f1)
    assert x2 == x1 and v2 == v1, "2 threads differ from 1"
    x3, v3, *_ = _run(scene, 1)
    assert x3 == x1 and v3 == v1, "run to run"


def _terms(sc, x, y, dbase):
    """Barrier + friction energy, gradient and Hessian of the current pairs at x (one call each)."""
    ops = sc.ops
    acc = wp.zeros(8, dtype=wp.float64, device=sc.device)
    g = ops.new_vector()
    vals = wp.zeros_like(sc.system.hessian_values)
    sc.run(SK.MODE_ENERGY, x, acc=acc, slot=0)
    sc.run(SK.MODE_GRADIENT, x, scale=0.7, g=g, acc=acc, slot=4)
    sc.run(SK.MODE_HESSIAN, x, scale=0.7, values=vals)
    sc.run_friction(0, dbase, y, 1.0, acc=acc, slot=0)
    sc.run_friction(1, dbase, y, 1.0, scale=0.7, g=g, acc=acc, slot=4)
    sc.run_friction(2, dbase, y, 1.0, scale=0.7, values=vals)
    return acc.numpy()[[0, 6]], g.numpy(), vals.numpy()


@pytest.mark.parametrize("scene", ["bodies", "self"])
def test_gathered_terms_equal_the_atomic_scatter(monkeypatch, scene):
    """Mid-contact, the gathered energy, gradient magnitude, gradient and Hessian of the barrier and
    friction pairs equal those of the atomic scatter (GATHER off) to 1e-12 relative, on one thread."""
    TH.set_threads(1)
    make, steps = SCENES[scene]
    sim = make()
    sc = sim.surface_contact
    for _ in range(steps):
        assert sim.step().converged
    assert sc.num_friction > 0 and sc._has_blocks.sum() > 0
    rng = np.random.default_rng(3)
    xs = sim.state.x.numpy()
    x = sim.ops.new_vector()
    x.assign(xs + 1e-3 * sc.dhat * rng.standard_normal(xs.shape))
    y = sim.ops.new_vector()
    y.assign(xs - sc.step_start.numpy())  # x - x_n = dbase + y with dbase 0
    dbase = sim.ops.new_vector()
    sc.update_pairs(x)
    got = _terms(sc, x, y, dbase)
    monkeypatch.setattr(S, "GATHER", False)
    ref = _terms(sc, x, y, dbase)
    assert np.abs(ref[1]).max() > 0 and np.abs(ref[2]).max() > 0 and ref[0][0] > 0
    for a, b in zip(got, ref):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())


def test_slot_map_lists_each_targets_slots_in_ascending_order():
    t, o, e = S.slot_map([5, 2, 5, 7, 2, 5])
    assert t.tolist() == [2, 5, 7] and o.tolist() == [0, 2, 5, 6] and e.tolist() == [1, 4, 0, 2, 5, 3]
    pairs = np.array([[3, 1, 2, 0], [0, 5, 6, 7], [3, 0, 9, 9], [0, 5, 6, 2]])
    kinds = np.array([0, 1, 0, 0])
    assert S.canonical_order(pairs, kinds).tolist() == [3, 2, 0, 1]
