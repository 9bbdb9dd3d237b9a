"""Tetrahedralising a closed triangle surface (OBJ, STL, PLY, OFF) into a Tet4 ``VolumeMesh``.

The mesher is optional (``pip install warpfem[mesh]``):

* ``"tetgen"`` -- TetGen (H. Si, "TetGen, a Delaunay-Based Quality Tetrahedral Mesh Generator")
  through the ``tetgen`` wheel. Constrained Delaunay with radius-edge refinement: keeps the input
  surface (Steiner points may be added on it), fast. **TetGen itself is AGPL-3.0** (the Python
  wrapper is MIT): fine to use, but an application that ships it inherits the AGPL.
* ``"tetwild"`` -- TetWild (Hu et al., "Tetrahedral Meshing in the Wild") through the
  ``wildmeshing`` wheel (MPL-2.0; ``pip install warpfem[tetwild]``). Envelope-based: the boundary
  approximates the input within a tolerance, tets are well shaped, but it is ~200x slower.
* ``"auto"`` (default): TetGen when installed, else TetWild.

docs/meshing.md has the measurements behind that choice. Before any mesher runs,
:func:`check_surface` rejects what would make it fail or silently produce garbage (open,
non-manifold, degenerate, self-intersecting surfaces, NaN, bad indices) with a ``MeshError``
that says what is wrong and where. :func:`tetrahedralize_file` caches its result by a hash of
the file bytes and the options (``$WARPFEM_CACHE_DIR/tetra``, default ``~/.cache/warpfem/tetra``).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import importlib.util
import json
import logging
import math
import os
import tempfile
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from .volume_mesh import MeshError, VolumeMesh, _fmt_list, boundary_faces, tet_volumes

__all__ = ["tetrahedralize", "tetrahedralize_file", "check_surface", "read_surface", "cache_dir",
           "Tetrahedralization", "MesherNotInstalled", "DirtySurface", "SURFACE_EXTENSIONS", "MESHERS", "DEFAULTS"]

log = logging.getLogger(__name__)

#: Files that hold a surface, never tets: always tetrahedralised on load.
SURFACE_EXTENSIONS = (".obj", ".off", ".ply", ".stl")

#: Mesher name -> (Python module, pip extra that installs it, what it is).
MESHERS = {
    "tetgen": ("tetgen", "mesh", "TetGen (constrained Delaunay, AGPL-3.0) via the tetgen wheel"),
    "tetwild": ("wildmeshing", "tetwild", "TetWild (envelope-based, MPL-2.0) via the wildmeshing wheel"),
}

#: Option defaults (``None`` for max_edge_length: the surface's own resolution sets the size).
DEFAULTS = {"max_edge_length": None, "max_radius_edge_ratio": 2.0, "mesher": "auto", "target_tets": None}

#: Tets per triangle of the input surface when a mesher keeps the surface's own resolution
#: (measured with TetGen, quality 2.0: bunny.off 35,870 / 6,966 = 5.1, decimated-knight 3,424 / 1,000 = 3.4).
OWN_RESOLUTION_TETS_PER_FACE = 5.0

#: Tets per regular-tet volume of the edge bound, per mesher: TetGen's quality refinement fills the
#: bound ~3x over (bunny.off decimated: 9,865 / 29,508 / 64,938 tets where volume / regular tet gives
#: 3,000 / 10,000 / 25,000); TetWild's ideal edge length ~0.74x (two unit cubes, 3,191 for 4,324).
FILL = {"tetgen": 3.0, "tetwild": 0.75}

#: Refuse a max_edge_length that would give more tets than this (estimated from the volume).
MAX_ESTIMATED_TETS = 20_000_000

#: Bumped when the cache file layout or the meaning of an option changes.
_CACHE_VERSION = 2  # 2: target_tets is a target (a coarser surface refined) unless coarsen_only

_AREA_RTOL = 1e-14  # zero-area face: area <= _AREA_RTOL * bbox_diagonal**2


class MesherNotInstalled(MeshError, ImportError):
    """The requested mesher's Python package is missing; the message names the pip extra."""


class DirtySurface(MeshError):
    """A surface that is readable but does not bound a volume cleanly (a face repeating a vertex,
    zero-area or duplicated faces, holes, non-manifold edges, self-intersections): TetGen refuses
    it, an envelope-based mesher (TetWild) meshes it. ``problem`` is the message without the name."""

    def __init__(self, message, problem):
        super().__init__(message)
        self.problem = problem


@dataclass
class Tetrahedralization:
    """How a mesh was made from a surface (``VolumeMesh.tetrahedralization`` of the result)."""

    mesher: str
    version: str
    options: dict
    num_tets: int
    num_vertices: int
    surface_vertices: int
    surface_faces: int
    seconds: float
    source: str | None = None
    cache_path: str | None = None
    cache_hit: bool = False
    extra: dict = field(default_factory=dict)

    def describe(self) -> str:
        opts = ", ".join(f"{k} = {v:g}" if isinstance(v, float) else f"{k} = {v}"
                         for k, v in self.options.items() if k != "mesher" and v is not None)
        how = "cache hit" if self.cache_hit else f"meshed in {self.seconds:.2f} s"
        where = f", cache {self.cache_path}" if self.cache_path else ""
        coarse = ""
        if "edge_length" in self.extra:
            simple = self.extra.get("simulation_surface_faces")
            target = self.extra["target_tets"]
            tries = self.extra.get("meshes")
            direction = "finer" if self.extra.get("refined") else "coarser"
            coarse = (f"; {direction} than the surface for target_tets = {target}: {self.num_tets} tets "
                      f"({100 * (self.num_tets / target - 1):+.1f} %"
                      + (f", {tries} mesh{'es' if tries != 1 else ''}" if tries else "") + "), edge bound "
                      f"{self.extra['edge_length']:.4g}" + (f", surface simplified to {simple} triangles" if simple else "")
                      + (", TetWild's boundary re-meshed by TetGen" if self.extra.get("remeshed_from") else "")
                      + (", no clean decimation: the surface's own resolution" if self.extra.get("own_resolution") else "")
                      + (f", volume {100 * self.extra['volume_change']:+.1f} % of the surface's"
                         if "volume_change" in self.extra else ""))
        dirty = ""
        if "dirty" in self.extra:
            dirty = f"; the surface is not clean ({self.extra['dirty']}): " + (
                "its decimation is, TetGen" if self.extra.get("dirty_cleared") else "TetWild")
        return (f"tetrahedralised from a {self.surface_vertices}-vertex, {self.surface_faces}-triangle surface by "
                f"{self.mesher} ({MESHERS[self.mesher][0]} {self.version}): {self.num_tets} tets, "
                f"{self.num_vertices} vertices ({opts}; {how}{where}{coarse}{dirty})")


