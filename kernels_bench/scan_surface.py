"""A scanned-surface stand-in made from the shipped bunny: midpoint subdivision and noise along the
normals (kernels_bench/bench_scan.py, tests/test_surface_in.py)."""

from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def midpoint_subdivide(V, F):
    """Every triangle into four through its edge midpoints (shared midpoints: the result stays closed)."""
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    edges, inv = np.unique(E, axis=0, return_inverse=True)
    inv = inv.reshape(3, -1).T + len(V)  # midpoint ids of edges (01, 12, 20) of each face
    V2 = np.concatenate([V, 0.5 * (V[edges[:, 0]] + V[edges[:, 1]])])
    a, b, c = F.T
    ab, bc, ca = inv.T
    F2 = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return V2, F2


def vertex_normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for k in range(3):
        np.add.at(N, F[:, k], n)
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)


def make_scan(subdivisions, noise, seed=0):
    from warpfem.mesh.tetrahedralization import read_surface

    V, F = read_surface(ROOT / "examples" / "meshes" / "bunny.off")
    for _ in range(subdivisions):
        V, F = midpoint_subdivide(V, F)
    h = float(np.mean(np.linalg.norm(V[F[:, 1]] - V[F[:, 0]], axis=1)))
    rng = np.random.default_rng(seed)
    V = V + vertex_normals(V, F) * (noise * h * rng.standard_normal(len(V)))[:, None]
    return V, F, h
