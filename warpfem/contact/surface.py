"""Contact between bodies and of a body with itself: the model's boundary surface against itself.

:func:`contact_surface` extracts, from a volume mesh (and an optional per-vertex body id), the
surface triangles, their unique edges, the surface vertices and a group id per vertex (the
connected component of the element graph, split further by body id): two primitives of the same
group are *self* contact, of different groups *body* contact. :class:`SurfaceContact` holds them on
the device with two Warp BVHs (triangles, edges), finds the candidate pairs of each Newton
iteration (``wp.bvh_query_aabb`` over boxes of the segment x -> x + s d padded by dhat / 2,
refitted per query), grows the Hessian's pattern for new pairs (``HessianSystem.ensure_blocks``)
and lags friction at the step start; :class:`SurfaceContactForm` is its form of the incremental
potential (energy, gradient, SPD-projected Hessian blocks, additive-CCD ``max_step``). The
kernels and the formulas: :mod:`warpfem.contact.surface_kernels`; docs/contact.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import logging

import numpy as np
import warp as wp

from warpfem.contact import surface_kernels as SK
from warpfem.contact.colliders import default_dhat, default_friction_velocity
from warpfem.contact.colliders import default_stiffness as _default_stiffness
from warpfem.contact.contact import CollisionError, LaggedFrictionForm
from warpfem.contact.stiffness import AdaptiveStiffness, parse_stiffness
from warpfem.solvers.forms import InfeasibleStart
from warpfem.kernels.generic import launch
from warpfem.transfer import read, read_int, read_scalar, to_device, upload

log = logging.getLogger(__name__)

__all__ = ["ContactSurface", "contact_surface", "SurfaceContact", "SurfaceContactForm", "CONTACT_KEYS", "pair_terms"]

#: the keys of ``Simulator.set_contact`` and of a scene's ``[contact]`` table
CONTACT_KEYS = ("bodies", "self", "friction", "dhat", "stiffness", "friction_velocity")
STEP_ETA = 0.2  # the step bound keeps each pair's gap at least this fraction of its current one
#: the start check (``SurfaceContactForm.check_start``): a kinematic motion that brings no pair within this
#: fraction of its gap passes with one read-back; otherwise distances and crossings are tested exactly
CHECK_ETA = 0.01
#: Jacobi's stopping test of the per-pair PSD projection: off-diagonal squared norm below this x |H|^2
JACOBI_TOL = {np.dtype(np.float64): 1e-22, np.dtype(np.float32): 1e-11}
#: the broad phase's candidates are the pairs within this many dhat over the segment (the margin
#: lets later line searches whose boxes fit in these reuse them, and the pattern grow less often)
QUERY_MARGIN = 2.0
#: self pairs closer than this many dhat in the rest shape get no barrier (only the step bound):
#: features that are close but not neighbours at rest (short edges, slivers) are not pushed apart
REST_GAP = 1.0
#: gradients and Hessian blocks per pair into slots, then gathered per vertex and per block in a fixed
#: order (bit-identical whatever the thread count, on every device); False: added with atomics (the
#: reference of tests and benchmarks; CPU launches are then not split)
GATHER = True


def slot_map(keys):
    """(targets, offsets, entries) int32: the distinct values of ``keys`` (ascending) and, per
    target t, the positions k with keys[k] == targets[t] in ascending order,
    ``entries[offsets[t]:offsets[t + 1]]``: the map a gather follows (a CSR of slot -> target)."""
    keys = np.asarray(keys, dtype=np.int64).reshape(-1)
    n = len(keys)
    # one sort of (key, position) packed into an int64 (unique values: a plain sort is a stable one,
    # and sorting values is several times faster than an argsort)
    packed = np.sort(keys * max(n, 1) + np.arange(n, dtype=np.int64))
    sorted_keys = packed // max(n, 1)
    order = packed - sorted_keys * max(n, 1)
    first = np.ones(n, dtype=bool)
    first[1:] = sorted_keys[1:] != sorted_keys[:-1]
    starts = np.flatnonzero(first)
    offsets = np.append(starts, n)
    return sorted_keys[starts].astype(np.int32), offsets.astype(np.int32), order.astype(np.int32)


def canonical_order(pairs, kinds):
    """The permutation that sorts candidate pairs by (kind, vertex ids): the pair list's order no
    longer depends on the broad phase's (thread count, device, BVH traversal)."""
    pairs = np.asarray(pairs).reshape(-1, 4)
    return np.lexsort((pairs[:, 3], pairs[:, 2], pairs[:, 1], pairs[:, 0], np.asarray(kinds).reshape(-1)))


class _GatherMap:
    """A gather map (``slot_map``) on the device, its buffers grown by powers of two and reused."""

    def __init__(self, device):
        self.device = device
        self.n = 0
        self.bufs = None

    def set(self, keys):
        t, o, e = slot_map(keys)
        self.n = len(t)
        if self.n == 0:
            return self
        need = (len(t), len(o), len(e))
        if self.bufs is None or any(b.shape[0] < k for b, k in zip(self.bufs, need)):
            self.bufs = tuple(wp.zeros(_capacity(k), dtype=wp.int32, device=self.device) for k in need)
        for b, a in zip(self.bufs, (t, o, e)):
            upload(b[:len(a)], a)
        return self

    def gather(self, kernel, active, shift, contrib, out):
        if self.n:
            launch(kernel, self.n, [*self.bufs, active, shift, contrib, out], self.device)


@dataclass
class ContactSurface:
    """The boundary surface of a model for contact.

    triangles (m, 3), edges (e, 2) (unique, i < j) and vertices (v,) are mesh vertex indices;
    group (n,) int32 per mesh vertex (connected component x body); num_groups."""

    triangles: np.ndarray
    edges: np.ndarray
    vertices: np.ndarray
    group: np.ndarray
    num_groups: int



def connected_labels(n: int, rows, cols) -> np.ndarray:
    """Connected components of the undirected graph on n vertices with edges (rows[k], cols[k]): a
    label 0..c-1 per vertex, numbered in the order of each component's smallest vertex (as
    ``scipy.sparse.csgraph.connected_components`` numbers them), in numpy: each round hooks every
    edge's larger root onto its smaller one, then jumps pointers to the roots (a few rounds; no
    scipy.sparse.linalg import at contact set-up)."""
    rows = np.asarray(rows, dtype=np.int64)
    cols = np.asarray(cols, dtype=np.int64)
    lab = np.arange(n, dtype=np.int64)
    while True:
        a, b = lab[rows], lab[cols]
        new = lab.copy()
        np.minimum.at(new, np.maximum(a, b), np.minimum(a, b))
        while True:  # every vertex to its root
            nxt = new[new]
            if np.array_equal(nxt, new):
                break
            new = nxt
        if np.array_equal(new, lab):
            break
        lab = new
    return np.unique(lab, return_inverse=True)[1].reshape(-1)

