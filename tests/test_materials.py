"""Material library: derivatives, eigensystems, reference values (docs/shared reference sec. 2, 4)."""

import numpy as np
import pytest

from warpfem.materials import (
    COROTATED,
    LINEAR,
    MATERIALS,
    STABLE_NEO_HOOKEAN,
    STABLE_NEO_HOOKEAN_LOG,
    STVK,
    Corotated,
    LinearElastic,
    StableNeoHookean,
    StableNeoHookeanLog,
    StVenantKirchhoff,
    evaluate,
    make_material,
)

# mu_L = 1, lambda_L = 10  <=>  nu = lambda/(2(lambda+mu)) = 5/11, E = mu(3 lambda + 2 mu)/(lambda + mu) = 32/11
E_REF, NU_REF = 32.0 / 11.0, 5.0 / 11.0
NAMES = list(MATERIALS)


def mat(name, E=E_REF, nu=NU_REF):
    return make_material(name, youngs_modulus=E, poisson_ratio=nu, density=1000.0)


def sample_F():
    """Seeded well-conditioned F (det > 0) plus inverted ones (det < 0)."""
    rng = np.random.default_rng(12345)
    Fs = []
    while len(Fs) < 12:
        F = np.eye(3) + 0.35 * rng.normal(size=(3, 3))
        if len(Fs) >= 6:
            F = F @ np.diag([1.0, 1.0, -1.0])  # reflect: det < 0
        s = np.linalg.svd(F, compute_uv=False)
        if s.min() > 0.3 and np.min(np.diff(s[::-1])) > 0.05:
            Fs.append(F)
    F = np.array(Fs)
    assert np.sum(np.linalg.det(F) < 0) == 6
    return F


def rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def rel_err(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


@pytest.mark.parametrize("name", NAMES)
def test_pk1_matches_fd_of_psi(name):
    m = mat(name)
    F = sample_F()
    h = 1e-6
    E9 = np.eye(9).reshape(9, 3, 3)
    Fp = (F[:, None] + h * E9[None]).reshape(-1, 3, 3)
    Fm = (F[:, None] - h * E9[None]).reshape(-1, 3, 3)
    fd = ((m.psi(Fp) - m.psi(Fm)) / (2 * h)).reshape(-1, 3, 3)
    P = m.pk1(F)
    for n in range(len(F)):
        assert rel_err(fd[n], P[n]) < 1e-6, (name, n)


@pytest.mark.parametrize("name", NAMES)
def test_hessian_matches_fd_of_pk1(name):
    m = mat(name)
    F = sample_F()
    h = 1e-6
    E9 = np.eye(9).reshape(9, 3, 3)
    Fp = (F[:, None] + h * E9[None]).reshape(-1, 3, 3)
    Fm = (F[:, None] - h * E9[None]).reshape(-1, 3, 3)
    # column c of H = d vec(P) / d vec(F)_c
    fd = ((m.pk1(Fp) - m.pk1(Fm)) / (2 * h)).reshape(len(F), 9, 9).transpose(0, 2, 1)
    H = m.hessian(F)
    for n in range(len(F)):
        assert rel_err(fd[n], H[n]) < 1e-6, (name, n)
        assert np.allclose(H[n], H[n].T, rtol=0, atol=1e-12 * np.abs(H[n]).max())


@pytest.mark.parametrize("name", NAMES)
def test_projection_is_numerical_eigen_clamp(name):
    m = mat(name)
    F = np.concatenate([sample_F(), 0.4 * sample_F()[:3]])  # compressed ones have negative modes
    r = evaluate(m.kind, F, m.kernel_mu, m.kernel_lam, outputs=("hessian", "hessian_projected"))
    H, Hp = r["hessian"], r["hessian_projected"]
    clamped = 0
    for n in range(len(F)):
        w, Q = np.linalg.eigh(H[n])
        clamped += np.sum(w < 0)
        ref = (Q * np.maximum(w, 0.0)) @ Q.T
        scale = np.abs(H[n]).max()
        assert np.max(np.abs(Hp[n] - ref)) < 1e-10 * scale, (name, n)
        assert np.linalg.eigvalsh(Hp[n]).min() > -1e-10 * scale
    if name != "linear":
        assert clamped > 0  # the test actually exercised the clamp


def test_stable_neo_hookean_hessian_at_identity():
    m = mat("stable_neo_hookean")
    mu_L, lam_L = 1.0, 10.0
    assert np.isclose(m.mu_lame, mu_L) and np.isclose(m.lam_lame, lam_L)
    assert np.isclose(m.kernel_mu, mu_L) and np.isclose(m.kernel_lam, lam_L + mu_L)
    w = np.sort(np.linalg.eigvalsh(m.hessian(np.eye(3))))
    expected = np.sort([0.0] * 3 + [2 * m.kernel_mu] * 5 + [3 * m.kernel_lam - m.kernel_mu])
    assert np.allclose(w, expected, rtol=0, atol=1e-12)
    assert np.isclose(3 * m.kernel_lam - m.kernel_mu, 3 * lam_L + 2 * mu_L)
    assert np.allclose(m.pk1(np.eye(3)), 0.0, atol=1e-14)


@pytest.mark.parametrize("nu", [0.0, 0.3, 0.49, -0.5])
def test_all_materials_agree_with_linear_at_identity(nu):
    E = 7.0
    H_lin = mat("linear", E, nu).hessian(np.eye(3))
    mu = E / (2 * (1 + nu))
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    # closed form: dP_ij/dF_kl = mu (d_ik d_jl + d_il d_jk) + lam d_ij d_kl
    d = np.eye(3)
    ref = (mu * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d)) + lam * np.einsum("ij,kl->ijkl", d, d)).reshape(9, 9)
    assert np.allclose(H_lin, ref, rtol=0, atol=1e-12 * E)
    for name in NAMES:
        m = mat(name, E, nu)
        assert np.allclose(m.hessian(np.eye(3)), ref, rtol=0, atol=1e-12 * ref.max()), name
        assert np.allclose(m.pk1(np.eye(3)), 0.0, atol=1e-14), name


