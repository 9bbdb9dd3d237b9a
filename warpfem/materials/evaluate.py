"""numpy-facing evaluation of the materials with one Warp kernel (tests, diagnostics).

``evaluate(kind, F, mu, lam, dtype=np.float64)`` computes, for a batch F of shape (N, 3, 3):
psi (N,), P (N, 3, 3), and the 9x9 Hessian dP/dF and its SPD projection (N, 9, 9), F flattened
row-major (index 3 i + j for F[i, j]). The Hessian is assembled from the analytic eigensystem
with unit vectors: H[3i+j, 3k+l] = hessian_block(e_j, e_l)[i, k].
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from .dispatch import hessian_block, material_eigensystem, material_pk1, material_psi

__all__ = ["evaluate", "OUTPUTS"]

wp.set_module_options({"enable_backward": False})

OUTPUTS = ("psi", "pk1", "hessian", "hessian_projected")


@wp.kernel
def evaluate_material_kernel(
    kind: int,
    F: wp.array(dtype=Any),
    mu: Any,
    lam: Any,
    want_hessian: int,
    psi: wp.array(dtype=Any),
    P: wp.array(dtype=Any),
    H: wp.array3d(dtype=Any),
    Hp: wp.array3d(dtype=Any),
):
    n = wp.tid()
    f = F[n]
    psi[n] = material_psi(kind, f, mu, lam)
    P[n] = material_pk1(kind, f, mu, lam)
    if want_hessian != 0:
        U, V, Q, d, tw, fl = material_eigensystem(kind, f, mu, lam)
        I = wp.identity(n=3, dtype=f.dtype)
        for j in range(3):
            for l in range(3):
                blk = hessian_block(U, V, Q, d, tw, fl, I[j], I[l], 0)
                blkp = hessian_block(U, V, Q, d, tw, fl, I[j], I[l], 1)
                for i in range(3):
                    for k in range(3):
                        H[n, 3 * i + j, 3 * k + l] = blk[i, k]
                        Hp[n, 3 * i + j, 3 * k + l] = blkp[i, k]


_TYPES = {
    np.dtype(np.float64): (wp.float64, wp.mat33d),
    np.dtype(np.float32): (wp.float32, wp.mat33),
}


def evaluate(kind: int, F, mu: float, lam: float, *, dtype=np.float64, outputs=OUTPUTS, device="cpu"):
    """Evaluate material ``kind`` at F ((N, 3, 3) or (3, 3)); returns a dict with the requested
    ``outputs`` among "psi", "pk1", "hessian", "hessian_projected" as numpy arrays of ``dtype``
    (float64 or float32). A single (3, 3) F gives unbatched results."""
    dt = np.dtype(dtype)
    if dt not in _TYPES:
        raise ValueError(f"dtype must be float32 or float64, got {dtype!r}")
    for o in outputs:
        if o not in OUTPUTS:
            raise ValueError(f"unknown output {o!r}; expected one of {OUTPUTS}")
    Fa = np.asarray(F, dtype=np.float64)
    single = Fa.shape == (3, 3)
    if single:
        Fa = Fa[None]
    if Fa.ndim != 3 or Fa.shape[1:] != (3, 3):
        raise ValueError(f"F must have shape (N, 3, 3) or (3, 3), got {np.shape(F)}")
    if not np.all(np.isfinite(Fa)):
        raise ValueError("F contains non-finite values")
    scalar, mat = _TYPES[dt]
    n = Fa.shape[0]
    want_h = any(o.startswith("hessian") for o in outputs)
    nh = n if want_h else 1
    with wp.ScopedDevice(device):
        F_wp = wp.array(Fa.astype(dt), dtype=mat)
        psi = wp.zeros(n, dtype=scalar)
        P = wp.zeros(n, dtype=mat)
        H = wp.zeros((nh, 9, 9), dtype=scalar)
        Hp = wp.zeros((nh, 9, 9), dtype=scalar)
        if n > 0:
            wp.launch(
                evaluate_material_kernel,
                dim=n,
                inputs=[int(kind), F_wp, scalar(mu), scalar(lam), int(want_h), psi, P, H, Hp],
            )
        res = {"psi": (psi, ()), "pk1": (P, (3, 3)), "hessian": (H, (9, 9)), "hessian_projected": (Hp, (9, 9))}
        out = {o: res[o][0].numpy().reshape((n,) + res[o][1]) for o in outputs}
    if single:
        out = {k: v[0] for k, v in out.items()}
    return out