# ----------------------------------------------------------------------------- reading
def read_surface(path):
    """``(vertices (n, 3) float64, faces (m, 3) int64)`` of a surface file (meshio: .obj, .off,
    .ply, .stl, or any meshio file holding triangle / quad cells). Quads are split in two.
    Nothing is checked beyond shapes: see :func:`check_surface`."""
    import meshio

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"surface file not found: {path}")
    try:
        m = meshio.read(path)
    except Exception as exc:  # meshio raises ReadError / ValueError / KeyError on bad input
        raise MeshError(f"{path}: meshio could not read the file: {type(exc).__name__}: {exc}") from exc
    return _surface_of(m, path)


def _surface_of(m, path):
    tris = []
    for c in m.cells:
        data = np.asarray(c.data, dtype=np.int64)
        if c.type == "triangle" and len(data):
            tris.append(data.reshape(-1, 3))
        elif c.type == "quad" and len(data):
            q = data.reshape(-1, 4)
            tris += [q[:, [0, 1, 2]], q[:, [0, 2, 3]]]
    if not tris:
        found = sorted({f"{c.type} ({len(c.data)})" for c in m.cells if len(c.data)}) or ["none"]
        raise MeshError(f"{path}: no triangles to tetrahedralise; cell types in file: {', '.join(found)}")
    points = np.asarray(m.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"{path}: points must be 3D to tetrahedralise, got shape {points.shape}")
    return points, np.concatenate(tris, axis=0)


# ----------------------------------------------------------------------------- checking
def _dirty(pre, problem):
    return DirtySurface(f"{pre}{problem}", problem)


def _edge(e):
    return f"({int(e[0])}, {int(e[1])})"


