"""Stiffness warping (corotational linear FEM, Müller et al. 2002) against linear FEM, Newton corotated and invariants."""

import dataclasses
import warnings

import numpy as np
import pytest

import warpfem as wf
from warpfem.solvers.stiffness_warping import StiffnessWarpingSimulator, tet_linear_stiffness_blocks

MESH = wf.box_tet_mesh(size=(4, 1, 1), cells=(8, 2, 2))
X = MESH.vertices
LEFT = wf.select_vertices_in_box(MESH, (-1, -1, -1), (1e-6, 2, 2))
RIGHT = wf.select_vertices_in_box(MESH, (4 - 1e-6, -1, -1), (5, 2, 2))
MIDDLE = wf.select_vertices_in_box(MESH, (2 - 1e-6, -1, -1), (2 + 1e-6, 2, 2))


def _rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _model(name="corotated", E=1e5, fixed=(LEFT,), gravity=(0.0, 0.0, -9.81)):
    m = wf.Model(MESH, wf.make_material(name, youngs_modulus=E, poisson_ratio=0.3, density=1000.0), gravity=gravity)
    for idx in fixed:
        m.fix(idx)
    return m


def _volume(x):
    t = MESH.tets
    D = np.stack([x[t[:, i]] - x[t[:, 0]] for i in (1, 2, 3)], axis=2)
    return np.linalg.det(D).sum() / 6.0


def test_identity_rotation_is_exactly_linear_elasticity():
    """R_e = I: same K as the Newton simulator's linear material and the same backward Euler trajectory
    (with Rayleigh damping and a moving kinematic handle) to solver tolerance."""
    kw = dict(dt=0.01, damping_mass=0.5, damping_stiffness=1e-3)
    sw = StiffnessWarpingSimulator(_model("linear", fixed=(LEFT, RIGHT)), rotation="identity", cg_tol=1e-12, **kw)
    nt = wf.Simulator(_model("linear", fixed=(LEFT, RIGHT)), cg_tol=1e-12, tol=1e-10, **kw)
    np.testing.assert_allclose(sw.stiffness_matrix().toarray(), nt.stiffness_matrix(project=False).toarray(),
                               rtol=0, atol=1e-12 * 2e5)
    for k in range(12):
        target = X[RIGHT] + [0.0, 0.0, 0.01 * min(k + 1, 6)]
        sw.set_targets(RIGHT, target)
        nt.set_targets(RIGHT, target)
        st = sw.step()
        nt.step()
        assert st.converged and st.newton_iterations == 1 and st.cg_iterations > 0
    u = nt.positions() - X
    assert np.abs(u).max() > 0.05  # a real motion
    np.testing.assert_allclose(sw.positions(), nt.positions(), rtol=0, atol=1e-9 * np.abs(u).max())
    np.testing.assert_allclose(sw.velocities(), nt.velocities(), rtol=0, atol=1e-8 * np.abs(nt.velocities()).max())
    np.testing.assert_allclose(sw.positions()[RIGHT], X[RIGHT] + [0, 0, 0.06], atol=1e-12)  # handle reached


def test_rigid_rotation_gives_zero_force_unlike_linear_fem():
    R = _rotation((1, 1, 1), np.pi / 2)
    xr = X @ R.T + np.array([0.3, -2.0, 5.0])
    lin = StiffnessWarpingSimulator(_model("linear"), rotation="identity")
    ghost = lin.elastic_forces(xr)
    # identity warping = linear FEM ghost forces, checked against the Newton simulator's linear kernel
    np.testing.assert_allclose(ghost, wf.Simulator(_model("linear")).elastic_forces(xr), rtol=1e-10, atol=1e-6)
    assert np.abs(ghost).max() > 1e4
    for rotation in ("polar", "qr"):
        sw = StiffnessWarpingSimulator(_model("linear"), rotation=rotation)
        f = sw.elastic_forces(xr)
        assert np.abs(f).max() < 1e-12 * np.abs(ghost).max() * 1e3, rotation
        assert abs(sw.elastic_energy(xr)) < 1e-18
        Rs = sw.rotations(xr)
        assert np.abs(Rs - R[None]).max() < 1e-12, rotation


