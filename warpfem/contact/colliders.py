"""Kinematic colliders: a floor (plane), spheres, boxes and triangle meshes the body cannot enter.

A collider is rigid and prescribed (it is not simulated). Its motion follows the schedule of a
kinematic handle (docs/scenes.md, ``[[handle]]``): at time t, with f = min(t / ramp_time, 1),

    x(t) = c + R(f * rotation_angle about rotation_axis) (X - c) + f * translation,

X the collider's point at t = 0 and c the rotation centre (default: the collider's centre).

Each collider class owns what is particular to its type: its kernel ``kind`` (the int the contact
kernel dispatches on), its scene keys (``scene_keys``: required and optional ``[[collider]]`` keys,
read by ``warpfem.scenes.schema`` and the scene builder), its kernel parameters (``params``,
``triangles``), its Warp distance (``distance_func``, a ``wp.func``, with ``distance_args`` saying
what it is called with) and the host (numpy, complex-safe) counterpart of it (``local_distances``:
the adjoint's complex-step derivatives). :func:`register_collider` adds a class to the registry
the contact kernel's dispatch (``warpfem.contact.kernels.primitive_distance``) is generated from,
so a new collider type is a class, registered, without editing the kernels (docs/contact.md,
"Writing a collider type"). The body-based defaults of every contact barrier (colliders and surface contact)
are the functions :func:`default_dhat`, :func:`default_stiffness` and
:func:`default_friction_velocity`; :func:`contact_parameters` fills them in for a collider.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import warp as wp

from warpfem.contact.stiffness import parse_stiffness

__all__ = ["Collider", "Plane", "Sphere", "Box", "Capsule", "MeshCollider", "make_collider", "COLLIDER_TYPES", "collider_class",
           "collider_scene_keys", "register_collider", "unregister_collider", "registered_colliders",
           "add_registry_listener", "default_dhat", "default_stiffness", "default_friction_velocity", "contact_parameters",
           "FRICTION_VELOCITY"]

#: the built-in collider types (the ``[[collider]]`` types of scene files)
COLLIDER_TYPES = ("plane", "sphere", "box", "capsule", "mesh")

#: Default friction velocity eps_v (below it friction is smoothed into sticking), in body diagonals
#: per second, by precision. float32 gets 10x: with 1e-3 the sticking force's round-off
#: (about eps_32 |x - x_n| / (eps_v h)) is above the Newton loop's floor at impacts and 3 of 20
#: steps of a collider drop stopped at max_iters; with 1e-2 every step converges (30 Newton
#: iterations per impact step), a mu = 0.8 block on a 30 degree incline creeps 0.45 mm in 0.5 s
#: instead of 0.09 mm, and sliding keeps the Coulomb acceleration to 0.001 % (docs/contact.md).
FRICTION_VELOCITY = {"float64": 1e-3, "float32": 1e-2}


# -- the body-based defaults of a contact barrier (colliders, surface contact, scene descriptions) --------
def default_dhat(mean_edge):
    """The default contact distance dhat (m): a tenth of the body's mean surface edge."""
    return 0.1 * mean_edge


def default_stiffness(youngs_modulus, mean_edge, total_mass, surface_vertices, dhat):
    """The default barrier stiffness kappa (N/m): as stiff as the material over a surface edge
    (E x mean edge, so an impact is stopped within a fraction of dhat rather than at a
    float32-unresolvable gap), and at least the weight under 1 g spread over the surface
    vertices, per dhat."""
    return max(youngs_modulus * mean_edge, total_mass * 9.81 / (max(int(surface_vertices), 1) * dhat))


def default_friction_velocity(diagonal, precision):
    """eps_v (m/s) for a body of bounding-box ``diagonal`` (m) simulated in ``precision``."""
    return FRICTION_VELOCITY.get(str(precision), 1e-3) * float(diagonal)