def check_surface(vertices, faces, *, name=None, self_intersections=True, clean=True):
    """Check that a triangle surface bounds a volume; raise ``MeshError`` naming the problem.

    In order: shapes, fewer than 4 vertices, NaN/inf coordinates, face indices out of range, all
    vertices coinciding (always); then, with ``clean=True`` (what TetGen needs), each raising a
    :class:`DirtySurface`: faces repeating a vertex, zero-area faces (area <= 1e-14 * bbox diagonal^2), duplicated
    faces, open boundary (edges in one face), non-manifold edges (in more than two faces), and
    (``self_intersections=True``) self-intersections. The self-intersection test is approximate:
    candidate face pairs come from a uniform grid over face bounding boxes; for pairs sharing no
    vertex (or one vertex: the edges opposite it) it detects an edge whose ends lie strictly on
    either side of the other face's plane and which passes through that face (interior, edges or
    corners; orientation sign tests with a 1e-12 relative tolerance). Coplanar overlaps, a vertex
    lying on another face, and pairs of faces sharing an edge are not tested. Orientation is not checked (the meshers do not need it).
    Returns ``(vertices (n, 3) float64, faces (m, 3) int64)`` as arrays.
    """
    pre = f"{name}: " if name else ""
    V = np.asarray(vertices)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3:
        raise MeshError(f"{pre}vertices must have shape (n, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] == 0:
        raise MeshError(f"{pre}faces must be triangles, shape (m, 3) with m > 0, got {F.shape}")
    if not np.issubdtype(F.dtype, np.integer):
        if not (np.issubdtype(F.dtype, np.floating) and np.all(np.isfinite(F)) and np.all(F == np.round(F))):
            raise MeshError(f"{pre}face indices must be integers, got dtype {F.dtype}")
    V = V.astype(np.float64)
    F = F.astype(np.int64)
    n, m = len(V), len(F)
    if n < 4:
        raise MeshError(f"{pre}a closed surface needs at least 4 vertices, got {n}")
    bad = np.flatnonzero(~np.isfinite(V).all(axis=1))
    if bad.size:
        raise MeshError(f"{pre}vertex {bad[0]} has non-finite (NaN/inf) coordinates {V[bad[0]].tolist()}; "
                        f"{bad.size} such vertices: {_fmt_list(bad)}")
    oob = np.flatnonzero(((F < 0) | (F >= n)).any(axis=1))
    if oob.size:
        f = oob[0]
        raise MeshError(f"{pre}face {f} = {F[f].tolist()} references a vertex out of range [0, {n}); "
                        f"{oob.size} such faces: {_fmt_list(oob)}")
    used = np.unique(F)
    lo, hi = V[used].min(axis=0), V[used].max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    if not diag > 0:
        raise MeshError(f"{pre}all vertices coincide at {lo.tolist()}")
    if not clean:  # what an envelope-based mesher needs; the rest is what TetGen needs
        return V, F
    s = np.sort(F, axis=1)
    rep = np.flatnonzero((s[:, 1:] == s[:, :-1]).any(axis=1))
    if rep.size:
        f = rep[0]
        raise _dirty(pre, f"degenerate face {f} = {F[f].tolist()} repeats a vertex; {rep.size} such faces: "
                        f"{_fmt_list(rep)}")
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    zero = np.flatnonzero(area <= _AREA_RTOL * diag * diag)
    if zero.size:
        f = zero[0]
        raise _dirty(pre, f"degenerate face {f} = {F[f].tolist()} has zero area ({area[f]:.3g}; its vertices are "
                        f"collinear or coincide); {zero.size} zero-area faces: {_fmt_list(zero)}")
    _, first, inv, cnt = np.unique(s, axis=0, return_index=True, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    dup = np.flatnonzero(cnt[inv] > 1)
    if dup.size:
        f = dup[np.flatnonzero(dup != first[inv[dup]])[0]]
        raise _dirty(pre, f"face {f} = {F[f].tolist()} duplicates face {first[inv[f]]} (same three vertices); "
                        f"{dup.size - int((cnt > 1).sum())} duplicated faces")
    # edges: 3 per face, undirected
    E = np.sort(np.stack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], axis=1).reshape(-1, 2), axis=1)
    ue, einv, ecnt = np.unique(E, axis=0, return_inverse=True, return_counts=True)
    einv = einv.ravel()
    open_ = np.flatnonzero(ecnt == 1)
    if open_.size:
        e = open_[0]
        f = int(np.flatnonzero(einv == e)[0] // 3)
        raise _dirty(pre, f"the surface is open: {open_.size} boundary edges (in only one face), e.g. edge "
                        f"{_edge(ue[e])} of face {f}; close the holes (the tetrahedraliser needs a closed surface)")
    nm = np.flatnonzero(ecnt > 2)
    if nm.size:
        e = nm[0]
        fs = np.flatnonzero(einv == e) // 3
        raise _dirty(pre, f"{nm.size} non-manifold edges (in more than two faces), e.g. edge {_edge(ue[e])} "
                        f"at {np.round(V[ue[e]], 6).tolist()} shared by faces {_fmt_list(fs)}")
    if self_intersections:
        pairs = _self_intersections(V, F, diag)
        if len(pairs):
            f, g = (int(i) for i in pairs[0])
            raise _dirty(pre, f"the surface intersects itself: faces {f} = {F[f].tolist()} and {g} = {F[g].tolist()} "
                            f"cross near {np.round(V[F[[f, g]]].reshape(-1, 3).mean(axis=0), 6).tolist()}; "
                            f"{len(pairs)} crossing face pairs found")
    return V, F


def _candidate_pairs(lo, hi, max_cells_per_face=64):
    """Face pairs (i < j) whose bounding boxes share a cell of a uniform grid and overlap."""
    m = len(lo)
    ext = hi - lo
    h = float(np.median(ext.max(axis=1)))
    h = max(h, float(ext.max()) * 1e-6, 1e-300)
    while True:
        c0 = np.floor(lo / h).astype(np.int64)
        c1 = np.floor(hi / h).astype(np.int64)
        span = c1 - c0 + 1
        cells = np.prod(span, axis=1)
        if cells.max() <= max_cells_per_face or cells.sum() <= 8 * m:
            break
        h *= 2.0
    total = int(cells.sum())
    owner = np.repeat(np.arange(m), cells)
    local = np.arange(total) - np.repeat(np.cumsum(cells) - cells, cells)
    sy, sz = span[owner, 1], span[owner, 2]
    ix = c0[owner, 0] + local // (sy * sz)
    iy = c0[owner, 1] + (local // sz) % sy
    iz = c0[owner, 2] + local % sz
    key = (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791)  # hash collisions only add candidates
    order = np.lexsort((owner, key))
    key, owner = key[order], owner[order]
    pairs = []
    k = 1
    while k < total:
        same = key[k:] == key[:-k]
        if not same.any():
            break
        pairs.append(np.stack([owner[:-k][same], owner[k:][same]], axis=1))
        k += 1
    if not pairs:
        return np.zeros((0, 2), np.int64)
    p = np.sort(np.concatenate(pairs), axis=1)
    code = np.unique(p[p[:, 0] != p[:, 1]] @ np.array([m, 1], dtype=np.int64))  # 1D keys: fast unique
    p = np.stack([code // m, code % m], axis=1)
    ov = np.all((lo[p[:, 0]] <= hi[p[:, 1]]) & (lo[p[:, 1]] <= hi[p[:, 0]]), axis=1)
    return p[ov]


def _orient(a, b, c, d):
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))


def _segment_crosses_triangle(p, q, a, b, c, eps):
    """Segment pq crosses the plane of triangle abc strictly (its ends on either side) at a point
    of the closed triangle (vectorised)."""
    sp, sq = _orient(a, b, c, p), _orient(a, b, c, q)
    cross = ((sp > eps) & (sq < -eps)) | ((sp < -eps) & (sq > eps))
    s1, s2, s3 = _orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)
    inside = ((s1 >= -eps) & (s2 >= -eps) & (s3 >= -eps)) | ((s1 <= eps) & (s2 <= eps) & (s3 <= eps))
    return cross & inside


def _self_intersections(V, F, diag):
    """Face pairs (i, j) where an edge of one properly crosses the other (see check_surface)."""
    tri = V[F]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    pairs = _candidate_pairs(lo, hi)
    if len(pairs) == 0:
        return pairs
    Fi, Fj = F[pairs[:, 0]], F[pairs[:, 1]]
    shared = (Fi[:, :, None] == Fj[:, None, :])
    nshared = shared.sum(axis=(1, 2))
    eps = 1e-12 * diag ** 3
    hit = np.zeros(len(pairs), dtype=bool)
    edges = ((0, 1), (1, 2), (2, 0))
    # no shared vertex: each of the six edges against the other face
    sel = np.flatnonzero(nshared == 0)
    for A, B, idx in ((Fi, Fj, sel), (Fj, Fi, sel)):
        for u, v in edges:
            hit[idx] |= _segment_crosses_triangle(V[A[idx, u]], V[A[idx, v]], V[B[idx, 0]], V[B[idx, 1]],
                                                  V[B[idx, 2]], eps)
    # one shared vertex: the edge opposite it in each face against the other face
    sel = np.flatnonzero(nshared == 1)
    if sel.size:
        for A, B, axis in ((Fi, Fj, 2), (Fj, Fi, 1)):
            k = np.argmax(shared[sel].any(axis=axis), axis=1)  # local index of the shared vertex in A
            a = A[sel]
            r = np.arange(sel.size)
            p, q = a[r, (k + 1) % 3], a[r, (k + 2) % 3]
            b = B[sel]
            hit[sel] |= _segment_crosses_triangle(V[p], V[q], V[b[:, 0]], V[b[:, 1]], V[b[:, 2]], eps)
    return pairs[hit]


# ----------------------------------------------------------------------------- meshing
def _resolve_options(max_edge_length=None, max_radius_edge_ratio=None, mesher=None, target_tets=None, coarsen_only=False):
    opts = dict(DEFAULTS)
    if coarsen_only and target_tets is not None:  # only then (the options of other meshes print as before)
        opts["coarsen_only"] = True
    if target_tets is not None:
        if isinstance(target_tets, bool) or not isinstance(target_tets, (int, np.integer)) or target_tets < 10:
            raise MeshError(f"target_tets must be an integer >= 10, got {target_tets!r}")
        opts["target_tets"] = int(target_tets)
    if max_edge_length is not None:
        opts["max_edge_length"] = max_edge_length
    if max_radius_edge_ratio is not None:
        opts["max_radius_edge_ratio"] = max_radius_edge_ratio
    if mesher is not None:
        opts["mesher"] = mesher
    L = opts["max_edge_length"]
    if L is not None:
        if isinstance(L, bool) or not isinstance(L, (int, float, np.floating, np.integer)) or not (math.isfinite(L) and L > 0):
            raise MeshError(f"max_edge_length must be a finite number > 0 (m), got {L!r}")
        opts["max_edge_length"] = float(L)
    q = opts["max_radius_edge_ratio"]
    if isinstance(q, bool) or not isinstance(q, (int, float, np.floating, np.integer)) or not (math.isfinite(q) and q >= 1.1):
        raise MeshError(f"max_radius_edge_ratio must be a number >= 1.1 (TetGen may not terminate below), got {q!r}")
    opts["max_radius_edge_ratio"] = float(q)
    if opts["mesher"] not in ("auto", *MESHERS):
        raise MeshError(f"mesher must be one of 'auto', {', '.join(repr(k) for k in MESHERS)}, got {opts['mesher']!r}")
    if opts["mesher"] == "auto":
        opts["mesher"] = next((k for k, (mod, _, _) in MESHERS.items() if _installed(mod)), "tetgen")
    return opts


def _installed(module):
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a broken or stubbed-out package
        return False


def _import_mesher(mesher):
    module, extra, what = MESHERS[mesher]
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        others = [k for k in MESHERS if k != mesher]
        raise MesherNotInstalled(
            f"tetrahedralising a surface with {mesher!r} needs the Python package {module!r} ({what}), which is not "
            f"installed: pip install 'warpfem[{extra}]' (or pip install {module}); other meshers: "
            f"{', '.join(f'{k} (warpfem[{MESHERS[k][1]}])' for k in others)}") from exc


def _version(module):
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(module)
    except PackageNotFoundError:
        return "unknown"


def _run_tetgen(V, F, opts):
    tetgen = _import_mesher("tetgen")
    kw = {"quality": True, "minratio": opts["max_radius_edge_ratio"], "quiet": True}
    if opts["max_edge_length"] is not None:
        L = opts["max_edge_length"]
        kw["fixedvolume"] = True  # TetGen -a<volume>
        kw["maxvolume"] = L ** 3 / (6.0 * math.sqrt(2.0))  # the regular tet of edge L
    try:
        with _scratch_cwd():
            tg = tetgen.TetGen(np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int32))
            nodes, elems = tg.tetrahedralize(**kw)[:2]
    except (RuntimeError, ValueError) as exc:
        raise MeshError(f"TetGen failed: {exc} (a self-intersection or nearly touching faces that the surface check "
                        "did not catch? mesher = 'tetwild' tolerates those)") from exc
    return np.asarray(nodes, dtype=np.float64), np.asarray(elems, dtype=np.int64)


