"""Runtime dispatch over material kinds (one kernel serves all materials, docs/design.md).

    material_psi(kind, F, mu, lam)          -> energy density psi (J/m^3)
    material_pk1(kind, F, mu, lam)          -> first Piola-Kirchhoff stress P = dpsi/dF
    material_eigensystem(kind, F, mu, lam)  -> (U, V, Q, d, twist, flip)
    material_hessian_parts(kind, F, mu, lam) -> (U, V, A, twist, flip)   (A = Q diag(d) Q^T, no eigen-solve)

The eigensystem is that of Smith, de Goes, Kim 2019 (see ``eigensystem.py``): feed it to
``hessian_block(U, V, Q, d, twist, flip, ga, gb, project)``. For linear elasticity U = V = I.
kind: LINEAR = 0, STVK = 1, COROTATED = 2, STABLE_NEO_HOOKEAN = 3, STABLE_NEO_HOOKEAN_LOG = 4. An unknown kind gives
psi = 0, P = 0 and a zero Hessian (kernels never crash; Python validates kinds).
All functions are generic over float32/float64; mu and lam must have F's scalar type.
"""

from typing import Any

import warp as wp

from .corotated import corotated_eigen, corotated_pk1, corotated_psi
from .eigensystem import hessian_block, scaling_eigensystem, signed_svd
from .linear import linear_eigen, linear_pk1, linear_psi
from .stable_neo_hookean import snh_eigen, snh_pk1, snh_psi
from .stable_neo_hookean_log import snh_log_eigen, snh_log_pk1, snh_log_psi
from .stvk import stvk_eigen, stvk_pk1, stvk_psi

__all__ = ["material_psi", "material_pk1", "material_eigensystem", "material_hessian_parts", "hessian_block"]

_LINEAR = wp.constant(0)
_STVK = wp.constant(1)
_COROTATED = wp.constant(2)
_STABLE_NEO_HOOKEAN = wp.constant(3)
_STABLE_NEO_HOOKEAN_LOG = wp.constant(4)


@wp.func
def material_psi(kind: int, F: Any, mu: Any, lam: Any):
    """Energy density psi(F) of material ``kind``."""
    if kind == _STABLE_NEO_HOOKEAN:
        return snh_psi(F, mu, lam)
    if kind == _STABLE_NEO_HOOKEAN_LOG:
        return snh_log_psi(F, mu, lam)
    if kind == _COROTATED:
        return corotated_psi(F, mu, lam)
    if kind == _STVK:
        return stvk_psi(F, mu, lam)
    if kind == _LINEAR:
        return linear_psi(F, mu, lam)
    return F.dtype(0.0)


@wp.func
def material_pk1(kind: int, F: Any, mu: Any, lam: Any):
    """First Piola-Kirchhoff stress P(F) of material ``kind``."""
    if kind == _STABLE_NEO_HOOKEAN:
        return snh_pk1(F, mu, lam)
    if kind == _STABLE_NEO_HOOKEAN_LOG:
        return snh_log_pk1(F, mu, lam)
    if kind == _COROTATED:
        return corotated_pk1(F, mu, lam)
    if kind == _STVK:
        return stvk_pk1(F, mu, lam)
    if kind == _LINEAR:
        return linear_pk1(F, mu, lam)
    return type(F)()


@wp.func
def material_hessian_parts(kind: int, F: Any, mu: Any, lam: Any):
    """dP/dF in eigen form before the scaling block is diagonalised: returns (U, V, A, twist, flip).

    F = U diag(s) V^T (signed SVD, det U = det V = +1; U = V = I for linear elasticity); A =
    d2Psi/ds2 (symmetric 3x3, scaling modes U diag(q) V^T for its eigenvectors q); twist / flip
    eigenvalues of pair k (k=0 -> (1,2), 1 -> (0,2), 2 -> (0,1)). Assembly uses this directly
    (``hessian_point_prepare`` / ``hessian_point_matrix``): A needs an eigen-solve only to be
    projected where it is indefinite.
    """
    if kind == _LINEAR:
        I = wp.identity(n=3, dtype=F.dtype)
        A0, tw0, fl0 = linear_eigen(F, mu, lam)
        return I, I, A0, tw0, fl0
    U, s, V = signed_svd(F)
    A = type(F)()
    tw = wp.vector(length=3, dtype=F.dtype)
    fl = wp.vector(length=3, dtype=F.dtype)
    if kind == _STABLE_NEO_HOOKEAN:
        A, tw, fl = snh_eigen(s, mu, lam)
    elif kind == _STABLE_NEO_HOOKEAN_LOG:
        A, tw, fl = snh_log_eigen(s, mu, lam)
    elif kind == _COROTATED:
        A, tw, fl = corotated_eigen(s, mu, lam)
    elif kind == _STVK:
        A, tw, fl = stvk_eigen(s, mu, lam)
    return U, V, A, tw, fl


@wp.func
def material_eigensystem(kind: int, F: Any, mu: Any, lam: Any):
    """Analytic eigensystem of dP/dF: returns (U, V, Q, d, twist, flip).

    F = U diag(s) V^T (signed SVD, det U = det V = +1); scaling modes U diag(Q[:, m]) V^T with
    eigenvalues d[m]; twist / flip modes of pair k (k=0 -> (1,2), 1 -> (0,2), 2 -> (0,1)) with
    eigenvalues twist[k] / flip[k]. (``material_hessian_parts`` plus ``scaling_eigensystem``.)
    """
    U, V, A, tw, fl = material_hessian_parts(kind, F, mu, lam)
    Q, d = scaling_eigensystem(A)
    return U, V, Q, d, tw, fl