def contact_parameters(dhat, stiffness, friction_velocity, *, adaptive=False, mean_edge, diagonal, total_mass,
                       surface_vertices, youngs_modulus, precision):
    """(dhat, kappa, eps_v) of a collider given its own values (None: the default) and the body's
    measures; kappa is None when it is adaptive (``stiffness="auto"``: warpfem.contact.stiffness)."""
    dhat = dhat if dhat is not None else default_dhat(mean_edge)
    kappa = stiffness if stiffness is not None else (
        None if adaptive else default_stiffness(youngs_modulus, mean_edge, total_mass, surface_vertices, dhat))
    epsv = friction_velocity if friction_velocity is not None else default_friction_velocity(diagonal, precision)
    return dhat, kappa, epsv


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def closest_on_triangles(p, A, B, C):
    """Closest points of p (m, 3) to triangles (T, 3) each: (m, T, 3), the host counterpart of
    :func:`closest_on_triangle` (Ericson's regions, chosen on real parts; complex-safe)."""
    p = p[:, None, :]
    ab, ac, ap = B - A, C - A, p - A
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - B
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - C
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    R = np.real
    one = np.ones_like(d1)

    def safe(x):
        return np.where(R(x) == 0.0, one, x)

    den = safe(va + vb + vc)
    q = A + ab * (vb / den)[..., None] + ac * (vc / den)[..., None]  # interior
    # the edge and vertex regions, in reverse order of Ericson's tests so the first test wins
    reg = [
        ((R(va) <= 0) & (R(d4 - d3) >= 0) & (R(d5 - d6) >= 0),
         B + (C - B) * ((d4 - d3) / safe((d4 - d3) + (d5 - d6)))[..., None]),
        ((R(vb) <= 0) & (R(d2) >= 0) & (R(d6) <= 0), A + ac * (d2 / safe(d2 - d6))[..., None]),
        ((R(d6) >= 0) & (R(d5) <= R(d6)), np.broadcast_to(C, q.shape)),
        ((R(vc) <= 0) & (R(d1) >= 0) & (R(d3) <= 0), A + ab * (d1 / safe(d1 - d3))[..., None]),
        ((R(d3) >= 0) & (R(d4) <= R(d3)), np.broadcast_to(B, q.shape)),
        ((R(d1) <= 0) & (R(d2) <= 0), np.broadcast_to(A, q.shape)),
    ]
    for mask, val in reg:
        q = np.where(mask[..., None], val, q)
    return q


def _rotation(axis, angle):
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def _vec3(v, what):
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{what} must be 3 finite numbers, got {v!r}")
    return a


# -- the Warp distances of the built-in types (``distance_func`` of their classes) ------------------------
# Signed distance of a point p in the collider's t = 0 frame and its gradient (unit normal), generic
# over float32 / float64: every literal is typed through ``zero = p[0] - p[0]``.
@wp.func
def plane_distance(p: Any, a: Any, b: Any):
    """Plane: point a, unit normal b."""
    return wp.dot(b, p - a), b


@wp.func
def sphere_distance(p: Any, a: Any, b: Any):
    """Sphere: centre a, radius b[0]; at the centre the normal is +y."""
    zero = p[0] - p[0]
    one = zero + type(zero)(1.0)
    r = p - a
    L = wp.length(r)
    if L > zero:
        return L - b[0], r / L
    return -b[0], type(p)(zero, one, zero)


@wp.func
def box_distance(p: Any, a: Any, b: Any):
    """Box: centre a, half extents b; inside, the (negative) largest face distance."""
    zero = p[0] - p[0]
    one = zero + type(zero)(1.0)
    r = p - a
    sg = type(p)(one, one, one)
    for k in range(3):
        if r[k] < zero:
            sg[k] = -one
    q = type(p)(wp.abs(r[0]) - b[0], wp.abs(r[1]) - b[1], wp.abs(r[2]) - b[2])
    qmax = wp.max(wp.max(q[0], q[1]), q[2])
    if qmax > zero:
        m = type(p)(wp.max(q[0], zero), wp.max(q[1], zero), wp.max(q[2], zero))
        L = wp.length(m)
        return L, wp.cw_mul(sg, m) / L
    n = type(p)(zero, zero, zero)
    if q[0] >= q[1] and q[0] >= q[2]:
        n[0] = sg[0]
    elif q[1] >= q[2]:
        n[1] = sg[1]
    else:
        n[2] = sg[2]
    return qmax, n