@contextlib.contextmanager
def _scratch_cwd():
    """Run the block in a fresh temporary working directory: TetGen writes ``_skipped.node/.face``
    on self-intersections and TetWild ``__tracked_surface.stl`` into the current directory."""
    old = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="warpfem-mesher-") as tmp:
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(old)


@contextlib.contextmanager
def _quiet_stdout():
    """Send file descriptor 1 to /dev/null (native code writing to stdout) for the block."""
    import sys

    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError, AttributeError):  # no usable fd 1: nothing to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _run_tetwild(V, F, opts, diag, **settings):
    wm = _import_mesher("tetwild")
    kw = dict(settings)  # (TetWild's mesh differs slightly run to run, with one thread too: the cache keeps one)
    if opts["max_edge_length"] is not None:
        kw["edge_length_r"] = min(opts["max_edge_length"] / diag, 1.0)  # relative to the bbox diagonal
    try:
        with _quiet_stdout(), _scratch_cwd():  # TetWild prints its progress with C++ streams
            t = wm.Tetrahedralizer(**kw)
            t.set_log_level(6)
            t.set_mesh(np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int32))
            t.tetrahedralize()
            out = t.get_tet_mesh(correct_surface_orientation=True)
    except (RuntimeError, ValueError) as exc:
        raise MeshError(f"TetWild failed: {exc}") from exc
    return np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)


def _enclosed_volume_and_area(V, F):
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    vol = abs(float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0))
    area = float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())
    return vol, area


def _regular_tet_volume(L):
    return L ** 3 / (6.0 * math.sqrt(2.0))


def _edge_for_tets(mesher, vol, tets):
    """The edge bound that gives about ``tets`` tets in volume ``vol`` (FILL measured per mesher)."""
    return (FILL[mesher] * vol * 6.0 * math.sqrt(2.0) / tets) ** (1.0 / 3.0)


#: A decimated surface is accepted for TetGen when its worst triangle has shape quality
#: 4 sqrt(3) area / (sum of squared edges) >= this (1 for equilateral) and its shortest edge is at least
#: ``DECIMATION_MIN_EDGE`` times the tet edge bound. Quadric edge collapse leaves slivers and
#: near-zero edges on flat or finely subdivided regions (its error is zero there); TetGen refines
#: around them into 1e-21 m^3 tets. Measured (docs/meshing.md): bunny.off's decimation has quality
#: 0.054 and edges >= 0.07 L, a 0.01-noise subdivided bunny 0.007 and 0.002 L.
DECIMATION_MIN_QUALITY = 0.02
DECIMATION_MIN_EDGE = 0.02
#: ... and must keep the enclosed volume within this fraction (the mass follows the volume).
DECIMATION_MAX_VOLUME_CHANGE = 0.1


def _triangle_quality(V, F):
    """(worst shape quality 4 sqrt(3) A / sum e^2, shortest edge) of a triangle surface."""
    e2 = np.stack([np.sum((V[F[:, (k + 1) % 3]] - V[F[:, k]]) ** 2, axis=1) for k in range(3)], axis=1)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    q = 4.0 * math.sqrt(3.0) * area / np.maximum(e2.sum(axis=1), 1e-300)
    return float(q.min()), float(math.sqrt(e2.min()))


def _tangential_relaxation(V, F, iterations):
    """Each vertex moved half-way towards the mean of its neighbours, within its tangent plane
    (the normal part of the move removed): triangle shapes even out and the surface stays put to
    first order (the enclosed volume shrinks 0.5-1 % on the meshes measured). It rounds sharp
    features, so it is the last resort of :func:`_simplified`."""
    import scipy.sparse as sp

    n = len(V)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    V = np.array(V, dtype=np.float64)

    for _ in range(iterations):
        fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        N = np.zeros_like(V)
        for k in range(3):
            np.add.at(N, F[:, k], fn)
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
        d = (A @ V) / deg[:, None] - V
        d -= np.sum(d * N, axis=1, keepdims=True) * N
        V += 0.5 * d
    return V


def _simplified(V, F, faces, name, edge=None):
    """The surface decimated to about ``faces`` triangles (quadric edge collapse, fast-simplification)
    and repaired (:func:`_repaired`), retried with 1.6, 0.7 and 2.56 times the faces while the result
    is not clean; None when no decimation is clean. Each size is tried plain, then relaxed.

    With ``edge`` (the tet edge bound) a decimation must also pass ``DECIMATION_MIN_QUALITY``,
    ``DECIMATION_MIN_EDGE`` and ``DECIMATION_MAX_VOLUME_CHANGE``. When a plain decimation does not, it
    is relaxed tangentially (3, then 10 sweeps) and the first surface that is clean and passes is
    taken; when none passes, the clean candidate of best quality is kept."""
    fs = _fast_simplification(F, name)
    vol0 = _enclosed_volume_and_area(V, F)[0]
    decimations = []

    sizes = [f for f in (int(faces), int(1.6 * faces), int(0.7 * faces), int(2.56 * faces)) if 20 <= f < 0.9 * len(F)]

    def decimation(k):  # made when first asked for (one costs ~0.2 s on a 100k-triangle surface)
        while len(decimations) <= k:
            if len(decimations) >= len(sizes):
                return None
            decimations.append(_repaired(*_decimate(fs, V, F, sizes[len(decimations)])))
        return decimations[k]

    best = None
    for k in range(4):  # each size plain, then relaxed, before the next is made
        d = decimation(k)
        if d is None:
            break
        for sweeps in (0, 3, 10) if edge is not None else (0,):
            Vd, Fd = d
            Vc = _tangential_relaxation(Vd, Fd, sweeps) if sweeps else Vd
            try:
                cand = check_surface(Vc, Fd, name=name)
            except MeshError as exc:
                log.info("%s: decimation to %d triangles (%d relaxation sweeps) is not clean (%s)", name, len(Fd), sweeps, exc)
                continue
            if edge is None:
                return cand
            q, e = _triangle_quality(*cand)
            dv = abs(_enclosed_volume_and_area(*cand)[0] / max(vol0, 1e-300) - 1.0)
            if dv > DECIMATION_MAX_VOLUME_CHANGE:
                log.info("%s: decimation to %d triangles changes the volume by %.1f %%", name, len(Fd), 100 * dv)
                continue
            if q >= DECIMATION_MIN_QUALITY and e >= DECIMATION_MIN_EDGE * edge:
                if sweeps:
                    log.info("%s: decimated surface relaxed tangentially (%d sweeps): quality %.3g", name, sweeps, q)
                return cand
            log.info("%s: decimation to %d triangles (%d sweeps) has slivers: quality %.3g, shortest edge %.3g L",
                     name, len(Fd), sweeps, q, e / edge)
            if best is None or q > best[0]:
                best = (q, cand)
    return best[1] if best is not None else None