def contact_surface(mesh, body=None, *, elements=None) -> ContactSurface:
    """The contact surface of ``mesh`` (a :class:`~warpfem.mesh.VolumeMesh`: its
    ``boundary_faces()``). ``body``: optional (n,) body id per vertex (a model of several
    bodies); groups are the connected components of the element graph (``elements``: (m, k)
    connectivity or a list of such tables, one per element type; default ``mesh.elements``, else
    the surface triangles; the surface triangles connect as well), split by body id."""
    faces = np.asarray(mesh.boundary_faces(), dtype=np.int64).reshape(-1, 3)
    n = int(mesh.num_vertices)
    if elements is None:
        elements = getattr(mesh, "elements", None)
    tables = elements if isinstance(elements, (list, tuple)) else [elements]
    tables = [np.asarray(E, dtype=np.int64) for E in tables if E is not None]
    tables = [E for E in tables if E.ndim == 2 and E.size]
    # the surface triangles connect too: vertices no element holds (a rigid body's surface) are
    # one group per connected surface instead of one each (for elements' vertices they add nothing)
    tables.append(faces)
    rows = np.concatenate([np.repeat(E[:, 0], E.shape[1]) for E in tables])
    cols = np.concatenate([E.ravel() for E in tables])
    comp = connected_labels(n, rows, cols)
    if body is not None:
        body = np.asarray(body, dtype=np.int64).reshape(-1)
        if body.shape != (n,):
            raise ValueError(f"contact_surface: body must hold one id per vertex ({n}), got shape {body.shape}")
        _, comp = np.unique(np.stack([body, comp], axis=1), axis=0, return_inverse=True)
    _, group = np.unique(comp, return_inverse=True)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    return ContactSurface(triangles=faces, edges=e, vertices=np.unique(faces), group=group.reshape(-1).astype(np.int32),
                          num_groups=int(group.max()) + 1 if n else 0)


def _barrier_slope(d, dhat):
    """b'(d) of b(d) = -(d - dhat)^2 ln(d / dhat)."""
    return -2.0 * (d - dhat) * np.log(d / dhat) - (d - dhat) ** 2 / d


def _capacity(k):
    return int(2 ** int(np.ceil(np.log2(max(int(k), 256)))))


def pair_terms(kind, x, *, dhat, kappa, rest=None, direction=None, precision="float64", device="cpu"):
    """One pair evaluated by the contact kernels (for tests and tools): ``kind`` "pt" (x: point,
    then the triangle's three vertices) or "ee" (edge a, then edge b), ``x`` (4, 3). Returns a dict:
    distance, energy (kappa m b), gradient (12,), hessian (12, 12, exact) and hessian_psd (its
    projection) and, with ``direction`` (4, 3), step (the additive-CCD step bound along it)."""
    f64 = precision == "float64"
    S, V, M = (wp.float64, wp.vec3d, wp.mat33d) if f64 else (wp.float32, wp.vec3, wp.mat33)
    npt = np.float64 if f64 else np.float32
    k = {"pt": SK.PT, "ee": SK.EE}[kind]
    x = np.asarray(x, dtype=np.float64).reshape(4, 3)
    xa = to_device(x.astype(npt), V, device)
    ra = to_device(np.asarray(x if rest is None else rest, dtype=npt).reshape(4, 3), V, device)
    da = to_device(np.zeros((4, 3), npt) if direction is None else np.asarray(direction, dtype=npt).reshape(4, 3), V, device)
    pairs = to_device(np.array([[0, 1, 2, 3]], dtype=np.int32), wp.vec4i, device)
    kinds = to_device(np.array([k], dtype=np.int32), wp.int32, device)
    count = to_device(np.array([1], dtype=np.int32), wp.int32, device)
    blocks = to_device(np.arange(16, dtype=np.int32), wp.int32, device)
    dist = wp.zeros(1, dtype=S, device=device)
    fw = wp.zeros(1, dtype=wp.vec4d if f64 else wp.vec4, device=device)
    fn = wp.zeros(1, dtype=V, device=device)
    flam = wp.zeros(1, dtype=S, device=device)
    hidx = wp.zeros(1, dtype=wp.int32, device=device)
    out = {}

    def go(mode, g=None, values=None):
        acc = wp.zeros(4, dtype=wp.float64, device=device)
        acc.fill_(1.0) if mode == SK.MODE_MAX_STEP else None
        g = wp.zeros(4, dtype=V, device=device) if g is None else g
        values = wp.zeros(16, dtype=M, device=device) if values is None else values
        launch(SK.pair_kernel, 1, [xa, ra, pairs, kinds, count, S(dhat * dhat), S(kappa), mode, S(1.0), da, S(STEP_ETA), g,
                                   blocks, values, dist, fw, fn, flam, acc, 0, S(JACOBI_TOL[np.dtype(npt)]), g, values,
                                   hidx, hidx, hidx, 0], device)
        return read(acc), read(g), read(values)

    go(SK.MODE_DISTANCE)
    out["distance"] = read_scalar(dist)
    out["energy"] = float(go(SK.MODE_ENERGY)[0][0])
    out["gradient"] = go(SK.MODE_GRADIENT)[1].astype(np.float64).reshape(12)
    for key, mode in (("hessian", SK.MODE_HESSIAN_UNPROJECTED), ("hessian_psd", SK.MODE_HESSIAN)):
        blk = go(mode)[2].astype(np.float64).reshape(4, 4, 3, 3)
        out[key] = blk.transpose(0, 2, 1, 3).reshape(12, 12)
    if direction is not None:
        out["step"] = float(go(SK.MODE_MAX_STEP)[0][3])
    return out