@wp.func
def capsule_distance(p: Any, a: Any, b: Any):
    """Capsule: centre a, b = (radius, half length of the segment, axis 0 / 1 / 2); on the
    segment the normal is one perpendicular to the axis."""
    zero = p[0] - p[0]
    one = zero + type(zero)(1.0)
    e = type(p)(zero, zero, one)
    if b[2] < type(zero)(0.5):
        e = type(p)(one, zero, zero)
    elif b[2] < type(zero)(1.5):
        e = type(p)(zero, one, zero)
    r = p - a
    t = wp.clamp(wp.dot(r, e), -b[1], b[1])
    q = r - t * e
    L = wp.length(q)
    if L > zero:
        return L - b[0], q / L
    return -b[0], type(p)(e[1], e[2], e[0])


@wp.func
def closest_on_triangle(p: Any, a: Any, b: Any, c: Any):
    """Closest point to p on triangle abc (Ericson, "Real-Time Collision Detection", 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    zero = d1 - d1
    if d1 <= zero and d2 <= zero:
        return a
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        return a + ab * (d1 / (d1 - d3))
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        return a + ac * (d2 / (d2 - d6))
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
    den = va + vb + vc
    return a + ab * (vb / den) + ac * (vc / den)


@wp.func
def triangle_distance(p: Any, a: Any, b: Any, c: Any):
    """Unsigned distance to triangle abc (a two-sided surface); the normal is 0 on the triangle."""
    zero = p[0] - p[0]
    q = closest_on_triangle(p, a, b, c)
    r = p - q
    d = wp.length(r)
    nl = type(p)(zero, zero, zero)
    if d > zero:
        nl = r / d
    return d, nl


def _outside_radius(q, radius):
    """(d (m, 1), n (m, 1, 3)) of points at offsets q (m, 3) from a centre or a segment: |q| - radius
    and q / |q| (complex-safe; at q = 0 the normal is 0)."""
    L = np.sqrt(_dot(q, q))
    L = np.where(np.real(L) > 0, L, 1.0)
    return (L - radius)[:, None], (q / L[:, None])[:, None, :]


def _unit_sphere():
    """(points (13 x 25, 3), triangles) of a latitude-longitude unit sphere about y, for output."""
    u, v = np.meshgrid(np.linspace(0, np.pi, 13), np.linspace(0, 2 * np.pi, 25), indexing="ij")
    pts = np.stack([np.sin(u) * np.cos(v), np.cos(u), np.sin(u) * np.sin(v)], -1).reshape(-1, 3)
    nu, nv = u.shape
    tri = []
    for i in range(nu - 1):
        for j in range(nv - 1):
            a, b, c, d = i * nv + j, i * nv + j + 1, (i + 1) * nv + j, (i + 1) * nv + j + 1
            tri += [[a, b, d], [a, d, c]]
    return pts, np.array(tri)


class Collider:
    """Base class. Args (keyword): ``friction`` (Coulomb mu >= 0), ``dhat`` (contact distance, m;
    None: a tenth of the body's mean surface edge length), ``stiffness`` (barrier kappa, N/m;
    None: Young's modulus x the mean surface edge, at least the weight under 1 g per surface vertex
    per dhat; ``"auto"``: adaptive, :mod:`warpfem.contact.stiffness`),
    ``friction_velocity`` (m/s, below which friction is smoothed into sticking; None: 1e-3 body
    diagonals per second, 1e-2 in float32), the motion ``translation``, ``rotation_axis``, ``rotation_angle``
    (degrees), ``rotation_center``, ``ramp_time`` (s; required when it moves), and ``name``."""

    #: the int the contact kernel dispatches on (unique among the registered types; >= 0)
    kind = -1
    type_name = ""
    #: the ``[[collider]]`` keys of this type: (required, optional), besides the common ones
    scene_keys = ((), ())
    #: the Warp distance of one primitive in the collider's t = 0 frame: a ``wp.func`` returning
    #: (signed distance, unit normal), generic over float32 / float64 (literals typed through
    #: ``zero = p[0] - p[0]``); called as ``distance_func(p, a, b)`` with (a, b) = ``params()``
    #: (``distance_args = "params"``, one primitive), or ``distance_func(p, v0, v1, v2)`` once per
    #: triangle of ``triangles()`` (``distance_args = "triangle"``)
    distance_func = None
    distance_args = "params"

    def __init__(self, *, friction=0.0, dhat=None, stiffness=None, friction_velocity=None, translation=None,
                 rotation_axis=None, rotation_angle=0.0, rotation_center=None, ramp_time=None, name=None):
        self.name = name or self.type_name
        self.friction = float(friction)
        if not (np.isfinite(self.friction) and self.friction >= 0.0):
            raise ValueError(f"collider {self.name!r}: friction must be >= 0, got {friction!r}")
        for key, v in (("dhat", dhat), ("friction_velocity", friction_velocity), ("ramp_time", ramp_time)):
            if v is not None and not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"collider {self.name!r}: {key} must be > 0, got {v!r}")
        self.dhat = None if dhat is None else float(dhat)
        #: the given barrier stiffness (N/m; None: the default, or adaptive with ``adaptive_stiffness``)
        self.adaptive_stiffness, self.stiffness = parse_stiffness(stiffness, f"collider {self.name!r}: stiffness")
        self.friction_velocity = None if friction_velocity is None else float(friction_velocity)
        self.translation = np.zeros(3) if translation is None else _vec3(translation, f"collider {self.name!r}: translation")
        self.rotation_axis = None if rotation_axis is None else _vec3(rotation_axis, f"collider {self.name!r}: rotation_axis")
        if self.rotation_axis is not None and np.linalg.norm(self.rotation_axis) == 0.0:
            raise ValueError(f"collider {self.name!r}: rotation_axis must be nonzero")
        self.rotation_angle = float(rotation_angle)
        self.rotation_center = None if rotation_center is None else _vec3(rotation_center, f"collider {self.name!r}: rotation_center")
        self.ramp_time = None if ramp_time is None else float(ramp_time)
        if self.moving and self.ramp_time is None:
            raise ValueError(f"collider {self.name!r} moves: give its ramp_time (s)")

    @property
    def moving(self) -> bool:
        return bool(np.any(self.translation != 0.0) or (self.rotation_axis is not None and self.rotation_angle != 0.0))

    def center(self) -> np.ndarray:
        raise NotImplementedError

    def posed(self, vertices, t):
        """``vertices`` (k, 3) in the collider's t = 0 frame, moved by its pose at time ``t`` (s)."""
        R, p = self.pose(t)
        return np.asarray(vertices, dtype=np.float64) @ R.T + p

    def pose(self, t: float):
        """(R, p): the collider maps its t = 0 point X to R X + p at time t."""
        if not self.moving:
            return np.eye(3), np.zeros(3)
        f = min(max(t / self.ramp_time, 0.0), 1.0)
        R = np.eye(3)
        c = self.center() if self.rotation_center is None else self.rotation_center
        if self.rotation_axis is not None and self.rotation_angle != 0.0:
            R = _rotation(self.rotation_axis, math.radians(self.rotation_angle) * f)
        return R, c - R @ c + f * self.translation

    def params(self):
        """(a, b) vec3 parameters of the primitive in the t = 0 frame (see contact kernels)."""
        return np.zeros(3), np.zeros(3)

    def triangles(self) -> np.ndarray:
        return np.zeros((0, 3, 3))

    def num_primitives(self) -> int:
        """How many primitives the kernel loops over: 1, or the triangles (``distance_args = "triangle"``)."""
        return len(self.triangles()) if self.distance_args == "triangle" else 1

    @classmethod
    def geometry_keys(cls):
        """The type's own ``[[collider]]`` keys, required then optional."""
        return tuple(cls.scene_keys[0]) + tuple(cls.scene_keys[1])

    def local_distances(self, p):
        """(d (m, P), n (m, P, 3)): signed distances of points p (m, 3) in the collider's t = 0 frame
        to its P primitives (1; a mesh: its triangles) and their unit gradients, in numpy and
        complex-safe (branches on real parts): the host counterpart of the contact kernel's
        distance (``distance_func``) for the adjoint's
        complex-step derivatives (``warpfem.solvers.adjoint_contact``). Inside a solid the
        distance is <= 0 (never a contact term), its gradient unspecified."""
        raise NotImplementedError

    def surface(self, extent: float):
        """(vertices (k, 3), triangles (m, 3)) of the collider at t = 0 for output; ``extent`` sizes
        an infinite plane."""
        raise NotImplementedError

    def __repr__(self):
        return f"{type(self).__name__}(name={self.name!r})"