def _repaired(V, F, rounds=5):
    """What quadric edge collapse leaves at sharp features and flat regions, removed: a zero-area face
    has its shortest edge collapsed (its two ends merged at their midpoint), faces repeating a
    vertex are dropped, and a face listed twice (a flap folded back onto itself: both copies) is
    dropped; repeated until nothing changes (at most ``rounds``), unused vertices removed. The
    result is not checked (:func:`check_surface` decides)."""
    V = np.array(V, dtype=np.float64)
    F = np.array(F, dtype=np.int64)
    for _ in range(rounds):
        changed = False
        if len(F) == 0:
            break
        diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
        a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        zero = np.flatnonzero(area <= 1e3 * _AREA_RTOL * diag * diag)
        if zero.size:
            parent = np.arange(len(V))
            for f in zero:  # few: a loop is fine
                tri = F[f]
                e = [np.sum((V[tri[(k + 1) % 3]] - V[tri[k]]) ** 2) for k in range(3)]
                k = int(np.argmin(e))
                i, j = int(tri[k]), int(tri[(k + 1) % 3])
                while parent[i] != i:
                    i = parent[i]
                while parent[j] != j:
                    j = parent[j]
                if i != j:
                    V[min(i, j)] = 0.5 * (V[i] + V[j])
                    parent[max(i, j)] = min(i, j)
            for v in range(len(parent)):  # flatten
                r = v
                while parent[r] != r:
                    r = parent[r]
                parent[v] = r
            F = parent[F]
            changed = True
        s = np.sort(F, axis=1)
        keep = (s[:, 1:] != s[:, :-1]).all(axis=1)
        _, inv, cnt = np.unique(s, axis=0, return_inverse=True, return_counts=True)
        keep &= cnt[inv.ravel()] == 1
        if not keep.all():
            F = F[keep]
            changed = True
        if not changed:
            break
    used = np.unique(F)
    remap = np.full(len(V), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return V[used], remap[F]


def _fast_simplification(F, name):
    try:
        import fast_simplification
    except ImportError as exc:
        raise MesherNotInstalled(
            f"{name + ': ' if name else ''}a coarse simulation mesh of a {len(F)}-triangle surface (target_tets) needs the "
            "Python package 'fast_simplification' (quadric surface decimation), which is not installed: pip install "
            "'warpfem[mesh]' (or pip install fast-simplification), or set max_edge_length") from exc
    return fast_simplification


def _decimate(fs, V, F, faces):
    Vd, Fd = fs.simplify(np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int32),
                         target_reduction=1.0 - faces / len(F))
    return np.asarray(Vd, dtype=np.float64), np.asarray(Fd, dtype=np.int64)


#: ``target_tets`` is met when the count is within this fraction of it (documented: 10 %); the
#: edge bound is corrected (secant on log count against log edge) until then, at most
#: ``TARGET_TRIES`` meshes in all, and the closest count is kept.
TARGET_TOLERANCE = 0.1
TARGET_TRIES = 4
#: A TetWild run for a coarse physics mesh (a decimated or dirty surface under target_tets) uses a
#: looser envelope and fewer optimisation passes than its defaults: 16 s instead of 49 s for 17k
#: tets from the 2,000-triangle decimated scan stand-in (the render surface is the input anyway).
TETWILD_COARSE = {"epsilon": 4e-3, "max_its": 20, "stop_quality": 20.0}


def _faces_for_edge(area, L):
    return max(int(area / (math.sqrt(3.0) / 4.0 * L * L)), 20)


def _next_edge(history, target):
    """The next edge bound from the (edge, count) meshes so far: count ~ L^-b from the mesh closest
    to the target, b from the two closest (clamped to [1.5, 6]; 3 after one mesh, or when the
    counts do not fall as the edge grows: a decimation of another size can do that)."""
    ranked = sorted(history, key=lambda h: abs(math.log(max(h[1], 1) / target)))
    (L1, n1) = ranked[0]
    b = 3.0
    if len(ranked) >= 2:
        L0, n0 = ranked[1]
        if n0 > 0 and n1 > 0 and n0 != n1 and abs(math.log(L1 / L0)) > 1e-6:
            slope = -math.log(n1 / n0) / math.log(L1 / L0)
            b = min(max(slope, 1.5), 6.0) if slope > 0 else 3.0
    L = L1 * (max(n1, 1) / target) ** (1.0 / b)
    if any(abs(L / h[0] - 1.0) < 1e-3 for h in history):  # no new point: a smaller step from the best
        L = L1 * (max(n1, 1) / target) ** (1.0 / 6.0)
    return L


def _off(n, target):
    return abs(n / target - 1.0)


def _tetgen_to_target(V, F, area, target, opts, diag, name, L, stages, tries=TARGET_TRIES, clean=True, as_is=False,
                      seed=None, keep_surface=False):
    """TetGen meshes of ``V, F`` decimated to the triangle size of the edge bound, the bound corrected
    until the count is within TARGET_TOLERANCE of ``target``. Returns (nodes, tets, L, faces, history)
    of the closest, or None when no clean decimation exists (first try). ``clean=False``: ``V, F``
    itself is not clean (only its decimations may be meshed); ``as_is=True``: when no decimation is
    clean, ``V, F`` itself is meshed (a coarse surface: TetWild's boundary). ``seed``: an (edge, count)
    measured before (the surface's own resolution), the secant's first point. ``keep_surface``: never
    decimate (refining: only the edge bound changes)."""
    best, history = None, [seed] if seed else []
    for k in range(tries):
        faces = _faces_for_edge(area, L)
        if faces >= 0.9 * len(F) or keep_surface:
            surf = (V, F) if clean else None
        else:
            with stages.stage(f"decimating {len(F)} to about {faces} triangles (quadric edge collapse)"):
                surf = _simplified(V, F, faces, name, edge=L)
            if surf is None and as_is and clean:
                surf = (V, F)
        if surf is None:
            if best is None:
                return None
            break
        run = dict(opts, mesher="tetgen", max_edge_length=L)
        try:
            with stages.stage(f"TetGen: filling {len(surf[1])} triangles, edge bound {L:.4g} (mesh {k + 1} of at most {tries})"):
                nodes, tets = _run_tetgen(*surf, run)
        except MeshError as exc:  # a crossing the approximate surface check missed
            log.info("%s: %s", name, exc)
            if best is None:
                return None
            break
        n = len(tets)
        history.append((L, n))
        stages.note(f"{n} tets ({100 * (n / target - 1):+.1f} % of target_tets = {target})")
        if best is None or _off(n, target) < _off(len(best[1]), target):
            best = (nodes, tets, L, len(surf[1]) if surf[1] is not F else None)
        if _off(n, target) <= TARGET_TOLERANCE or n == 0:
            break
        L = _next_edge(history, target)
    return (*best, history[1:] if seed else history)