def test_rigid_rotation():
    R = rotation([1, 1, 1], np.pi / 2)
    assert np.isclose(np.linalg.det(R), 1.0)
    for name in ("stvk", "corotated", "stable_neo_hookean", "stable_neo_hookean_log"):
        m = mat(name)
        assert np.max(np.abs(m.pk1(R))) < 1e-13, name
        # zero energy at rest and under any rotation (SNH's constant is shifted so psi(I) = 0)
        assert abs(m.psi(np.eye(3))) < 1e-13 and abs(m.psi(R)) < 1e-13, name
    assert np.max(np.abs(mat("linear").pk1(R))) > 0.1


@pytest.mark.parametrize(
    "a,b_tab,P11_tab",
    [
        (0.5, 1.348400, -3.136364),
        (0.8, 1.105256, -0.726989),
        (1.2, 0.919761, 0.495034),
        (1.5, 0.828775, 1.042088),
        (2.0, 0.722999, 1.738636),
    ],
)
def test_stable_neo_hookean_uniaxial_reference(a, b_tab, P11_tab):
    m = mat("stable_neo_hookean")
    mu, lam = m.kernel_mu, m.kernel_lam
    alpha = 1 + mu / lam
    b = np.sqrt((alpha * lam * a - mu) / (lam * a * a))
    assert abs(b - b_tab) < 6e-7
    P = m.pk1(np.diag([a, b, b]))
    assert abs(P[0, 0] - P11_tab) < 1e-5
    assert abs(P[1, 1]) < 1e-12 and abs(P[2, 2]) < 1e-12
    assert np.allclose(P - np.diag(np.diag(P)), 0.0, atol=1e-14)
    # with the tabulated (rounded) b, the lateral stress is ~ dP22/db * 5e-7
    Pt = m.pk1(np.diag([a, b_tab, b_tab]))
    assert abs(Pt[0, 0] - P11_tab) < 3e-5 and abs(Pt[1, 1]) < 3e-5