def test_warped_force_equals_seed_assembly(rng):
    """f = -(K' x + f0') with K'_ij = sum R K_ij R^T, f0'_i = -sum R K_ij X_j (numpy reference), K' symmetric."""
    sw = StiffnessWarpingSimulator(_model("linear"), rotation="polar")
    x = (X + 0.05 * rng.standard_normal(X.shape)) @ _rotation((0.2, 1, -0.4), 1.1).T
    f, f0, K = sw.elastic_forces(x), sw.force_offset(x), sw.stiffness_matrix(x)
    Rs = sw.rotations(x)
    assert np.allclose(np.linalg.det(Rs), 1.0) and np.allclose(Rs @ Rs.transpose(0, 2, 1), np.eye(3))
    qd = sw.model.quadrature
    mat = sw.model.material
    Ke = tet_linear_stiffness_blocks(qd.qp_dNdX, qd.qp_weight, mat.mu_lame, mat.lam_lame)
    n = len(X)
    K_ref = np.zeros((3 * n, 3 * n))
    f0_ref = np.zeros((n, 3))
    for e, tet in enumerate(MESH.tets):
        for i, a in enumerate(tet):
            f0_ref[a] -= Rs[e] @ sum(Ke[e, i, j] @ X[b] for j, b in enumerate(tet))
            for j, b in enumerate(tet):
                K_ref[3 * a:3 * a + 3, 3 * b:3 * b + 3] += Rs[e] @ Ke[e, i, j] @ Rs[e].T
    scale = np.abs(K_ref).max()
    np.testing.assert_allclose(K.toarray(), K_ref, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(f0, f0_ref, rtol=0, atol=1e-12 * scale * 4)
    np.testing.assert_allclose(f, -(K_ref @ x.ravel()).reshape(-1, 3) - f0_ref, rtol=0, atol=1e-9 * np.abs(f).max())
    assert np.abs(f).max() > 1e3


def test_small_deformation_matches_newton_corotated():
    """Stiff beam starting to sag under gravity (max displacement ~0.2 % of the length, 15 steps of 2 ms):
    stated tolerance 2e-4 (polar) and 5e-4 (qr) of the maximum displacement against Newton backward
    Euler with the corotated material (measured ~2e-5 and ~4e-5)."""
    dt = 0.002
    nt = wf.Simulator(_model("corotated", E=1e8), dt=dt, cg_tol=1e-8, tol=1e-6, max_iters=8)
    sws = {r: StiffnessWarpingSimulator(_model("corotated", E=1e8), dt=dt, cg_tol=1e-10, rotation=r) for r in ("polar", "qr")}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # Newton near round-off may stop on the line search
        for _ in range(15):
            nt.step()
            for s in sws.values():
                s.step()
    u = nt.positions() - X
    umax = np.abs(u).max()
    assert 0.003 < umax < 0.05
    err = {r: np.abs(s.positions() - nt.positions()).max() / umax for r, s in sws.items()}
    assert err["polar"] < 2e-4, err
    assert err["qr"] < 5e-4, err


def test_large_rotation_cantilever_keeps_volume_unlike_linear_fem():
    """Soft cantilever swinging down under gravity (the clamp-to-tip chord turns > 30 degrees): warped volume stays within
    6 % of rest (measured max 1.030 polar, 1.033 qr; Newton corotated 1.032) while linear FEM grows > 30 %."""
    vmax, tips = {}, {}
    V0 = _volume(X)
    for rotation in ("polar", "qr", "identity"):
        sw = StiffnessWarpingSimulator(_model("corotated", E=3e5), dt=1 / 60, rotation=rotation)
        vols = []
        for _ in range(40):
            sw.step()
            vols.append(_volume(sw.positions()) / V0)
        vmax[rotation] = max(vols)
        assert min(vols) > 0.97, (rotation, min(vols))
        tips[rotation] = sw.positions()[RIGHT].mean(axis=0)
    d = tips["polar"] - X[RIGHT].mean(axis=0) + [4.0, 0, 0]  # vector from the clamp to the tip
    assert np.degrees(np.arctan2(-d[2], d[0])) > 30.0  # measured 38.5
    assert vmax["polar"] < 1.06 and vmax["qr"] < 1.06, vmax
    assert vmax["identity"] > 1.3, vmax


def test_release_and_refix_mid_run_equals_run_built_with_final_set():
    a = StiffnessWarpingSimulator(_model("corotated", fixed=(LEFT, RIGHT)), dt=1 / 60, cg_tol=1e-10)
    for _ in range(5):
        a.step()
    a.release(RIGHT)
    a.fix(MIDDLE)
    x_mid, v_mid = a.positions(), a.velocities()
    assert np.abs(v_mid[MIDDLE]).max() > 1e-3  # re-fixing really changes something
    b = StiffnessWarpingSimulator(_model("corotated", fixed=(LEFT, MIDDLE)), dt=1 / 60, cg_tol=1e-10)
    b.set_positions(x_mid)
    b.set_velocities(v_mid)
    for _ in range(6):
        a.step()
        b.step()
    np.testing.assert_allclose(a.positions(), b.positions(), rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.positions()[MIDDLE], x_mid[MIDDLE], rtol=0, atol=1e-15)  # held where fixed
    assert np.abs(a.positions()[RIGHT] - x_mid[RIGHT]).max() > 1e-3  # the released end moved


def test_float32_matches_float64():
    sims = [StiffnessWarpingSimulator(_model("corotated"), precision=p, dt=1 / 60, cg_tol=1e-7) for p in ("float32", "float64")]
    for _ in range(10):
        for s in sims:
            s.step()
    u = sims[1].positions() - X
    assert np.abs(sims[0].positions() - sims[1].positions()).max() < 1e-4 * np.abs(u).max() + 1e-6


def test_bad_input_is_rejected_clearly():
    m = _model("corotated")
    with pytest.raises(ValueError, match="rotation"):
        StiffnessWarpingSimulator(m, rotation="svd")
    with pytest.raises(ValueError, match="dt"):
        StiffnessWarpingSimulator(m, dt=0.0)
    with pytest.raises(ValueError, match="cg_tol"):
        StiffnessWarpingSimulator(m, cg_tol=2.0)
    fake = _model("corotated")
    fake.quadrature = dataclasses.replace(fake.quadrature, element_type="tet10")
    with pytest.raises(ValueError, match="tet4"):
        StiffnessWarpingSimulator(fake)
    sw = StiffnessWarpingSimulator(m)
    with pytest.raises(ValueError, match="positions"):
        sw.set_positions(np.zeros((3, 3)))
    with pytest.raises(IndexError):
        sw.fix([10**6])


def test_scene_selects_stiffness_warping_with_rotation_option():
    from pathlib import Path

    import warpfem.scenes as scenes
    from warpfem.solvers.stiffness_warping import StiffnessWarpingSimulator

    scene = scenes.load_scene(Path(__file__).parent / "data" / "stiffness_warping.toml")
    run = scene.build(device="cpu", precision="float64")
    assert isinstance(run.sim, StiffnessWarpingSimulator) and run.sim.rotation == "qr"
    x0 = run.sim.positions()
    for _ in range(3):
        run.step_frame()
    u = run.sim.positions() - x0
    assert u[:, 2].min() < -1e-4  # sags under gravity
    assert np.abs(u[run.model.fixed.any(axis=1)]).max() == 0.0  # clamped end held