def _own_edge(vol, tets):
    """The TetGen edge bound that would give ``tets`` tets (a mesh made without one, for the secant)."""
    return _edge_for_tets("tetgen", vol, max(tets, 1))


def _tetwild_to_target(V, F, target, opts, diag, L, stages, tries, settings=None):
    """TetWild meshes (coarse settings, TETWILD_COARSE) with the ideal edge corrected as in
    :func:`_tetgen_to_target`; returns (nodes, tets, L, history) of the closest."""
    best, history = None, []
    for k in range(tries):
        run = dict(opts, mesher="tetwild", max_edge_length=L)
        with stages.stage(f"TetWild: meshing {len(F)} triangles, ideal edge {L:.4g} (mesh {k + 1} of at most {tries}; "
                          "one native call, typically 15-60 s, silent until it ends)"):
            nodes, tets = _run_tetwild(V, F, run, diag, **(TETWILD_COARSE if settings is None else settings))
        n = len(tets)
        history.append((L, n))
        stages.note(f"{n} tets ({100 * (n / target - 1):+.1f} % of target_tets = {target})")
        if best is None or _off(n, target) < _off(len(best[1]), target):
            best = (nodes, tets, L)
        if _off(n, target) <= TARGET_TOLERANCE or n == 0:
            break
        L = _next_edge(history, target)
    return (*best, history)