@pytest.mark.parametrize("a,P11_tab", [(0.5, -0.545455), (1.2, 0.768), (1.5, 2.727273)])
def test_stvk_uniaxial_reference(a, P11_tab):
    m = mat("stvk")
    E, nu = m.youngs_modulus, m.poisson_ratio
    # S22 = 0  =>  E22 = -nu E11  =>  b^2 = 1 - nu (a^2 - 1); then P11 = a S11 = E a (a^2 - 1)/2
    b = np.sqrt(1 - nu * (a * a - 1))
    P = m.pk1(np.diag([a, b, b]))
    assert np.isclose(P[0, 0], E * a * (a * a - 1) / 2, rtol=1e-12)
    assert abs(P[0, 0] - P11_tab) < 1e-6
    assert abs(P[1, 1]) < 1e-12 and abs(P[2, 2]) < 1e-12


def test_closed_forms_numpy():
    F = sample_F()
    mu, lam = 1.0, 10.0
    I = np.eye(3)
    lin, stvk, cor, snh = mat("linear"), mat("stvk"), mat("corotated"), mat("stable_neo_hookean")
    for Fn, P_lin, P_stvk, psi_cor, P_snh in zip(F, lin.pk1(F), stvk.pk1(F), cor.psi(F), snh.pk1(F)):
        eps = 0.5 * (Fn + Fn.T) - I
        assert np.allclose(P_lin, 2 * mu * eps + lam * np.trace(eps) * I, atol=1e-12)
        Eg = 0.5 * (Fn.T @ Fn - I)
        assert np.allclose(P_stvk, Fn @ (2 * mu * Eg + lam * np.trace(Eg) * I), atol=1e-12)
        J = np.linalg.det(Fn)
        # closest rotation (det +1) via numpy SVD with reflection handled
        U, s, Vt = np.linalg.svd(Fn)
        D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
        R = U @ D @ Vt
        assert np.isclose(psi_cor, mu * np.sum((Fn - R) ** 2) + lam / 2 * (J - 1) ** 2, rtol=1e-12)
        mu_s, lam_s = 1.0, 11.0
        alpha = 1 + mu_s / lam_s
        assert np.allclose(P_snh, mu_s * Fn + lam_s * (J - alpha) * J * np.linalg.inv(Fn).T, atol=1e-12)


def test_float32_agrees_with_float64():
    F = sample_F()
    for name in NAMES:
        m = mat(name)
        r64 = evaluate(m.kind, F, m.kernel_mu, m.kernel_lam, dtype=np.float64)
        r32 = evaluate(m.kind, F, m.kernel_mu, m.kernel_lam, dtype=np.float32)
        for key in ("psi", "pk1", "hessian", "hessian_projected"):
            assert r32[key].dtype == np.float32 and r64[key].dtype == np.float64
            for n in range(len(F)):
                assert rel_err(r32[key][n].astype(np.float64), r64[key][n]) < 1e-4, (name, key, n)


def test_kinds_and_classes():
    assert (LINEAR, STVK, COROTATED, STABLE_NEO_HOOKEAN, STABLE_NEO_HOOKEAN_LOG) == (0, 1, 2, 3, 4)
    for name, cls, kind in [
        ("linear", LinearElastic, LINEAR),
        ("stvk", StVenantKirchhoff, STVK),
        ("corotated", Corotated, COROTATED),
        ("stable_neo_hookean", StableNeoHookean, STABLE_NEO_HOOKEAN),
        ("stable_neo_hookean_log", StableNeoHookeanLog, STABLE_NEO_HOOKEAN_LOG),
    ]:
        m = make_material(name, youngs_modulus=1e5, poisson_ratio=0.3, density=1100.0)
        assert type(m) is cls and m.kind == kind and m.name == name
        assert m.density == 1100.0 and m.youngs_modulus == 1e5 and m.poisson_ratio == 0.3
        assert np.isclose(m.mu_lame, 1e5 / 2.6) and np.isclose(m.lam_lame, 1e5 * 0.3 / (1.3 * 0.4))
    with pytest.raises(ValueError, match="unknown material"):
        make_material("rubber", youngs_modulus=1.0, poisson_ratio=0.3, density=1.0)
    with pytest.raises(TypeError):
        StableNeoHookean(1.0, 0.3, 1.0)  # keyword-only