class Plane(Collider):
    """The half-space n.(x - point) >= 0 (the body stays on the side n points to)."""

    kind, type_name = 0, "plane"
    scene_keys = ((), ("point", "normal"))
    distance_func = plane_distance

    def __init__(self, point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0), **kw):
        self.point = _vec3(point, "plane point")
        n = _vec3(normal, "plane normal")
        if np.linalg.norm(n) == 0.0:
            raise ValueError("plane normal must be nonzero")
        self.normal = n / np.linalg.norm(n)
        super().__init__(**kw)

    def center(self):
        return self.point

    def params(self):
        return self.point, self.normal

    def local_distances(self, p):
        n = np.broadcast_to(self.normal, p.shape)
        return _dot(p - self.point, self.normal)[:, None], n[:, None, :]

    def surface(self, extent):
        n = self.normal
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 0.0, 1.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        e = float(extent)
        v = np.array([self.point + e * (a * t1 + b * t2) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        return v, np.array([[0, 2, 1], [0, 3, 2]]) if np.dot(np.cross(v[1] - v[0], v[2] - v[0]), n) < 0 else np.array([[0, 1, 2], [0, 2, 3]])


class Sphere(Collider):
    """A solid ball of ``radius`` around ``center``."""

    kind, type_name = 1, "sphere"
    scene_keys = (("center", "radius"), ())
    distance_func = sphere_distance

    def __init__(self, center=(0.0, 0.0, 0.0), radius=1.0, **kw):
        self.center_ = _vec3(center, "sphere center")
        self.radius = float(radius)
        if not (np.isfinite(self.radius) and self.radius > 0.0):
            raise ValueError(f"sphere radius must be > 0, got {radius!r}")
        super().__init__(**kw)

    def center(self):
        return self.center_

    def params(self):
        return self.center_, np.array([self.radius, 0.0, 0.0])

    def local_distances(self, p):
        return _outside_radius(p - self.center(), self.radius)

    def surface(self, extent):
        pts, tri = _unit_sphere()
        return self.center_ + self.radius * pts, tri


class Box(Collider):
    """A solid axis-aligned box (at t = 0) from ``box_min`` to ``box_max``."""

    kind, type_name = 2, "box"
    scene_keys = (("box_min", "box_max"), ())
    distance_func = box_distance

    def __init__(self, box_min=(-1.0, -1.0, -1.0), box_max=(1.0, 1.0, 1.0), **kw):
        lo, hi = _vec3(box_min, "box_min"), _vec3(box_max, "box_max")
        if not np.all(hi > lo):
            raise ValueError(f"box_max must exceed box_min on every axis, got {box_min!r}, {box_max!r}")
        self.lo, self.hi = lo, hi
        super().__init__(**kw)

    def center(self):
        return 0.5 * (self.lo + self.hi)

    def params(self):
        return self.center(), 0.5 * (self.hi - self.lo)

    def local_distances(self, p):
        R = np.real
        ctr, half = self.params()
        r = p - ctr
        sg = np.where(R(r) < 0, -1.0, 1.0)
        q = sg * r - half
        m = np.where(R(q) > 0, q, 0.0)
        L = np.sqrt(_dot(m, m))
        outside = R(L) > 0
        Ls = np.where(outside, L, 1.0)
        d = np.where(outside, L, np.max(R(q), axis=1))  # inside: negative (never an active pair)
        return d[:, None], (sg * m / Ls[:, None])[:, None, :]

    def surface(self, extent):
        c = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
        v = self.lo + c * (self.hi - self.lo)
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        return v, np.array([t for a, b, c_, d in quads for t in ((a, b, c_), (a, c_, d))])


_AXES = {"x": 0, "y": 1, "z": 2}


class Capsule(Collider):
    """A solid capsule: the points within ``radius`` of the segment of half length ``half_length``
    through ``center`` along the axis ``axis`` ("x", "y" or "z"; turn it with the motion keys).
    newton's capsule shape (its local z axis) is one with ``axis = "z"``."""

    kind, type_name = 4, "capsule"
    scene_keys = (("center", "radius", "half_length"), ("axis",))
    distance_func = capsule_distance

    def __init__(self, center=(0.0, 0.0, 0.0), radius=1.0, half_length=1.0, axis="y", **kw):
        self.center_ = _vec3(center, "capsule center")
        self.radius, self.half_length = float(radius), float(half_length)
        if not (np.isfinite(self.radius) and self.radius > 0.0):
            raise ValueError(f"capsule radius must be > 0, got {radius!r}")
        if not (np.isfinite(self.half_length) and self.half_length >= 0.0):
            raise ValueError(f"capsule half_length must be >= 0, got {half_length!r}")
        if axis not in _AXES:
            raise ValueError(f"capsule axis must be 'x', 'y' or 'z', got {axis!r}")
        self.axis = axis
        super().__init__(**kw)

    def center(self):
        return self.center_

    def params(self):
        return self.center_, np.array([self.radius, self.half_length, float(_AXES[self.axis])])

    def local_distances(self, p):
        e = np.eye(3)[_AXES[self.axis]]
        r = p - self.center_
        s = r @ e
        h = self.half_length
        t = np.where(np.real(s) > h, h, np.where(np.real(s) < -h, -h, s))
        return _outside_radius(r - t[:, None] * e, self.radius)

    def surface(self, extent):
        pts, tri = _unit_sphere()
        pts = self.radius * pts
        pts[:, 1] += np.where(pts[:, 1] >= 0.0, self.half_length, -self.half_length)  # the two caps apart
        k = _AXES[self.axis]
        pts = np.roll(pts, k - 1, axis=1)  # the y axis onto the capsule's (a cyclic turn: triangles stay outward)
        return self.center_ + pts, tri


class MeshCollider(Collider):
    """A rigid triangle mesh (``path`` read with meshio, or ``vertices`` and ``triangles``),
    treated as a two-sided surface: the body is kept at a positive distance from every triangle
    (point-triangle distances, brute force over the triangles: meant for small meshes)."""

    kind, type_name = 3, "mesh"
    scene_keys = (("path",), ("scale", "offset"))
    distance_func, distance_args = triangle_distance, "triangle"

    def __init__(self, path=None, *, vertices=None, triangles=None, scale=1.0, offset=(0.0, 0.0, 0.0), **kw):
        if path is not None:
            import meshio

            m = meshio.read(str(path))
            tri = [c.data for c in m.cells if c.type == "triangle"]
            if not tri:
                raise ValueError(f"mesh collider {path}: no triangles in the file")
            vertices, triangles = m.points, np.concatenate(tri)
        if vertices is None or triangles is None:
            raise ValueError("a mesh collider needs a path or vertices and triangles")
        V = np.asarray(vertices, dtype=np.float64)[:, :3] * float(scale) + _vec3(offset, "mesh offset")
        T = np.asarray(triangles, dtype=np.int64)
        if T.ndim != 2 or T.shape[1] != 3 or T.min() < 0 or T.max() >= len(V):
            raise ValueError(f"mesh collider {path or ''}: triangles must be (m, 3) indices into the vertices")
        area = np.linalg.norm(np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), axis=1)
        if np.any(area <= 1e-14 * max(np.ptp(V, axis=0).max(), 1e-300) ** 2):
            raise ValueError(f"mesh collider {path or ''}: degenerate triangle {int(np.argmin(area))}")
        self.vertices, self.faces = V, T
        super().__init__(**kw)

    def center(self):
        return self.vertices.mean(axis=0)

    def triangles(self):
        return self.vertices[self.faces]

    def local_distances(self, p):
        tri = self.triangles()  # (T, 3, 3) in the t = 0 frame
        Q = closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
        r = p[:, None, :] - Q
        d = np.sqrt(_dot(r, r))
        ds = np.where(np.real(d) > 0, d, 1.0)
        return d, r / ds[..., None]

    def surface(self, extent):
        return self.vertices, self.faces


# -- the registry ------------------------------------------------------------------------------------------
#: type name -> class, in registration order (the kernel's dispatch tests kinds in this order)
_BY_TYPE: dict = {}
_LISTENERS: list = []


def registered_colliders() -> tuple:
    """The registered collider classes, in registration order."""
    return tuple(_BY_TYPE.values())


def add_registry_listener(fn):
    """Call ``fn()`` after every change of the registry (the contact kernels regenerate their
    dispatch through it)."""
    _LISTENERS.append(fn)


def _changed():
    for fn in _LISTENERS:
        fn()


def register_collider(cls):
    """Class decorator: register a collider type (a :class:`Collider` subclass with its ``kind``,
    ``type_name``, ``scene_keys``, ``distance_func``, ``distance_args`` and ``local_distances``),
    so the contact kernel's dispatch calls its ``distance_func`` for its kind. Kinds and type names
    must be unique. The kernel module is built again (once) at its next launch."""
    if not (isinstance(cls, type) and issubclass(cls, Collider)):
        raise TypeError(f"register_collider takes a Collider subclass, got {cls!r}")
    name, kind = cls.type_name, cls.kind
    if not (isinstance(name, str) and name.isidentifier()):
        raise ValueError(f"collider {cls.__name__}: type_name must be an identifier, got {name!r}")
    if not (isinstance(kind, int) and kind >= 0):
        raise ValueError(f"collider {name!r}: kind must be an int >= 0, got {kind!r}")
    if name in _BY_TYPE:
        raise ValueError(f"collider type {name!r} is already registered")
    other = next((c for c in _BY_TYPE.values() if c.kind == kind), None)
    if other is not None:
        raise ValueError(f"collider kind {kind} of {name!r} is already used by {other.type_name!r}")
    if not isinstance(cls.distance_func, wp.Function):
        raise ValueError(f"collider {name!r}: distance_func must be a wp.func, got {cls.distance_func!r}")
    if cls.distance_args not in ("params", "triangle"):
        raise ValueError(f"collider {name!r}: distance_args must be 'params' or 'triangle', got {cls.distance_args!r}")
    if cls.local_distances is Collider.local_distances:
        raise ValueError(f"collider {name!r}: define local_distances (the host counterpart of distance_func)")
    _BY_TYPE[name] = cls
    _changed()
    return cls


def unregister_collider(type_name: str):
    """Remove a registered collider type (a test's own type, when it is done with it)."""
    if type_name not in _BY_TYPE:
        raise ValueError(f"collider type {type_name!r} is not registered")
    del _BY_TYPE[type_name]
    _changed()


for _cls in (Plane, Sphere, Box, Capsule, MeshCollider):
    register_collider(_cls)


def collider_class(type: str):
    """The collider class of a type name ("plane", "sphere", "box", "mesh", or a registered one)."""
    if type not in _BY_TYPE:
        raise ValueError(f"collider type must be one of {tuple(_BY_TYPE)}, got {type!r}")
    return _BY_TYPE[type]


def collider_scene_keys() -> dict:
    """{type: (required keys, optional keys)} of the ``[[collider]]`` types, from their classes."""
    return {t: _BY_TYPE[t].scene_keys for t in COLLIDER_TYPES}


def make_collider(type: str, **kw) -> Collider:
    """A collider from a type name ("plane", "sphere", "box", "mesh", or a registered one) and its keywords."""
    return collider_class(type)(**kw)