def tetrahedralize(vertices, faces, *, max_edge_length=None, max_radius_edge_ratio=None, mesher=None,
                   target_tets=None, name=None, check=True, coarsen_only=False):
    """Fill a closed triangle surface with tets; returns a Tet4 ``VolumeMesh``.

    Parameters
    ----------
    vertices, faces : (n, 3) float and (m, 3) int arrays of the surface.
    max_edge_length : float, optional
        Target largest tet edge (same units as ``vertices``). TetGen bounds each tet's volume by
        that of the regular tet of this edge (L^3 / (6 sqrt 2)); TetWild uses it as its ideal edge
        length. Default: none for TetGen (the surface's own triangles set the size), TetWild's
        bbox diagonal / 20.
    max_radius_edge_ratio : float, default 2.0
        TetGen's quality bound (circumradius / shortest edge of every tet, -q): smaller is better
        shaped, more tets; >= 1.1. TetWild ignores it (it optimises its own AMIPS energy).
    mesher : "auto" (default), "tetgen" or "tetwild". With "auto", a surface that is readable but
        not clean (holes, duplicated or degenerate faces, non-manifold edges, self-intersections)
        goes to TetWild with a warning naming the defect when TetWild is installed (under
        ``target_tets``, its clean decimation goes to TetGen first); otherwise the error says what
        is wrong and how to install it. A named mesher is used as asked.
    target_tets : int, optional
        Used when ``max_edge_length`` is not given: the mesh gets ``target_tets`` tets within 10 %
        (``TARGET_TOLERANCE``). A surface whose own resolution gives more is meshed coarser.
        TetGen meshes the surface decimated (quadric edge collapse) to the triangle size of the
        edge bound expected to give ``target_tets``; the bound is then corrected from the counts
        measured (at most ``TARGET_TRIES`` meshes, the closest kept). When no clean decimation
        exists or the surface is dirty, TetWild meshes the decimated surface and, with ``auto``,
        TetGen re-meshes TetWild's boundary to the target. A surface whose own resolution gives
        fewer tets is meshed finer (the edge bound corrected the same way), unless ``coarsen_only``.
        The input surface is not changed: embed it as the render surface (scenes do so by default).
    coarsen_only : bool
        ``target_tets`` only bounds the count from above: a surface whose own resolution gives fewer
        tets keeps it (what a scene does with its default ``target_tets``).
    name : used as the prefix of error messages and in the progress lines (a file name).
    check : run :func:`check_surface` first (default True).

    Progress: one line per stage (check, decimation, each mesher run and its count) through
    :class:`warpfem.progress.Stages` (silent unless a writer is set: the command line's stderr).
    The result carries ``.tetrahedralization`` (a :class:`Tetrahedralization`).
    """
    from warpfem.progress import Stages

    requested = mesher if mesher is not None else "auto"
    opts = _resolve_options(max_edge_length, max_radius_edge_ratio, mesher, target_tets, coarsen_only)
    pre = f"{name}: " if name else ""
    stages = Stages(f"meshing {os.path.basename(name) if name else 'a surface'}")
    dirty = ""
    n_in = len(np.asarray(faces))
    # a surface that will be decimated for target_tets: its decimation is checked for crossings (what
    # the mesher sees), the input only for the rest (the crossing test is most of a 100k-triangle check)
    decimated_ahead = (max_edge_length is None and opts["target_tets"] is not None and opts["mesher"] == "tetgen"
                       and OWN_RESOLUTION_TETS_PER_FACE * n_in > 2.0 * opts["target_tets"])
    if check:
        try:
            with stages.stage(f"checking the {n_in}-triangle surface (closed, manifold"
                              + (")" if decimated_ahead else ", no self-intersection)")):
                V, F = check_surface(vertices, faces, name=name, self_intersections=not decimated_ahead)
        except DirtySurface as exc:
            if requested != "auto":
                raise
            if not _installed(MESHERS["tetwild"][0]):
                if not (target_tets is not None and max_edge_length is None and _installed("fast_simplification")):
                    raise DirtySurface(f"{exc}. TetGen cannot mesh such a surface; TetWild (envelope-based) can: "
                                       f"pip install 'warpfem[tetwild]', then load it again (or repair the surface)",
                                       exc.problem) from exc
            V, F = check_surface(vertices, faces, name=name, clean=False)
            dirty = exc.problem
    else:
        V, F = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    nsurf_v, nsurf_f = len(V), len(F)
    used = np.unique(F)
    if used.size < len(V):  # isolated vertices would become points of the tet mesh
        remap = np.full(len(V), -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        log.info("%s%d surface vertices used by no face dropped", pre, len(V) - used.size)
        V, F = V[used], remap[F]
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    vol, area = _enclosed_volume_and_area(V, F)
    extra = {}
    L = opts["max_edge_length"]
    target = opts["target_tets"]
    if dirty and not (L is None and target is not None):  # no decimation ahead: TetWild as before
        opts["mesher"] = "tetwild"
    if opts["mesher"] == "tetgen":  # TetGen keeps the surface's triangles; TetWild's default edge is diag / 20
        own = OWN_RESOLUTION_TETS_PER_FACE * len(F)
    else:
        own = FILL["tetwild"] * vol / _regular_tet_volume(diag / 20.0)
    coarsen = L is None and target is not None and (own > target or dirty)
    if L is not None:
        est = vol / _regular_tet_volume(L)
        if est > MAX_ESTIMATED_TETS:
            raise MeshError(f"{pre}max_edge_length = {L:g} would give about {est:.3g} tets "
                            f"(enclosed volume {vol:.4g}, limit {MAX_ESTIMATED_TETS:.0e}); use a larger max_edge_length")
    if dirty and not coarsen:
        warnings.warn(f"{pre}{dirty}: meshed with TetWild (envelope-based, tolerates it) instead of TetGen",
                      RuntimeWarning, stacklevel=2)
    t0 = time.perf_counter()
    nodes = tets = None
    if not coarsen:
        what = {"tetgen": "TetGen", "tetwild": "TetWild"}[opts["mesher"]]
        with stages.stage(f"{what}: meshing {len(F)} triangles" + (f", edge bound {L:.4g}" if L is not None else
                                                                 f" at the surface's own resolution (about {own:.0f} tets)")):
            nodes, tets = _run(V, F, opts, diag)
        if L is None and target is not None and len(tets) > (1.0 + TARGET_TOLERANCE) * target:
            stages.note(f"{len(tets)} tets at the surface's own resolution, more than target_tets = {target}: coarser")
            coarsen = True  # the own-resolution estimate was low
        elif (L is None and target is not None and not coarsen_only
              and len(tets) < (1.0 - TARGET_TOLERANCE) * target):
            stages.note(f"{len(tets)} tets at the surface's own resolution, fewer than target_tets = {target}: finer")
            L0 = _edge_for_tets(opts["mesher"], vol, target)
            if opts["mesher"] == "tetgen":
                got = _tetgen_to_target(V, F, area, target, opts, diag, name, L0, stages, clean=not dirty,
                                        seed=(_own_edge(vol, len(tets)), len(tets)), keep_surface=True)
                if got is not None and _off(len(got[1]), target) < _off(len(tets), target):
                    nodes, tets, L, faces, history = got
                    extra.update(refined=True, meshes=1 + len(history))
                    if faces is not None:
                        extra.update(simulation_surface_faces=int(faces))
            else:
                n0 = len(tets)
                got = _tetwild_to_target(V, F, target, opts, diag, L0, stages, TARGET_TRIES - 1, settings={})
                if _off(len(got[1]), target) < _off(n0, target):
                    nodes, tets, L, history = got
                    extra.update(refined=True, meshes=1 + len(history))
    if extra.get("refined"):
        extra.update(edge_length=float(L), target_tets=int(target))
    if coarsen:
        nodes, tets, L = _coarse_mesh(V, F, vol, area, diag, target, opts, requested, dirty, name, stages, extra)
    seconds = time.perf_counter() - t0
    if coarsen:
        extra.update(edge_length=float(L), target_tets=int(target))
    if dirty:
        extra.update(dirty=dirty)
    if len(tets) == 0:
        raise MeshError(f"{pre}{opts['mesher']} produced no tets (does the surface enclose a volume?)")
    with stages.stage(f"checking the {len(tets)}-tet mesh"):
        mesh = VolumeMesh(nodes, tets, name=name)
    if coarsen and vol > 0.0:  # what decimation did to the volume (and so to the mass)
        extra.update(volume_change=float(mesh.total_volume() / vol - 1.0))
    module = MESHERS[opts["mesher"]][0]
    mesh.tetrahedralization = Tetrahedralization(
        mesher=opts["mesher"], version=_version(module), options=opts, num_tets=mesh.num_elements,
        num_vertices=mesh.num_vertices, surface_vertices=nsurf_v, surface_faces=nsurf_f, seconds=seconds, source=name,
        extra=extra)
    stages.note(f"done: {mesh.num_elements} tets, {mesh.num_vertices} vertices by {opts['mesher']}")
    log.info("%s", mesh.tetrahedralization.describe())
    return mesh


def _coarse_mesh(V, F, vol, area, diag, target, opts, requested, dirty, name, stages, extra):
    """The coarse physics mesh for ``target_tets`` (see :func:`tetrahedralize`); sets ``opts['mesher']``
    to the mesher that made it and fills ``extra``. Returns (nodes, tets, edge bound)."""
    pre = f"{name}: " if name else ""
    have_tetgen, have_tetwild = _installed(MESHERS["tetgen"][0]), _installed(MESHERS["tetwild"][0])
    use_tetgen = opts["mesher"] == "tetgen" or (dirty and requested == "auto" and have_tetgen)
    if use_tetgen:
        L = _edge_for_tets("tetgen", vol, target)
        got = _tetgen_to_target(V, F, area, target, opts, diag, name, L, stages, clean=not dirty)
        if got is not None:
            nodes, tets, L, faces, history = got
            opts["mesher"] = "tetgen"
            if faces is not None:
                extra.update(simulation_surface_faces=int(faces))
            extra.update(meshes=len(history))
            if dirty:
                extra.update(dirty_cleared="its decimation is clean")
                log.info("%s%s: the decimated surface is clean, meshed by TetGen", pre, dirty)
            return nodes, tets, L
        faces = _faces_for_edge(area, L)
        if not have_tetwild:
            if dirty:
                raise DirtySurface(f"{pre}{dirty}. No clean decimation of it to about {faces} triangles either; "
                                   "TetWild (envelope-based) meshes such a surface: pip install 'warpfem[tetwild]', "
                                   "then load it again (or repair the surface)", dirty)
            warnings.warn(f"{pre}no clean decimation of the {len(F)}-triangle surface to about {faces} triangles: "
                          f"meshed at the surface's own resolution instead of target_tets = {target}. TetWild makes "
                          "the coarse mesh from such a surface: pip install 'warpfem[tetwild]'; or set max_edge_length",
                          RuntimeWarning, stacklevel=3)
            with stages.stage(f"TetGen: meshing {len(F)} triangles at the surface's own resolution"):
                nodes, tets = _run_tetgen(V, F, dict(opts, mesher="tetgen", max_edge_length=None))
            opts["mesher"] = "tetgen"
            extra.update(own_resolution=True)
            return nodes, tets, L
        why = dirty or f"no clean decimation of the {len(F)}-triangle surface to about {faces} triangles"
        warnings.warn(f"{pre}{why}: the coarse mesh for target_tets is made by TetWild (envelope-based) from the "
                      "decimated surface" + (", then TetGen re-meshes its boundary to the target" if have_tetgen else ""),
                      RuntimeWarning, stacklevel=3)
    # TetWild on the surface decimated to about the triangle size of its edge (any cleanliness will do)
    L = _edge_for_tets("tetwild", vol, target)
    faces = _faces_for_edge(area, L) * 2
    Vw, Fw = V, F
    if faces < 0.9 * len(F) and _installed("fast_simplification"):
        with stages.stage(f"decimating {len(F)} to about {faces} triangles for TetWild"):
            Vw, Fw = _decimate(_fast_simplification(F, name), V, F, faces)
        extra.update(simulation_surface_faces=int(len(Fw)))
    hybrid = requested == "auto" and have_tetgen
    nodes, tets, L, history = _tetwild_to_target(Vw, Fw, target, opts, diag, L, stages, 1 if hybrid else TARGET_TRIES - 1)
    opts["mesher"] = "tetwild"
    extra.update(meshes=len(history))
    if _off(len(tets), target) <= TARGET_TOLERANCE or not hybrid or len(tets) == 0:
        return nodes, tets, L
    # TetWild's boundary is a clean closed surface: TetGen fills it to the target (fast retries)
    bV, bF = _boundary_surface(nodes, tets)
    try:
        bV, bF = check_surface(bV, bF, name=name)
    except MeshError as exc:
        log.info("%sTetWild's boundary is not clean (%s): its mesh is kept", pre, exc)
        return nodes, tets, L
    barea = _enclosed_volume_and_area(bV, bF)[1]
    got = _tetgen_to_target(bV, bF, barea, target, opts, diag, name, _edge_for_tets("tetgen", vol, target), stages,
                            as_is=True)
    if got is None or _off(len(got[1]), target) >= _off(len(tets), target):
        return nodes, tets, L
    nodes, tets, L, faces, history2 = got
    opts["mesher"] = "tetgen"
    extra.update(meshes=len(history) + len(history2), remeshed_from="tetwild",
                 simulation_surface_faces=int(faces if faces is not None else len(bF)))
    return nodes, tets, L


def _boundary_surface(nodes, tets):
    """(vertices, faces) of a tet mesh's boundary, unused vertices dropped."""
    tets = np.asarray(tets, dtype=np.int64)
    X = np.asarray(nodes, dtype=np.float64)
    vol = tet_volumes(X, tets)
    t = tets.copy()
    neg = vol < 0
    t[neg] = t[neg][:, [0, 1, 3, 2]]
    F = boundary_faces(t)
    used = np.unique(F)
    remap = np.full(len(X), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return X[used], remap[F]


def _run(V, F, opts, diag):
    if opts["mesher"] == "tetgen":
        return _run_tetgen(V, F, opts)
    return _run_tetwild(V, F, opts, diag)


# ----------------------------------------------------------------------------- file + cache
def cache_dir():
    """Folder of cached tetrahedralisations: ``$WARPFEM_CACHE_DIR/tetra`` if set, else
    ``$XDG_CACHE_HOME/warpfem/tetra`` or ``~/.cache/warpfem/tetra``."""
    root = os.environ.get("WARPFEM_CACHE_DIR")
    if not root:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(base, "warpfem")
    return os.path.join(root, "tetra")


def _cache_key(data: bytes, opts: dict) -> str:
    h = hashlib.sha256()
    h.update(f"warpfem-tetra-v{_CACHE_VERSION}\0".encode())
    h.update(data)
    h.update(b"\0" + json.dumps(opts, sort_keys=True).encode())
    return h.hexdigest()


def _read_cache(path):
    try:
        with np.load(path, allow_pickle=False) as z:
            V, T, meta = z["vertices"], z["tets"], json.loads(str(z["meta"]))
        if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4:
            raise ValueError("bad array shapes")
        return V, T, meta
    except FileNotFoundError:
        return None
    except Exception as exc:  # a truncated / foreign file: re-mesh and overwrite it
        log.warning("ignoring unreadable tetrahedralisation cache %s: %s", path, exc)
        return None


def _write_cache(path, mesh):
    """Write atomically (temporary file in the same folder, then rename); failures only warn."""
    info = mesh.tetrahedralization
    meta = {"mesher": info.mesher, "version": info.version, "options": info.options, "seconds": info.seconds,
            "surface_vertices": info.surface_vertices, "surface_faces": info.surface_faces, "source": info.source,
            "extra": info.extra}
    tmp = None
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".npz", dir=os.path.dirname(path))
        with os.fdopen(fd, "wb") as f:
            np.savez(f, vertices=mesh.vertices, tets=mesh.tets, meta=np.array(json.dumps(meta)))
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        log.warning("could not write the tetrahedralisation cache %s: %s", path, exc)
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def tetrahedralize_file(path, *, max_edge_length=None, max_radius_edge_ratio=None, mesher=None, cache=True,
                        check=True, target_tets=None, coarsen_only=False):
    """Read a surface file (.obj, .off, .ply, .stl, or any meshio file with triangles), check it and tetrahedralise it (see :func:`tetrahedralize`), through the cache.

    The cache key is a SHA-256 of the file bytes and the resolved options (mesher included), so
    editing the file or changing an option re-meshes; the entry is
    ``cache_dir()/<stem>-<key>.npz``. ``cache=False`` neither reads nor writes it.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"surface file not found: {path}")
    opts = _resolve_options(max_edge_length, max_radius_edge_ratio, mesher, target_tets, coarsen_only)
    with open(path, "rb") as f:
        data = f.read()
    entry = None
    if cache:
        stem = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in os.path.splitext(os.path.basename(path))[0])
        entry = os.path.join(cache_dir(), f"{stem[:40]}-{_cache_key(data, opts)[:32]}.npz")
        hit = _read_cache(entry)
        if hit is not None:
            V, T, meta = hit
            mesh = VolumeMesh(V, T, name=path)
            mesh.tetrahedralization = Tetrahedralization(
                mesher=meta["mesher"], version=meta["version"], options=meta["options"], num_tets=mesh.num_elements,
                num_vertices=mesh.num_vertices, surface_vertices=meta["surface_vertices"],
                surface_faces=meta["surface_faces"], seconds=meta["seconds"], source=path, cache_path=entry,
                cache_hit=True, extra=meta.get("extra", {}))
            log.info("%s: tetrahedralisation cache hit %s", path, entry)
            return mesh
    V, F = read_surface(path)
    mesh = tetrahedralize(V, F, name=path, check=check, max_edge_length=max_edge_length,
                          max_radius_edge_ratio=max_radius_edge_ratio, mesher=mesher, target_tets=target_tets,
                          coarsen_only=coarsen_only)
    if entry is not None:
        _write_cache(entry, mesh)
        mesh.tetrahedralization.cache_path = entry
    return mesh