class SurfaceContact:
    """Surface contact of one simulator (``sim``: ``model``, ``ops``, ``system``, ``device``, ``x``).

    Args (``Simulator.set_contact``): ``bodies`` (contact between different groups; default:
    True when the model has two or more), ``self`` (contact within a group, default False),
    ``friction`` (mu), ``dhat`` (m, default 0.1 x the mean surface edge), ``stiffness`` (kappa of
    the squared-distance barrier, N/m^3; default: the barrier's force at dhat / 2 is the collider
    default's there, :meth:`default_stiffness`; ``"auto"``: adaptive, :mod:`warpfem.contact.stiffness`), ``friction_velocity`` (m/s, default 1e-3 body
    diagonals per second, 1e-2 in float32). ``body``: optional (n,) body id per vertex (default from
    ``model.body_offsets`` when the model has two or more bodies)."""

    def __init__(self, sim, /, *, bodies=None, friction=0.0, dhat=None, stiffness=None, friction_velocity=None,
                 body=None, **flags):
        unknown = set(flags) - {"self", "self_contact"}
        if unknown:
            raise TypeError(f"set_contact: unknown key(s) {sorted(unknown)}; known: {', '.join(CONTACT_KEYS)}")
        self_on = bool(flags.get("self", flags.get("self_contact", False)))
        self.sim = sim
        self.ops = ops = sim.ops
        self.system = sim.system
        model = sim.model
        if body is None:
            offsets = getattr(model, "body_offsets", None)
            if offsets is not None and len(offsets) > 2:
                body = np.repeat(np.arange(len(offsets) - 1), np.diff(np.asarray(offsets)))
        elements = []  # one connectivity table per quadrature set (a body each in a multi-body model)
        for qd in getattr(model, "quadratures", None) or [model.quadrature]:
            try:
                elements.append(np.asarray(qd.elements).reshape(-1, int(qd.nodes_per_element)))
            except (AttributeError, TypeError, ValueError):  # components through the surface instead
                pass
        surf = contact_surface(model.mesh, body, elements=elements)
        self.surface = surf
        self.bodies = (surf.num_groups >= 2) if bodies is None else bool(bodies)
        self.self_contact = self_on
        X = np.asarray(model.rest_positions, dtype=np.float64)
        mean_edge = float(np.linalg.norm(X[surf.edges[:, 0]] - X[surf.edges[:, 1]], axis=1).mean())
        self.mean_edge = mean_edge
        self.diagonal = float(np.linalg.norm(np.ptp(X, axis=0)))
        self.nv, self.nt, self.ne = len(surf.vertices), len(surf.triangles), len(surf.edges)
        for key, v in (("dhat", dhat), ("friction_velocity", friction_velocity)):
            if v is not None and not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"set_contact: {key} must be > 0, got {v!r}")
        adaptive, kappa = parse_stiffness(stiffness, "set_contact: stiffness")
        if not (np.isfinite(friction) and friction >= 0.0):
            raise ValueError(f"set_contact: friction must be >= 0, got {friction!r}")
        self.friction = float(friction)
        self.dhat = default_dhat(mean_edge) if dhat is None else float(dhat)
        #: the adaptive kappa (stiffness "auto"; warpfem.contact.stiffness), else None
        self.stiffness = None
        self._kappa = self.default_stiffness(self.dhat) if kappa is None and not adaptive else kappa
        if adaptive:
            mean_mass = float(model.total_mass) / max(int(model.num_vertices), 1)
            self.stiffness = AdaptiveStiffness(mean_mass, self.diagonal, self.dhat, squared=True)
            self.stiffness.initial(float(getattr(sim, "dt", 1.0) or 1.0))
        self.friction_velocity = (default_friction_velocity(self.diagonal, sim.precision) if friction_velocity is None
                                  else float(friction_velocity))
        dev = sim.device
        self.device = dev
        i32 = lambda a: to_device(np.ascontiguousarray(a, dtype=np.int32).ravel(), wp.int32, dev)  # noqa: E731
        self._verts, self._tris, self._edges = i32(surf.vertices), i32(surf.triangles), i32(surf.edges)
        self._group = i32(surf.group)
        box = lambda k: (wp.zeros(k, dtype=wp.vec3, device=dev), wp.zeros(k, dtype=wp.vec3, device=dev))  # noqa: E731
        self._vbox, self._tbox, self._ebox = box(self.nv), box(self.nt), box(self.ne)
        self._rest = ops.new_vector()
        upload(self._rest, X.astype(ops.np_dtype))
        self._zero_dir = ops.new_vector()
        self._boxes(sim.x, None, 1.0)
        self._tbvh = wp.Bvh(*self._tbox)
        self._ebvh = wp.Bvh(*self._ebox)
        self._count = wp.zeros(1, dtype=wp.int32, device=dev)
        self._gmap = self._hmap = None  # the gather maps (_update_maps) and the Hessian slots
        self._hslots = wp.zeros(16 * 256, dtype=ops.mat, device=dev)
        self._hact = wp.zeros(256, dtype=wp.int32, device=dev)  # per pair with blocks: whether its Hessian slots hold terms
        self._maps_valid = False
        self._f_gmap, self._f_hmap = _GatherMap(dev), _GatherMap(dev)  # friction's
        self._f_gslots = self._f_hslots = None
        self._f_maps_valid = False
        self._alloc(_capacity(4 * (self.nv + self.ne)))
        self.num_pairs = 0
        # self pairs closer than rest_gap at rest: no barrier, the step bound only (docs/contact.md)
        self.rest_gap = REST_GAP * self.dhat if self_on else 0.0
        self._rest32 = to_device(X.astype(np.float32), wp.vec3, dev)
        self._ccd_count = wp.zeros(1, dtype=wp.int32, device=dev)
        self._alloc_ccd(256)
        self.num_ccd_pairs = 0
        self.pairs_np = np.zeros((0, 4), dtype=np.int64)
        # friction lagged at the step start
        self.num_friction = 0
        self._f_pairs_np = np.zeros((0, 4), dtype=np.int64)
        self._f_cap = 0
        self._f_blocks = None
        self._x0 = ops.new_vector()
        self._eps = 0.0
        self.system.listeners.append(self._pattern_changed)
        self.queries = 0  # broad-phase queries made (for benchmarks)
        self.reused = 0  # broad phases answered by the last query's pairs
        self._valid = False  # whether the last query's boxes and pairs stand (see update_pairs)
        self._misses = wp.zeros(1, dtype=wp.int32, device=dev)
        if self_on:  # a body already through itself: its crossing pairs have a positive distance, so check
            from warpfem.mesh.intersect import first_self_crossing

            problem = first_self_crossing(sim.positions(), surf.triangles, getattr(model, "body_offsets", None),
                                          getattr(model, "body_names", None))
            if problem:
                self.detach()
                raise CollisionError(f"set_contact: {problem}; self contact needs a start that does not")
        d = self.distances()
        if len(d) and d.min() <= 0.0:
            self.detach()
            k = int(np.argmin(d))
            kind = "vertex-triangle" if read_int(self._kinds, k) == SK.PT else "edge-edge"
            raise CollisionError(f"set_contact: {int((d <= 0.0).sum())} surface pairs touch now{self._bodies_of(k)} "
                                 f"(first: {kind} pair, vertices {self.pairs_np[k].tolist()}, distance {d[k]:.3g} m): "
                                 "contact needs a gap between them")
        close = d < self.dhat
        if close.any():
            k = int(np.argmin(d))
            log.warning("set_contact: %d surface pairs start closer than dhat = %.3g m (closest %.3g m, vertices %s): "
                        "the barrier pushes them apart in the first steps%s", int(close.sum()), self.dhat, d[k],
                        self.pairs_np[k].tolist(), "; with self contact, give a dhat below the mesh's smallest gap "
                        "between primitives that are not neighbours" if self.self_contact else "")

    @property
    def kappa(self) -> float:
        """The barrier stiffness now (N/m^3): the given one, or the adaptive one's current value."""
        return self.stiffness.kappa if self.stiffness is not None else self._kappa

    @property
    def adaptive(self) -> bool:
        return self.stiffness is not None

    def _bodies_of(self, k):
        """' between bodies 'a' and 'b'' for candidate pair k of a multi-body model, else ''."""
        offsets, names = getattr(self.sim.model, "body_offsets", None), getattr(self.sim.model, "body_names", None)
        if offsets is None or names is None or len(offsets) < 3:
            return ""
        b = np.searchsorted(np.asarray(offsets), self.pairs_np[k, [0, 2 if read_int(self._kinds, k) == SK.EE else 1]],
                            side="right") - 1
        return f" between bodies {names[b[0]]!r} and {names[b[1]]!r}" if b[0] != b[1] else f" in body {names[b[0]]!r}"

    def default_stiffness(self, dhat):
        """The default kappa (N/m^3) of the squared-distance barrier: its force at d = dhat / 2
        (2 d kappa |b'(d^2)|) equals that of the collider barrier's default kappa (E x mean surface
        edge, at least the weight under 1 g per surface vertex per dhat; docs/contact.md) there."""
        E = float(getattr(self.sim.model.material, "youngs_modulus", 0.0) or 0.0)
        k_lin = _default_stiffness(E, self.mean_edge, float(self.sim.model.total_mass), self.nv, dhat)
        return k_lin * abs(_barrier_slope(0.5 * dhat, dhat)) / (dhat * abs(_barrier_slope(0.25 * dhat * dhat, dhat * dhat)))

    def _alloc(self, cap):
        dev, ops = self.device, self.ops
        self.capacity = cap
        self._pairs = wp.zeros(cap, dtype=wp.vec4i, device=dev)
        self._kinds = wp.zeros(cap, dtype=wp.int32, device=dev)
        self._blocks = wp.zeros(16 * cap, dtype=wp.int32, device=dev)
        self._dist = wp.zeros(cap, dtype=ops.scalar, device=dev)
        self._fw = wp.zeros(cap, dtype=wp.vec4d if ops.np_dtype == np.float64 else wp.vec4, device=dev)
        self._fn = wp.zeros(cap, dtype=ops.vec, device=dev)
        self._flam = wp.zeros(cap, dtype=ops.scalar, device=dev)
        self._gslots = wp.zeros(4 * cap, dtype=ops.vec, device=dev)  # 4 gradient slots per pair
        self._hidx = wp.zeros(cap, dtype=wp.int32, device=dev)  # per pair: its Hessian slots' index, -1: none
        self._gact = wp.zeros(cap, dtype=wp.int32, device=dev)  # per pair: whether its gradient slots hold terms

    def _alloc_ccd(self, cap):
        self.ccd_capacity = cap
        self._ccd_pairs = wp.zeros(cap, dtype=wp.vec4i, device=self.device)
        self._ccd_kinds = wp.zeros(cap, dtype=wp.int32, device=self.device)

    # -- broad phase ---------------------------------------------------------------------------------
    def _boxes(self, x, d, scale, margin=1.0):
        ops, dev = self.ops, self.device
        d = self._zero_dir if d is None else d
        pad = ops.scalar(0.5 * margin * self.dhat * 1.001)
        for prims, k, (lo, hi), m in ((self._verts, 1, self._vbox, self.nv), (self._tris, 3, self._tbox, self.nt),
                                      (self._edges, 2, self._ebox, self.ne)):
            launch(SK.boxes_kernel, m, [x, d, ops.scalar(scale), prims, k, pad, lo, hi], dev)

    def update_pairs(self, x, d=None, scale=1.0):
        """Candidate pairs for every point of the segment x -> x + scale d (d None: x alone): the
        pairs whose primitives' boxes over the segment, padded by QUERY_MARGIN dhat / 2, overlap.
        When every primitive's box padded by dhat / 2 fits in its box of the last query, that
        query's pairs still hold every pair within dhat and are kept (no refit, no query);
        otherwise the BVHs are refitted and queried, and the Hessian's pattern grows for new pairs.
        One read-back (the misses, or the pairs)."""
        if self._valid and self._fits(x, d, scale):
            self.reused += 1
            self._grow_near(x, d, scale)
            return self.num_pairs
        n = self._query(x, d, scale, QUERY_MARGIN)
        self.num_pairs = n
        if n:  # in a canonical order (the broad phase's depends on the BVH traversal and the threads)
            pairs, kinds = read(self._pairs, n), read(self._kinds, n)
            order = canonical_order(pairs, kinds)
            pairs, kinds = np.ascontiguousarray(pairs[order]), np.ascontiguousarray(kinds[order])
            upload(self._pairs[:n], pairs)
            upload(self._kinds[:n], kinds)
            self.pairs_np = pairs.astype(np.int64)
        else:
            self.pairs_np = np.zeros((0, 4), dtype=np.int64)
        self._update_blocks()
        self._grow_near(x, d, scale)
        self._valid = True
        return n

    def _grow_near(self, x, d, scale):
        """Grow the Hessian's pattern for the candidate pairs without blocks that can come within dhat
        on x -> x + scale d: distance at x minus the largest displacements of the pair's two
        primitives relative to the pair's mean displacement (the additive CCD's bound) below dhat.
        Every iterate whose Hessian is assembled lies on such a segment, so every pair within dhat
        there has its blocks; the others (most candidates) never enter the pattern."""
        n = self.num_pairs
        if n == 0 or self._has_blocks.all():
            return
        self.run(SK.MODE_DISTANCE, x)
        lb = read(self._dist, n).astype(np.float64)
        if d is not None:
            q = float(scale) * read(d).astype(np.float64)[self.pairs_np]  # (n, 4, 3)
            q -= q.mean(axis=1, keepdims=True)
            ln = np.linalg.norm(q, axis=2)
            pt = read(self._kinds, n) == SK.PT
            lb -= np.where(pt, ln[:, 0] + ln[:, 1:].max(axis=1),
                           np.maximum(ln[:, 0], ln[:, 1]) + np.maximum(ln[:, 2], ln[:, 3]))
        need = (lb < 1.01 * self.dhat) & ~self._has_blocks
        if need.any():
            self._ensure(self.pairs_np[need])  # the pattern listener updates the block positions

    def _fits(self, x, d, scale):
        ops, dev = self.ops, self.device
        d = self._zero_dir if d is None else d
        pad = ops.scalar(0.5 * self.dhat * 1.001)
        self._misses.zero_()
        for prims, k, (lo, hi), m in ((self._verts, 1, self._vbox, self.nv), (self._tris, 3, self._tbox, self.nt),
                                      (self._edges, 2, self._ebox, self.ne)):
            launch(SK.boxes_fit_kernel, m, [x, d, ops.scalar(scale), prims, k, pad, lo, hi, self._misses], dev)
        return read_int(self._misses) == 0

    def _quad_pairs(self, quads):
        a = np.repeat(quads, 4, axis=1).reshape(-1)
        b = np.tile(quads, (1, 4)).reshape(-1)
        p = np.stack([a, b], axis=1)
        return p[p[:, 0] != p[:, 1]]

    def _query(self, x, d, scale, margin):
        self._boxes(x, d, scale, margin)
        self._tbvh.refit()
        self._ebvh.refit()
        self.queries += 1
        while True:
            self._count.zero_()
            self._ccd_count.zero_()
            launch(SK.broad_phase_kernel, self.nv + self.ne, [
                self._tbvh.id, self._ebvh.id, self._vbox[0], self._vbox[1], self._ebox[0], self._ebox[1], self._verts,
                self._tris, self._edges, self._group, int(self.self_contact), int(self.bodies), self.nv, self._pairs,
                self._kinds, self._count, self.capacity, self._rest32, float(self.rest_gap), self._ccd_pairs,
                self._ccd_kinds, self._ccd_count, self.ccd_capacity], self.device)
            n = read_int(self._count)
            nc = read_int(self._ccd_count)
            if n <= self.capacity and nc <= self.ccd_capacity:
                self.num_ccd_pairs = nc
                return n
            if n > self.capacity:
                self._alloc(_capacity(2 * n))
            if nc > self.ccd_capacity:
                self._alloc_ccd(_capacity(2 * nc))

    def _ensure(self, quads):
        p = self._quad_pairs(quads)
        p = p[self.system.pattern.pair_index(p) < 0]  # only the missing blocks: growing sorts what it is given
        if len(p):
            n = self.system.pattern.num_rows
            k = np.unique(p[:, 0] * n + p[:, 1])
            self.system.ensure_blocks(np.stack([k // n, k % n], axis=1))

    def _block_positions(self, quads, cap, out=None, missing_ok=False):
        """Device int32 (16 cap,): the pattern positions of the 4 x 4 vertex blocks of each quad
        (``missing_ok``: all 16 are -1 for a quad that lacks one, and ``_has_blocks`` says which)."""
        full = np.zeros(16 * cap, dtype=np.int32)
        if missing_ok:
            self._blocks_np = full[:16 * len(quads)]
        if len(quads):
            a = np.repeat(quads, 4, axis=1).reshape(-1)
            b = np.tile(quads, (1, 4)).reshape(-1)
            pos = self.system.pattern.pair_index(np.stack([a, b], axis=1)).reshape(-1, 16)
            has = np.all(pos >= 0, axis=1)
            if missing_ok:
                self._has_blocks = has
                pos[~has] = -1
            elif not has.all():
                raise RuntimeError("surface contact: a pair's Hessian block is missing from the pattern")
            full[:pos.size] = pos.reshape(-1)
        if out is None or out.shape[0] != len(full):
            return to_device(full, wp.int32, self.device)
        upload(out, full)
        return out

    def _update_blocks(self):
        self._has_blocks = np.zeros(self.num_pairs, dtype=bool)
        self._blocks = self._block_positions(self.pairs_np, self.capacity, self._blocks, missing_ok=True)
        self._maps_valid = False  # rebuilt by the next gradient or Hessian (_update_maps)

    def _update_maps(self):
        """The gather maps of the candidate pairs (``GATHER``): gradient slot 4 p + i -> vertex
        pairs[p, i]; Hessian slots (16 per pair with blocks, in pair order) -> pattern block; and
        per pair the index of its Hessian slots (-1: none). Built when first needed after the pairs
        or the pattern changed."""
        self._maps_valid = True
        n, dev = self.num_pairs, self.device
        if self._gmap is None:
            self._gmap, self._hmap = _GatherMap(dev), _GatherMap(dev)
        self._gmap.set(self.pairs_np[:n].reshape(-1))
        with_blocks = np.flatnonzero(self._has_blocks)
        hidx = np.full(self.capacity, -1, dtype=np.int32)
        hidx[with_blocks] = np.arange(len(with_blocks), dtype=np.int32)
        upload(self._hidx, hidx)
        k = len(with_blocks)
        if self._hslots.shape[0] < 16 * k:
            self._hslots = wp.zeros(16 * _capacity(k), dtype=self.ops.mat, device=dev)
            self._hact = wp.zeros(_capacity(k), dtype=wp.int32, device=dev)
        pos = self._blocks_np.reshape(-1, 16)[with_blocks]
        self._hmap.set(pos.reshape(-1))

    def detach(self):
        """Stop following the Hessian's pattern (the simulator dropped this contact)."""
        if self._pattern_changed in self.system.listeners:
            self.system.listeners.remove(self._pattern_changed)

    def _pattern_changed(self, pattern):
        if self.num_pairs:
            self._update_blocks()
        if self.num_friction:
            self._f_blocks = self._block_positions(self._f_pairs_np, self._f_cap, self._f_blocks)
            self._update_friction_maps()

    def _update_friction_maps(self):
        self._f_maps_valid = False  # rebuilt by the next gradient or Hessian (_build_friction_maps)

    def _build_friction_maps(self):
        """The friction pairs' gather maps: gradient slot 4 p + i -> vertex, Hessian slot 16 p + k
        -> pattern block (every friction pair has its blocks)."""
        self._f_maps_valid = True
        nf = self.num_friction
        self._f_gmap.set(self._f_pairs_np[:nf].reshape(-1))
        self._f_hmap.set(read(self._f_blocks, 16 * nf))

    # -- pair kernel ---------------------------------------------------------------------------------
    def exact_hessian(self, x, values, scale=1.0):
        """Add the candidate pairs' barrier Hessian at x, without the per-pair PSD projection, times
        ``scale`` into ``values`` (the adjoint solve's exact Hessian, warpfem.solvers.adjoint)."""
        self.run(SK.MODE_HESSIAN_UNPROJECTED, x, scale=scale, values=values)

    def run(self, mode, x, *, scale=1.0, d=None, g=None, values=None, acc=None, slot=0, kappa=None, eta=None):
        """The pair kernel's job ``mode`` over the candidate pairs; gradients into g and Hessian
        blocks into values through the pairs' slots and the gather maps (``GATHER``); ``eta``: the
        step bound's fraction of each gap it keeps (default ``STEP_ETA``, read at the call)."""
        ops = self.ops
        eta = STEP_ETA if eta is None else eta
        n = self.num_pairs
        if n == 0:
            return
        kappa = self.kappa if kappa is None else kappa
        gather = GATHER and mode in (SK.MODE_GRADIENT, SK.MODE_HESSIAN, SK.MODE_HESSIAN_UNPROJECTED)
        g = ops.zero if g is None else g
        values = self.system.hessian_values if values is None else values
        if gather and not self._maps_valid:
            self._update_maps()
        launch(SK.pair_kernel, n, [
            x, self._rest, self._pairs, self._kinds, self._count, ops.scalar(self.dhat ** 2), ops.scalar(kappa),
            int(mode), ops.scalar(scale), self._zero_dir if d is None else d, ops.scalar(eta), g, self._blocks,
            values, self._dist, self._fw, self._fn, self._flam, self._acc_default() if acc is None else acc, int(slot),
            ops.scalar(JACOBI_TOL[np.dtype(ops.np_dtype)]), self._gslots, self._hslots, self._hidx, self._gact,
            self._hact, int(GATHER)], self.device)
        if gather and mode == SK.MODE_GRADIENT:
            self._gmap.gather(SK.gather_vec_kernel, self._gact, 2, self._gslots, g)
        elif gather:
            self._hmap.gather(SK.gather_mat_kernel, self._hact, 4, self._hslots, values)

    def run_ccd(self, x, *, scale, d, acc, slot=0, eta=None):
        """The step bound (additive CCD) of the CCD-only pairs (self pairs closer than rest_gap at rest)."""
        if self.num_ccd_pairs == 0:
            return
        eta = STEP_ETA if eta is None else eta
        ops = self.ops
        launch(SK.pair_kernel, self.num_ccd_pairs, [
            x, self._rest, self._ccd_pairs, self._ccd_kinds, self._ccd_count, ops.scalar(self.dhat ** 2),
            ops.scalar(self.kappa), int(SK.MODE_MAX_STEP), ops.scalar(scale), d, ops.scalar(eta), ops.zero,
            self._blocks, self.system.hessian_values, self._dist, self._fw, self._fn, self._flam, acc, int(slot),
            ops.scalar(JACOBI_TOL[np.dtype(ops.np_dtype)]), self._gslots, self._hslots, self._hidx, self._gact,
            self._hact, int(GATHER)], self.device)

    def _acc_default(self):
        if getattr(self, "_acc", None) is None:
            self._acc = wp.zeros(4, dtype=wp.float64, device=self.device)
        return self._acc

    def candidates(self, x):
        """(pairs (k, 4), kinds (k,): ``surface_kernels.PT`` / ``EE``) of the candidate pairs at the
        device positions x after a broad phase there (host int64 copies; the pairs that ``lag``
        would take friction from are those of them within dhat)."""
        self.update_pairs(x)
        k = self.num_pairs
        return self.pairs_np[:k].copy(), read(self._kinds, k).astype(np.int64)

    def distances(self, x=None) -> np.ndarray:
        """Distances (m) of the current candidate pairs at x (default: the current positions),
        after a broad phase at x."""
        x = self.sim.x if x is None else x
        self.update_pairs(x)
        self.run(SK.MODE_DISTANCE, x)
        return read(self._dist, self.num_pairs).astype(np.float64)

    def pair_min_distance(self, x) -> float:
        """Smallest distance (m) of the current candidate pairs at x, without a broad phase (inf
        without pairs): the adaptive stiffness's measure after each Newton iteration."""
        if self.num_pairs == 0:
            return float("inf")
        self.run(SK.MODE_DISTANCE, x)
        return float(read(self._dist, self.num_pairs).min())

    def min_distance(self, x=None) -> float:
        d = self.distances(x)
        return float(d.min()) if len(d) else float("inf")

    def barrier_energy(self, x=None) -> float:
        """Barrier energy (J) at x (default: current positions), friction excluded."""
        x = self.sim.x if x is None else x
        self.update_pairs(x)
        acc = self._acc_default()
        acc.zero_()
        self.run(SK.MODE_ENERGY, x, acc=acc)
        a = read(acc)
        return float("inf") if a[1] > 0 else float(a[0])

    # -- the start check (kinematic motion) ----------------------------------------------------------
    def fixed_vertices(self) -> np.ndarray:
        """Mesh vertex indices of the surface vertices with a fixed component now (kinematic
        handles and bodies: their targets move them at a step's start)."""
        fixed = getattr(self.sim.model, "fixed", None)
        if fixed is None:
            return np.zeros(0, dtype=np.int64)
        v = np.asarray(self.surface.vertices, dtype=np.int64)
        return v[np.asarray(fixed)[v].any(axis=1)]

    def motion_contact(self, x_from, x_to, moved):
        """None when the motion x_from -> x_to (a step's start with its kinematic targets applied;
        ``moved``: the mesh vertices that may move) keeps the contact pairs apart; else a phrase
        naming the first pair at distance <= 0 at x_to, or the first edge through a triangle
        there. One read-back (the broad phase over the motion aside) when no pair comes within
        ``CHECK_ETA`` of its gap along it (additive CCD); otherwise the distances at x_to (one
        more) and, when none is <= 0, an exact edge-triangle crossing test on the host."""
        ops = self.ops
        if getattr(self, "_motion", None) is None:
            self._motion = ops.new_vector()
        d = self._motion
        ops.lincomb(1.0, x_to, -1.0, x_from, d)
        self.update_pairs(x_from, d, 1.0)
        acc = self._acc_default()
        acc.fill_(1.0)  # acc[1]: 1 + the pairs at distance <= 0 at x_to; acc[3]: the bound along the motion
        self.run(SK.MODE_MAX_STEP, x_from, d=d, acc=acc, eta=CHECK_ETA)
        self.run_ccd(x_from, scale=1.0, d=d, acc=acc, eta=CHECK_ETA)
        self.run(SK.MODE_ENERGY, x_to, acc=acc)
        a = read(acc)
        if a[1] == 1.0 and a[3] >= 1.0:
            return None
        if a[1] > 1.0:
            self.run(SK.MODE_DISTANCE, x_to)
            dist = read(self._dist, self.num_pairs).astype(np.float64)
            k = int(np.argmin(dist))
            kind = "vertex-triangle" if read_int(self._kinds, k) == SK.PT else "edge-edge"
            return (f"surface pairs at distance <= 0: {int((dist <= 0.0).sum())} (first: {kind} pair, model vertices "
                    f"{self.pairs_np[k].tolist()}{self._bodies_of(k)}, distance {dist[k]:.3g} m)")
        return self._crossing(read(x_to).astype(np.float64), moved)

    def _where(self, v):
        """"body 'name'" of mesh vertex v in a multi-body model, else "surface group g"."""
        offsets, names = getattr(self.sim.model, "body_offsets", None), getattr(self.sim.model, "body_names", None)
        if offsets is not None and names is not None and len(offsets) >= 3:
            return f"body {names[int(np.searchsorted(np.asarray(offsets), v, side='right') - 1)]!r}"
        return f"surface group {int(self.surface.group[v])}"

    def _crossing(self, P, moved):
        """The first edge through a triangle at the positions P (host, (n, 3)) between primitives
        that contact (other groups with ``bodies``, the same group with ``self``), one of them on
        a triangle with a vertex in ``moved``: a phrase, or None."""
        from warpfem.mesh.intersect import surface_crossing

        T = np.asarray(self.surface.triangles, dtype=np.int64)
        mv = np.zeros(len(P), dtype=bool)
        mv[moved] = True
        tk = mv[T].any(axis=1)
        gT = np.asarray(self.surface.group)[T[:, 0]]
        for g in np.unique(gT[tk]):
            A = T[tk & (gT == g)]
            lo, hi = P[A].reshape(-1, 3).min(axis=0), P[A].reshape(-1, 3).max(axis=0)
            for on, B, shared in ((self.bodies, T[gT != g], False), (self.self_contact, T[gT == g], True)):
                if not on:
                    continue
                B = B[np.all(P[B].min(axis=1) <= hi, axis=1) & np.all(P[B].max(axis=1) >= lo, axis=1)]
                if not len(B):
                    continue
                for Fa, Fb in ((A, B), (B, A)):
                    c = surface_crossing(P, Fa, P, Fb, skip_shared=shared)
                    if c is not None:
                        p = ", ".join(f"{v:.6g}" for v in c.point)
                        return (f"edge {list(c.edge)} of {self._where(c.edge[0])} crosses triangle {list(c.triangle)} "
                                f"of {self._where(c.triangle[0])} at ({p}) m (model vertex indices)")
        return None

    # -- friction lagging ----------------------------------------------------------------------------
    def begin_step(self, x0, dt):
        """Broad phase at the step start x0 and, with friction, the lagged normal forces, closest
        points and normals of the pairs within dhat."""
        wp.copy(self._x0, x0)
        self._eps = self.friction_velocity * float(dt)
        if self.friction > 0.0:  # (without friction the step's first max_step finds the pairs)
            self.update_pairs(x0)
        self.lag(x0)

    def has_friction(self) -> bool:
        return self.friction > 0.0

    def set_friction(self, mu):
        """Change the Coulomb coefficient mu in place (the friction kernel reads it at every launch;
        the next step's :meth:`begin_step` lags the pairs with it): for runs that differentiate or
        fit it (``warpfem.diff``)."""
        mu = float(mu)
        if not (np.isfinite(mu) and mu >= 0.0):
            raise ValueError(f"set_contact: friction must be >= 0, got {mu!r}")
        self.friction = mu

    def normal_forces(self) -> np.ndarray:
        """The lagged normal forces (N) of the friction pairs."""
        if not self.num_friction:
            return np.zeros(0)
        return read(self._f_lam, self.num_friction).astype(np.float64)

    def lag(self, x):
        """Friction's normal forces, closest points and normals from the positions x (pairs
        within dhat among the current candidates)."""
        self.lag_candidate(x)
        self.commit_lag()

    def lag_candidate(self, x) -> np.ndarray:
        """The lag of :meth:`lag` taken at x into the pairs' work arrays, not yet used
        (:meth:`commit_lag`); returns the normal forces of the pairs it would lag."""
        self._cand = None
        if self.friction <= 0.0 or self.num_pairs == 0:
            return np.zeros(0)
        self._flam.zero_()
        self.run(SK.MODE_LAG, x)
        lam = read(self._flam, self.num_pairs)
        keep = np.nonzero(lam > 0.0)[0]
        self._cand = keep
        return lam[keep].astype(np.float64)

    def lag_change(self, before, after):
        """(change, scale) from the lag's normal forces ``before`` to those of the candidate
        ``after`` (:meth:`lag_candidate`), the pairs matched by their vertices: a pair in one of
        them only counts with its force against 0 (a pair that enters or leaves dhat with a small
        force is a small change). Inf when a pair's vertices are not unique (no matching)."""
        keep = getattr(self, "_cand", None)
        old_q = self._f_pairs_np[:self.num_friction]
        new_q = self.pairs_np[keep] if keep is not None else np.zeros((0, 4), dtype=np.int64)
        before, after = np.asarray(before, dtype=np.float64), np.asarray(after, dtype=np.float64)
        scale = max(float(np.abs(before).max(initial=0.0)), float(np.abs(after).max(initial=0.0)))
        if len(old_q) != len(before) or len(new_q) != len(after):
            return float("inf"), scale
        rows, inv = np.unique(np.concatenate([old_q, new_q]).reshape(-1, 4), axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        io, ino = inv[:len(old_q)], inv[len(old_q):]
        if len(np.unique(io)) != len(io) or len(np.unique(ino)) != len(ino):
            return float("inf"), scale
        a = np.zeros(len(rows))
        b = np.zeros(len(rows))
        a[io], b[ino] = before, after
        return (float(np.abs(a - b).max()) if len(rows) else 0.0), scale

    def commit_lag(self):
        """The candidate of :meth:`lag_candidate` becomes the lag (compacted: host, once)."""
        keep, self._cand = getattr(self, "_cand", None), None
        self.num_friction = 0
        if keep is None or not len(keep):
            return
        self.num_friction = len(keep)
        # the lagged pairs, compacted (host: once per step)
        quads = self.pairs_np[keep]
        self._f_pairs_np = quads
        cap = _capacity(len(keep))
        dev = self.device
        if cap != self._f_cap:
            self._f_cap = cap
            self._f_pairs = wp.zeros(cap, dtype=wp.vec4i, device=dev)
            self._f_w = wp.zeros(cap, dtype=self._fw.dtype, device=dev)
            self._f_n = wp.zeros(cap, dtype=self._fn.dtype, device=dev)
            self._f_lam = wp.zeros(cap, dtype=self._flam.dtype, device=dev)
            self._f_blocks = None
            self._alloc_friction_slots(cap)
        for src, dst in ((self._pairs, self._f_pairs), (self._fw, self._f_w), (self._fn, self._f_n),
                         (self._flam, self._f_lam)):
            a = read(src)
            b = np.zeros((cap,) + a.shape[1:], dtype=a.dtype)
            b[:len(keep)] = a[keep]
            upload(dst, b)
        self._f_blocks = self._block_positions(quads, cap, self._f_blocks)
        self._update_friction_maps()

    def _alloc_friction_slots(self, cap):
        self._f_gslots = wp.zeros(4 * cap, dtype=self.ops.vec, device=self.device)
        self._f_hslots = wp.zeros(16 * cap, dtype=self.ops.mat, device=self.device)
        self._f_act = wp.zeros(cap, dtype=wp.int32, device=self.device)

    # -- the step-to-step state (Simulator.state_dict) --------------------------------------------------
    def state_dict(self) -> dict:
        """What a later step reads besides the state: the broad phase's last query (its primitives'
        boxes, candidate pairs and continuous-collision pairs, kept while the boxes still hold:
        :meth:`update_pairs`), friction's lagged pairs, and the adaptive stiffness."""
        n, nc, nf = self.num_pairs, self.num_ccd_pairs, self.num_friction
        d = {"valid": bool(self._valid), "capacity": int(self.capacity), "ccd_capacity": int(self.ccd_capacity),
             "pairs": self._pairs.numpy()[:n].copy(), "kinds": self._kinds.numpy()[:n].copy(),
             "ccd_pairs": self._ccd_pairs.numpy()[:nc].copy(), "ccd_kinds": self._ccd_kinds.numpy()[:nc].copy(),
             "friction_pairs": self._f_pairs.numpy()[:nf].copy() if nf else np.zeros((0, 4), dtype=np.int32),
             "queries": int(self.queries), "reused": int(self.reused), "step_start": self._x0.numpy().copy(),
             "friction_eps": float(self._eps)}
        for name, (lo, hi) in (("vertex", self._vbox), ("triangle", self._tbox), ("edge", self._ebox)):
            d[f"boxes/{name}_lo"], d[f"boxes/{name}_hi"] = lo.numpy().copy(), hi.numpy().copy()
        for key, buf in (("lag_offset", "_f_w"), ("lag_normal", "_f_n"), ("lag_normal_force", "_f_lam")):
            d[f"friction_{key}"] = getattr(self, buf).numpy()[:nf].copy() if nf else np.zeros((0,) + {
                "_f_w": (4,), "_f_n": (3,), "_f_lam": ()}[buf], dtype=self._flam.numpy().dtype)
        if self.stiffness is not None:
            d.update({f"stiffness/{k}": v for k, v in self.stiffness.state_dict().items()})
        return d

    def load_state_dict(self, view):
        # everything checked first
        boxes = {}
        for name, (lo, hi) in (("vertex", self._vbox), ("triangle", self._tbox), ("edge", self._ebox)):
            for side, buf in (("lo", lo), ("hi", hi)):
                boxes[(name, side)] = (buf, view.array(f"boxes/{name}_{side}", (buf.shape[0], 3), np.float32))
        cap, ccap = view.integer("capacity"), view.integer("ccd_capacity")
        pairs = view.array("pairs", (None, 4), np.int32)
        kinds = view.array("kinds", (len(pairs),), np.int32)
        ccd = view.array("ccd_pairs", (None, 4), np.int32)
        ccd_kinds = view.array("ccd_kinds", (len(ccd),), np.int32)
        fpairs = view.array("friction_pairs", (None, 4), np.int32)
        nf = len(fpairs)
        dt = self._flam.numpy().dtype
        fw = view.array("friction_lag_offset", (nf, 4), dt)
        fn = view.array("friction_lag_normal", (nf, 3), dt)
        flam = view.array("friction_lag_normal_force", (nf,), dt)
        x0 = view.array("step_start", (self._x0.shape[0], 3), self._x0.numpy().dtype)
        if len(pairs) > cap or len(ccd) > ccap or cap < 1 or ccap < 1:
            raise view.error("capacity", "smaller than the pairs saved with it")
        nv = self.system.pattern.num_rows
        for key, p in (("pairs", pairs), ("ccd_pairs", ccd), ("friction_pairs", fpairs)):
            if p.size and (p.min() < -1 or p.max() >= nv):
                raise view.error(key, f"vertex indices outside [0, {nv})")
        stiff = None
        if self.stiffness is not None:
            from warpfem.contact.stiffness import AdaptiveStiffness

            stiff = AdaptiveStiffness.read_state(view.view("stiffness"))
        valid, queries, reused, eps = view.flag("valid"), view.integer("queries"), view.integer("reused"), view.number(
            "friction_eps")
        # then written
        for buf, a in boxes.values():
            buf.assign(a)
        if cap != self.capacity:
            self._alloc(cap)
        if ccap != self.ccd_capacity:
            self._alloc_ccd(ccap)
        for buf, a in ((self._pairs, pairs), (self._kinds, kinds), (self._ccd_pairs, ccd), (self._ccd_kinds, ccd_kinds)):
            full = np.zeros((buf.shape[0],) + a.shape[1:], dtype=a.dtype)
            full[:len(a)] = a
            buf.assign(full)
        self.num_pairs, self.num_ccd_pairs = len(pairs), len(ccd)
        upload(self._count, np.array([len(pairs)], dtype=np.int32))
        upload(self._ccd_count, np.array([len(ccd)], dtype=np.int32))
        self.pairs_np = pairs.astype(np.int64)
        self._update_blocks()
        self._valid, self.queries, self.reused, self._eps = valid, queries, reused, eps
        self._x0.assign(x0)
        self.num_friction = nf
        if nf:
            fcap = _capacity(nf)
            if fcap != self._f_cap:
                self._f_cap = fcap
                self._f_pairs = wp.zeros(fcap, dtype=wp.vec4i, device=self.device)
                self._f_w = wp.zeros(fcap, dtype=self._fw.dtype, device=self.device)
                self._f_n = wp.zeros(fcap, dtype=self._fn.dtype, device=self.device)
                self._f_lam = wp.zeros(fcap, dtype=self._flam.dtype, device=self.device)
                self._f_blocks = None
                self._alloc_friction_slots(fcap)
            for buf, a in ((self._f_pairs, fpairs), (self._f_w, fw), (self._f_n, fn), (self._f_lam, flam)):
                full = np.zeros((fcap,) + a.shape[1:], dtype=a.dtype)
                full[:nf] = a
                buf.assign(full)
            self._f_pairs_np = fpairs.astype(np.int64)
            self._f_blocks = self._block_positions(self._f_pairs_np, fcap, self._f_blocks)
            self._update_friction_maps()
        if stiff is not None:
            self.stiffness.set_state(stiff)

    def run_friction(self, mode, dbase, y, sy, *, scale=1.0, g=None, values=None, acc=None, slot=0):
        """The friction kernel's job ``mode`` (0 energy, 1 gradient, 2 Hessian) over the lagged
        pairs; gradients and Hessian blocks gathered from the pairs' slots (``GATHER``)."""
        nf = self.num_friction
        if nf == 0:
            return
        ops = self.ops
        g = ops.zero if g is None else g
        values = self.system.hessian_values if values is None else values
        if GATHER and mode in (1, 2) and not self._f_maps_valid:
            self._build_friction_maps()
        launch(SK.friction_kernel, nf, [
            dbase, y, ops.scalar(sy), self._f_pairs, self._f_w, self._f_n, self._f_lam, nf,
            ops.scalar(self.friction), ops.scalar(self._eps), int(mode), ops.scalar(scale), g, self._f_blocks, values,
            self._acc_default() if acc is None else acc, int(slot), self._f_gslots, self._f_hslots, self._f_act,
            int(GATHER)], self.device)
        if GATHER and mode == 1:
            self._f_gmap.gather(SK.gather_vec_kernel, self._f_act, 2, self._f_gslots, g)
        elif GATHER and mode == 2:
            self._f_hmap.gather(SK.gather_mat_kernel, self._f_act, 4, self._f_hslots, values)

    @property
    def step_start(self):
        return self._x0


class SurfaceContactForm(LaggedFrictionForm):
    """Barrier (+ lagged friction) of a :class:`SurfaceContact` as a form of x = x_b + s y; its
    :meth:`max_step` refreshes the candidate pairs for the segment of the coming line search and
    bounds it by additive CCD."""

    name = "surface_contact"
    order = 20  # after the colliders' contact, before the load

    def begin_step(self, ctx):
        """Broad phase and friction lagged at the step's start x_n, then the step's x_b and s."""
        self.contact.begin_step(ctx.state.x, ctx.dt)
        super().begin_step(ctx)

    def static_error(self):
        return "solve_static does not handle surface contact (set_contact); use a damped time integration to reach rest"

    def check_start(self, x, ctx):
        """Raise :class:`InfeasibleStart` when the step's start x (free vertices where they are,
        kinematic ones at their targets) has a contact pair at distance <= 0 (outside the
        barrier's domain) or an edge through a triangle, brought there by the kinematic motion
        from the step start: a kinematic body or handle moved into a soft body within the step.
        Only when a surface vertex has a fixed component (else the start is the last step's end)."""
        c = self.contact
        moved = c.fixed_vertices()
        if ctx.static or not len(moved):
            return
        problem = c.motion_contact(ctx.state.x, x, moved)
        if problem:
            raise InfeasibleStart(f"surface contact: a kinematic body or handle moved into a soft body within one step: "
                                  f"{problem}; use smaller steps or a slower motion",
                                  reason="kinematic body moved into a soft body")

    def _friction(self, mode, y, x, **kw):
        c = self.contact
        if c.num_friction == 0:
            return
        if self._use_dbase and y is not None:
            c.run_friction(mode, self._dbase, y, self.s, **kw)
        else:  # x - x_n with x the unknown
            c.ops.lincomb(-1.0, c.step_start, 0.0, c.step_start, self._dbase)
            c.run_friction(mode, self._dbase, x, 1.0, **kw)

    def read(self, row):
        e = float(row[0])
        return e, e, not (row[1] > 0)

    def gradient_magnitude(self, row, scale):
        return float(np.sqrt(row[2]))

    def energy(self, y, x, acc):
        self.contact.run(SK.MODE_ENERGY, x, acc=acc, slot=self.acc_slot)
        self._friction(0, y, x, acc=acc, slot=self.acc_slot)

    def gradient(self, y, x, scale, g, acc):
        self.contact.run(SK.MODE_GRADIENT, x, scale=scale, g=g, acc=acc, slot=self.acc_slot)
        self._friction(1, y, x, scale=scale, g=g, acc=acc, slot=self.acc_slot)

    def hessian(self, y, x, scale, values):
        self.contact.run(SK.MODE_HESSIAN, x, scale=scale, values=values)
        self._friction(2, y, x, scale=scale, values=values)

    def max_step(self, x, d, s, acc):
        """Candidate pairs over x -> x + s d, then the additive-CCD bound into acc[slot + 3]."""
        c = self.contact
        c.update_pairs(x, d, s)
        c.run(SK.MODE_MAX_STEP, x, scale=s, d=d, acc=acc, slot=self.acc_slot)
        c.run_ccd(x, scale=s, d=d, acc=acc, slot=self.acc_slot)

    # -- adaptive stiffness (warpfem.contact.stiffness) ----------------------------------------------
    def adaptive_stiffness(self) -> bool:
        return self.contact.stiffness is not None

    def begin_stiffness(self, pot, y, g_rest) -> bool:
        """The adaptive kappa at the step's start y (``g_rest``: the gradient of the other forms
        there, masked, flat): balanced against the barrier's gradient when a pair is within dhat;
        friction is lagged again with it. Returns whether kappa changed."""
        c = self.contact
        x = pot.x_of(y)
        c.update_pairs(x)
        dmin = c.pair_min_distance(x)
        gb = None
        if dmin < c.dhat:
            scale = pot.scales(self)[0]
            gb = pot.masked_gradient(y, add=lambda x, g, acc: c.run(SK.MODE_GRADIENT, x, scale=scale, g=g, kappa=1.0))
        before = c.kappa
        c.stiffness.begin_step(pot.s, dmin, g_rest, gb)
        if c.kappa != before and c.has_friction():
            c.lag(c.step_start)
        return c.kappa != before

    def after_iteration(self, x, alpha=1.0) -> bool:
        """After an accepted Newton iteration at x (step length alpha): an adaptive kappa doubles
        when the smallest pair distance keeps shrinking below a fraction of dhat. Returns whether
        kappa changed."""
        c = self.contact
        if c.stiffness is None:
            return False
        return c.stiffness.update(c.pair_min_distance(x))

    def state_dict(self) -> dict:
        return self.contact.state_dict()

    def load_state_dict(self, state):
        self.contact.load_state_dict(state)

    def stiffness_state(self):
        s = self.contact.stiffness
        return None if s is None else s.state()

    def restore_stiffness(self, state):
        if self.contact.stiffness is not None and state is not None:
            self.contact.stiffness.restore(state)
