"""Runtime dispatch over material kinds (one kernel serves all materials, docs/design.md).

    material_psi(kind, F, mu, lam)          -> energy density psi (J/m^3)
    material_pk1(kind, F, mu, lam)          -> first Piola-Kirchhoff stress P = dpsi/dF
    material_eigensystem(kind, F, mu, lam)  -> (U, V, Q, d, twist, flip)
    material_hessian_parts(kind, F, mu, lam) -> (U, V, A, twist, flip)   (A = Q diag(d) Q^T, no eigen-solve)

The eigensystem is that of Smith, de Goes, Kim 2019 (see ``eigensystem.py``): feed it to
``hessian_block(U, V, Q, d, twist, flip, ga, gb, project)``. For linear elasticity U = V = I.

The switch over ``kind`` is generated from the material registry (:mod:`.registry`) when this
module is imported: a chain of Warp funcs, one link per registered material, each testing its kind
and calling the material's function or the next link. So the kinds are defined once, where each
material registers itself, and the kernels still compile one dispatch for all materials (one
kernel module instead of one per material: compiling ``warpfem.kernels.fem`` takes tens of seconds
on the CPU, while the run-time test of a few ints is not measurable in a step, docs/design.md).
An unknown kind gives psi = 0, P = 0 and a zero Hessian (kernels never crash; Python validates kinds).
All functions are generic over float32/float64; mu and lam must have F's scalar type.
"""

import re
from typing import Any

import warp as wp

# The material modules: importing one registers it. A new material is a module plus its name here.
# (The dispatch tests kinds in this order: the common ones first.)
from . import stable_neo_hookean, stable_neo_hookean_log, corotated, stvk, linear  # noqa: F401, I001
from .eigensystem import hessian_block, jacobi_signed_svd, scaling_eigensystem
from .registry import MATERIAL_TYPES

__all__ = ["material_psi", "material_pk1", "material_eigensystem", "material_hessian_parts", "hessian_block"]


# -- the end of each chain: an unknown kind ------------------------------------------------------
@wp.func
def _no_psi(kind: int, F: Any, mu: Any, lam: Any):
    return F.dtype(0.0)


@wp.func
def _no_pk1(kind: int, F: Any, mu: Any, lam: Any):
    return type(F)()


@wp.func
def _no_eigen_s(kind: int, F: Any, s: Any, mu: Any, lam: Any):
    return type(F)(), wp.vector(length=3, dtype=F.dtype), wp.vector(length=3, dtype=F.dtype)


@wp.func
def _no_eigen_f(kind: int, F: Any, mu: Any, lam: Any):
    return 0, type(F)(), wp.vector(length=3, dtype=F.dtype), wp.vector(length=3, dtype=F.dtype)


# -- one link per material -----------------------------------------------------------------------
# Each link is a Warp func named after its material and kind (``material_psi__linear_k0``): Warp's
# module hash covers a func's name, its source, the constants it captures (the kind K) and,
# recursively, the funcs it calls (the material's function f and the rest of the chain), so the
# hash of every module that uses the dispatch (``kernels.fem``, ``kernels.subspace``,
# ``materials.evaluate``) changes with the registry: a kernel cache (~/.cache/warp) compiled for
# other materials, kinds or order is never reused (tests/test_registries.py checks it).
def _named(fn, what, t):
    name = f"{what}__{re.sub(r'[^0-9A-Za-z_]', '_', t.name)}_k{t.kind}"  # a C identifier
    fn.__name__ = fn.__qualname__ = name
    return wp.func(fn)


def _link_value(t, f, rest, what):
    """One link of a chain returning one value (psi or P): ``f`` of material ``t`` when kind == t.kind."""
    K = wp.constant(t.kind)

    def value_link(kind: int, F: Any, mu: Any, lam: Any):
        if kind == K:
            return f(F, mu, lam)
        return rest(kind, F, mu, lam)

    return _named(value_link, what, t)


def _link_eigen_s(t, rest):
    """Materials written in the signed singular values s: (A, twist, flip) = f(s, mu, lam)."""
    K, f = wp.constant(t.kind), t.eigen

    def eigen_s_link(kind: int, F: Any, s: Any, mu: Any, lam: Any):
        if kind == K:
            A, tw, fl = f(s, mu, lam)
            return A, tw, fl
        A, tw, fl = rest(kind, F, s, mu, lam)
        return A, tw, fl

    return _named(eigen_s_link, "material_eigen_s", t)


def _link_eigen_f(t, rest):
    """Materials with U = V = I (no SVD): (A, twist, flip) = f(F, mu, lam); returns found = 1 first."""
    K, f = wp.constant(t.kind), t.eigen

    def eigen_f_link(kind: int, F: Any, mu: Any, lam: Any):
        if kind == K:
            A, tw, fl = f(F, mu, lam)
            return 1, A, tw, fl
        found, A, tw, fl = rest(kind, F, mu, lam)
        return found, A, tw, fl

    return _named(eigen_f_link, "material_eigen_f", t)


def _build():
    """The chains over the registered materials; the first registered is tested first."""
    psi, pk1, eig_s, eig_f = _no_psi, _no_pk1, _no_eigen_s, _no_eigen_f
    for t in reversed(list(MATERIAL_TYPES.values())):
        psi = _link_value(t, t.psi, psi, "material_psi")
        pk1 = _link_value(t, t.pk1, pk1, "material_pk1")
        if t.svd:
            eig_s = _link_eigen_s(t, eig_s)
        else:
            eig_f = _link_eigen_f(t, eig_f)
    return psi, pk1, eig_s, eig_f


_psi_chain, _pk1_chain, _eigen_s_chain, _eigen_f_chain = _build()


@wp.func
def material_psi(kind: int, F: Any, mu: Any, lam: Any):
    """Energy density psi(F) of material ``kind``."""
    return _psi_chain(kind, F, mu, lam)


@wp.func
def material_pk1(kind: int, F: Any, mu: Any, lam: Any):
    """First Piola-Kirchhoff stress P(F) of material ``kind``."""
    return _pk1_chain(kind, F, mu, lam)


@wp.func
def material_hessian_parts(kind: int, F: Any, mu: Any, lam: Any):
    """dP/dF in eigen form before the scaling block is diagonalised: returns (U, V, A, twist, flip).

    F = U diag(s) V^T (signed SVD ``jacobi_signed_svd``, det U = det V = +1; U = V = I for linear elasticity); A =
    d2Psi/ds2 (symmetric 3x3, scaling modes U diag(q) V^T for its eigenvectors q); twist / flip
    eigenvalues of pair k (k=0 -> (1,2), 1 -> (0,2), 2 -> (0,1)). Assembly uses this directly
    (``hessian_point_prepare`` / ``hessian_point_matrix``): A needs an eigen-solve only to be
    projected where it is indefinite.
    """
    found, A0, tw0, fl0 = _eigen_f_chain(kind, F, mu, lam)
    if found != 0:
        I = wp.identity(n=3, dtype=F.dtype)
        return I, I, A0, tw0, fl0
    U, s, V = jacobi_signed_svd(F)  # ~2x cheaper than wp.svd3 in float64, and more accurate in float32
    A, tw, fl = _eigen_s_chain(kind, F, s, mu, lam)
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
