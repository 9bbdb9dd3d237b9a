"""The signed SVD of the Hessian kernels (``jacobi_signed_svd``: cyclic Jacobi on F^T F, then
Gram-Schmidt on F V) keeps the convention of ``signed_svd`` (det U = det V = +1, s[0] >= s[1] >= |s[2]|,
a reflection in s[2] < 0) on the hard cases: rest, repeated and zero singular values, inversion."""

from typing import Any

import numpy as np
import pytest
import warp as wp

from warpfem.materials.eigensystem import jacobi_signed_svd


@wp.kernel
def _svd_kernel(F: wp.array(dtype=Any), U: wp.array(dtype=Any), S: wp.array(dtype=Any), V: wp.array(dtype=Any)):
    i = wp.tid()
    u, s, v = jacobi_signed_svd(F[i])
    U[i] = u
    S[i] = s
    V[i] = v


def _rotations(rng, n):
    q = rng.standard_normal((n, 4))
    return np.array([_quat(v / np.linalg.norm(v)) for v in q])


def _quat(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _cases(rng, n=64):
    R1, R2 = _rotations(rng, n), _rotations(rng, n)
    return {
        "near rest": np.eye(3) + 1e-3 * rng.standard_normal((n, 3, 3)),
        "rotated stretch": R1 @ (np.eye(3) + 0.2 * rng.standard_normal((n, 3, 3))),
        "general": rng.standard_normal((n, 3, 3)),
        "inverted": R1 @ np.diag([1.5, 1.0, -0.3]) @ R2,
        "identity": np.tile(np.eye(3), (n, 1, 1)),
        "repeated": R1 @ np.diag([2.0, 2.0, 2.0 + 1e-9]) @ R2,
        "rank 2": R1 @ np.diag([1.0, 1.0, 0.0]) @ R2,
        "rank 1": np.einsum("ni,nj->nij", rng.standard_normal((n, 3)), rng.standard_normal((n, 3))),
        "zero": np.zeros((n, 3, 3)),
    }


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_jacobi_signed_svd_convention_and_accuracy(precision):
    np_t, mat, vec = (np.float64, wp.mat33d, wp.vec3d) if precision == "float64" else (np.float32, wp.mat33, wp.vec3)
    eps = float(np.finfo(np_t).eps)
    for name, F in _cases(np.random.default_rng(7)).items():
        n = len(F)
        Fd = wp.array(F.astype(np_t), dtype=mat, device="cpu")
        U, S, V = (wp.zeros(n, dtype=t, device="cpu") for t in (mat, vec, mat))
        wp.launch(_svd_kernel, n, [Fd, U, S, V], device="cpu")
        u, s, v = (a.numpy().astype(np.float64) for a in (U, S, V))
        F32 = F.astype(np_t).astype(np.float64)  # the matrix the kernel saw
        scale = np.linalg.norm(F32, axis=(1, 2)).max() + 1e-300
        rec = np.einsum("nij,nj,nkj->nik", u, s, v)
        assert np.abs(rec - F32).max() <= 64 * eps * scale, name
        for Q in (u, v):
            assert np.abs(np.einsum("nji,njk->nik", Q, Q) - np.eye(3)).max() <= 32 * eps, name
            assert np.all(np.abs(np.linalg.det(Q) - 1.0) <= 64 * eps), name
        tol = 64 * eps * scale
        assert np.all(s[:, 0] >= s[:, 1] - tol) and np.all(s[:, 1] >= np.abs(s[:, 2]) - tol), name
        ref = np.linalg.svd(F32, compute_uv=False)
        np.testing.assert_allclose(np.abs(s), ref, rtol=0, atol=tol, err_msg=name)
        det = np.linalg.det(F32)
        flipped = det < -tol * scale * scale
        assert np.all(s[flipped, 2] < 0.0) and np.all(s[det > tol * scale * scale, 2] >= 0.0), name