@pytest.mark.parametrize(
    "kw,param",
    [
        (dict(youngs_modulus=0.0), "youngs_modulus"),
        (dict(youngs_modulus=-3.0), "youngs_modulus"),
        (dict(youngs_modulus=float("nan")), "youngs_modulus"),
        (dict(poisson_ratio=0.5), "poisson_ratio"),
        (dict(poisson_ratio=-1.0), "poisson_ratio"),
        (dict(poisson_ratio=0.7), "poisson_ratio"),
        (dict(density=0.0), "density"),
        (dict(density=-1.0), "density"),
        (dict(density="heavy"), "density"),
    ],
)
def test_invalid_parameters(kw, param):
    args = dict(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    args.update(kw)
    for cls in (LinearElastic, StVenantKirchhoff, Corotated, StableNeoHookean, StableNeoHookeanLog):
        with pytest.raises(ValueError, match=param) as exc:
            cls(**args)
        assert repr(args[param])[:4] in str(exc.value)


def test_evaluate_rejects_bad_input():
    m = mat("stvk")
    with pytest.raises(ValueError, match="shape"):
        m.pk1(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        m.psi(np.full((1, 3, 3), np.nan))


def test_degenerate_F_stays_finite():
    # F = 0, flattened, and s1 + s2 = 0 (corotated twist denominator guard), repeated singular values
    F = np.array([np.zeros((3, 3)), np.diag([1.0, 1.0, 0.0]), np.diag([1.0, 1.0, -1.0]), 2.0 * np.eye(3), -np.eye(3)])
    for name in NAMES:
        m = mat(name)
        r = evaluate(m.kind, F, m.kernel_mu, m.kernel_lam)
        for key, v in r.items():
            assert np.all(np.isfinite(v)), (name, key)
        for n in range(len(F)):
            # >=: the log form's Hessian at F = 0 is exactly zero
            assert np.linalg.eigvalsh(r["hessian_projected"][n]).min() >= -1e-9 * np.abs(r["hessian"][n]).max()
    # repeated singular values: Hessian still matches FD (closed forms have no 1/(s_i - s_j))
    h = 1e-6
    E9 = np.eye(9).reshape(9, 3, 3)
    F0 = rotation([1, 2, 3], 0.7) @ np.diag([1.3, 1.3, 0.8])
    for name in NAMES:
        m = mat(name)
        fd = np.array([(m.pk1(F0 + h * E9[c]) - m.pk1(F0 - h * E9[c])).ravel() / (2 * h) for c in range(9)]).T
        assert rel_err(fd, m.hessian(F0)) < 1e-6, name


def test_unknown_kind_gives_zero():
    r = evaluate(7, np.eye(3) * 1.1, 1.0, 1.0)
    for v in r.values():
        assert np.all(v == 0.0)


# -- stable neo-Hookean with the log term (Smith, de Goes, Kim 2018) ---------------------------
def snh_log_reference(F, mu, lam):
    """Textbook psi (with the rest offset removed) and P of the log form, in numpy."""
    alpha = 1 + 0.75 * mu / lam
    IC, J = np.sum(F * F), np.linalg.det(F)
    psi = mu / 2 * (IC - 3) + lam / 2 * (J - alpha) ** 2 - mu / 2 * np.log(1 + IC)
    psi -= lam / 2 * (1 - alpha) ** 2 - mu * np.log(2.0)
    P = mu * F + lam * (J - alpha) * J * np.linalg.inv(F).T - mu * F / (1 + IC)
    return psi, P


def test_stable_neo_hookean_log_parameters_and_hessian_at_identity():
    m = mat("stable_neo_hookean_log")
    mu_L, lam_L = 1.0, 10.0
    assert np.isclose(m.mu_lame, mu_L) and np.isclose(m.lam_lame, lam_L)
    assert np.isclose(m.kernel_mu, 4 / 3 * mu_L) and np.isclose(m.kernel_lam, lam_L + 5 / 6 * mu_L)
    # paper's alpha = 1 + mu/lambda - mu/(4 lambda) makes P(I) = 0 exactly
    alpha = 1 + m.kernel_mu / m.kernel_lam - m.kernel_mu / (4 * m.kernel_lam)
    assert np.isclose(m.kernel_mu - m.kernel_mu / 4 + m.kernel_lam * (1 - alpha), 0.0, atol=1e-14)
    w = np.sort(np.linalg.eigvalsh(m.hessian(np.eye(3))))
    expected = np.sort([0.0] * 3 + [2 * mu_L] * 5 + [3 * lam_L + 2 * mu_L])
    assert np.allclose(w, expected, rtol=0, atol=1e-12)
    assert np.allclose(m.pk1(np.eye(3)), 0.0, atol=1e-14) and abs(m.psi(np.eye(3))) < 1e-14


def test_stable_neo_hookean_log_matches_textbook_formulas():
    m = mat("stable_neo_hookean_log")
    F = np.concatenate([sample_F(), [2.5 * np.eye(3), 0.2 * np.eye(3), np.diag([3.0, 0.1, -0.5])]])
    psi, P = m.psi(F), m.pk1(F)
    for n, Fn in enumerate(F):
        psi_ref, P_ref = snh_log_reference(Fn, m.kernel_mu, m.kernel_lam)
        assert abs(psi[n] - psi_ref) < 1e-12 * max(1.0, abs(psi_ref)), n
        assert np.allclose(P[n], P_ref, rtol=0, atol=1e-12 * max(1.0, np.abs(P_ref).max())), n


def test_stable_neo_hookean_log_origin_is_a_saddle_not_a_minimum():
    """The log term cancels mu/2 I_C to second order at F = 0: P(0) = 0, dP/dF(0) = 0 and
    psi(eps I) - psi(0) = -lambda alpha eps^3 + O(eps^4) < 0, where the log-free energy has a
    strict minimum (+mu/2 eps^2 |I|^2)."""
    log, plain = mat("stable_neo_hookean_log"), mat("stable_neo_hookean")
    Z = np.zeros((3, 3))
    assert np.all(log.pk1(Z) == 0.0) and np.all(log.hessian(Z) == 0.0)
    alpha = 1 + 0.75 * log.kernel_mu / log.kernel_lam
    for eps in (1e-3, 1e-2, 0.1):
        d_log = log.psi(eps * np.eye(3)) - log.psi(Z)
        assert d_log < 0.0
        assert abs(d_log / (-log.kernel_lam * alpha * eps ** 3) - 1.0) < 10 * eps, eps
        assert plain.psi(eps * np.eye(3)) - plain.psi(Z) > 0.0


@pytest.mark.parametrize("nu", [0.0, 0.3, 0.45])
def test_stable_neo_hookean_log_small_strain_uniaxial_gives_E_and_nu(nu):
    """Uniaxial stress at a = 1 + 1e-6 (lateral b from P22 = 0, solved on the kernel's P):
    -(b - 1)/(a - 1) = nu and P11/(a - 1) = E, i.e. the reparametrised moduli are E, nu."""
    from scipy.optimize import brentq

    E = 7.0
    m = mat("stable_neo_hookean_log", E, nu)
    d = 1e-6
    a = 1.0 + d
    b = brentq(lambda b: m.pk1(np.diag([a, b, b]))[1, 1], 1 - 10 * d, 1 + 10 * d, xtol=1e-15)
    assert abs(-(b - 1) / d - nu) < 1e-5
    P = m.pk1(np.diag([a, b, b]))
    assert abs(P[0, 0] / d / E - 1.0) < 1e-5
    assert abs(P[2, 2]) < 1e-12


@pytest.mark.parametrize("a", [0.5, 1.5, 2.0])
def test_stable_neo_hookean_log_finite_uniaxial(a):
    """Uniaxial stress state at finite stretch: lateral stretch b from the textbook P22 = 0
    (mu (1 - 1/(1 + I_C)) + lambda (a b^2 - alpha) a = 0, solved in numpy), then the kernel's P
    is uniaxial with the textbook P11, and stiffer than the log-free form's lateral contraction."""
    from scipy.optimize import brentq

    m = mat("stable_neo_hookean_log")
    mu, lam = m.kernel_mu, m.kernel_lam
    alpha = 1 + 0.75 * mu / lam

    def p22(b):
        return mu * (1 - 1 / (1 + a * a + 2 * b * b)) + lam * (a * b * b - alpha) * a

    b = brentq(p22, 0.05, 3.0, xtol=1e-15)
    P = m.pk1(np.diag([a, b, b]))
    P11 = mu * a * (1 - 1 / (1 + a * a + 2 * b * b)) + lam * (a * b * b - alpha) * b * b
    assert abs(P[0, 0] - P11) < 1e-12 * max(1.0, abs(P11))
    assert abs(P[1, 1]) < 1e-12 and abs(P[2, 2]) < 1e-12
    assert (P[0, 0] > 0) == (a > 1)


def test_stable_neo_hookean_log_float32_energy_is_accurate_at_small_strain():
    """psi is evaluated in H = F - I with an accurate x - log(1 + x): in float32 it keeps ~1e-6
    relative accuracy at strains 1e-2 .. 1e-6 (the textbook form subtracts O(mu) terms and would
    keep none below ~1e-3). F is rounded to float32 first so both precisions see the same F."""
    m = mat("stable_neo_hookean_log")
    rng = np.random.default_rng(7)
    F = np.array([np.eye(3) + s * rng.normal(size=(3, 3)) for s in (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)])
    F = F.astype(np.float32).astype(np.float64)
    p64 = evaluate(m.kind, F, m.kernel_mu, m.kernel_lam, outputs=("psi",))["psi"]
    p32 = evaluate(m.kind, F, m.kernel_mu, m.kernel_lam, dtype=np.float32, outputs=("psi",))["psi"]
    assert np.all(p64 > 0)
    assert np.max(np.abs(p32 - p64) / p64) < 2e-6
    # and float64 agrees with the textbook formula where that is still accurate (strain 1e-2)
    assert abs(p64[0] - snh_log_reference(F[0], m.kernel_mu, m.kernel_lam)[0]) < 1e-9 * p64[0]


def test_stable_neo_hookean_log_volumetric_split_is_exact_and_psd_at_rest():
    m = mat("stable_neo_hookean_log", 7.0, 0.45)
    (mu_f, lam_f), (mu_v, lam_v) = m.volumetric_split()
    assert mu_v == 0.0 and np.isclose(lam_v, m.lam_lame)  # the 1-point part is lambda_L/2 (J - 1)^2
    F = np.concatenate([sample_F(), [0.3 * np.eye(3)]])
    full = evaluate(m.kind, F, mu_f, lam_f)
    vol = evaluate(m.kind, F, mu_v, lam_v)
    whole = evaluate(m.kind, F, m.kernel_mu, m.kernel_lam)
    for key in ("psi", "pk1", "hessian"):
        assert np.allclose(full[key] + vol[key], whole[key], rtol=0, atol=1e-12 * np.abs(whole[key]).max()), key
    J = np.linalg.det(F)
    assert np.allclose(vol["psi"], lam_v / 2 * (J - 1) ** 2, rtol=1e-12)
    I = np.eye(3)
    for mu_p, lam_p in ((mu_f, lam_f), (mu_v, lam_v)):
        r = evaluate(m.kind, I, mu_p, lam_p)
        assert np.allclose(r["pk1"], 0.0, atol=1e-14) and abs(r["psi"]) < 1e-14
        assert np.linalg.eigvalsh(r["hessian"]).min() > -1e-12
    # the full-rule part is this material with Lame (mu_L, 0): small-strain moduli 2 mu_L (x5) and 2 mu_L
    w = np.sort(np.linalg.eigvalsh(evaluate(m.kind, I, mu_f, lam_f)["hessian"]))
    assert np.allclose(w, [0, 0, 0] + [2 * m.mu_lame] * 6, atol=1e-12)
