"""The contact term of the incremental potential: barrier + lagged friction against colliders.

:class:`ContactSet` holds a simulator's colliders on the device (their parameters, their poses at
the end of the current step, the friction data lagged from its start); :class:`ContactForm` is the
form of :mod:`warpfem.solvers.forms` that adds their energy, gradient and (SPD-projected, vertex-
diagonal: colliders are kinematic) Hessian blocks to the potential and bounds the line search's
step (continuous collision: no surface vertex crosses a collider along y + alpha d). Its life cycle
(the hooks of ``warpfem.solvers.forms.Form``, called by the simulator for every form): on while the
set holds a collider (``enabled``), the colliders' poses and friction lagged at each step start
(``begin_step``), a collider that moved into the body fails the step (``check_start``), friction
lagged again from a converged step's end (``update_lagging``), refused by the static solve
(``static_error``).
"""

from __future__ import annotations

import logging

import numpy as np
import warp as wp

from warpfem.contact import friction as FR
from warpfem.contact import kernels as CK
from warpfem.contact.colliders import (FRICTION_VELOCITY, Collider, contact_parameters,  # noqa: F401 (re-exported)
                                       default_friction_velocity, registered_colliders)
from warpfem.contact.colliders import default_stiffness as _default_stiffness
from warpfem.contact.stiffness import AdaptiveStiffness
from warpfem.kernels.generic import launch
from warpfem.solvers.forms import Form, InfeasibleStart, lagged_change
from warpfem.transfer import read, read_int, to_device, upload

log = logging.getLogger(__name__)

__all__ = ["ContactSet", "ContactForm", "CollisionError"]

# the line search may take a vertex at most this close (fraction of its current distance) to a collider
STEP_ETA = 0.2

def unique_name(name: str, taken) -> str:
    """``name``, or ``name`` numbered from 2 on (``floor2``, ``floor3``, ...) when ``taken`` has it: the
    name a collider gets among those already added."""
    k = 2
    out = name
    while out in taken:
        out, k = f"{name}{k}", k + 1
    return out


class CollisionError(ValueError):
    """A collider intersects the body (at the start, or a moving collider ran into it)."""


class ContactSet:
    """The colliders of one simulator and their device data.

    Uses the simulator's public interface only: ``model``, ``device``, ``num_vertices``, ``x`` and
    ``time`` (the current state), ``ops`` (its :class:`~warpfem.solvers.state.DeviceVectors`) and
    ``system`` (its :class:`~warpfem.solvers.sparse.HessianSystem`: the Hessian's pattern and values)."""

    def __init__(self, sim):
        self.sim = sim
        self.ops = ops = sim.ops
        self.system = sim.system
        self.colliders: list[Collider] = []
        mesh = sim.model.mesh
        faces = np.asarray(mesh.boundary_faces())
        self.surface = np.unique(faces)
        X = sim.model.rest_positions
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        self.mean_edge = float(np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1).mean())
        self.diagonal = float(np.linalg.norm(np.ptp(X, axis=0)))
        self.total_mass = float(sim.model.total_mass)
        dev = sim.device
        self._surf = to_device(self.surface.astype(np.int32), wp.int32, dev)
        self._diag = None
        self._pattern_changed(self.system.pattern)
        self.system.listeners.append(self._pattern_changed)
        self._cuts = wp.zeros(1, dtype=wp.int32, device=dev)  # contacts cut by the friction filter this step
        self._pins = wp.zeros(1, dtype=wp.int32, device=dev)  # contacts pinned by the last pin_direction
        self._tally = wp.zeros(1, dtype=wp.float64, device=dev)  # filter_direction's tally when none is given
        self._x0 = ops.new_vector()  # positions at the start of the step (friction's lag)
        self._neg_x0 = ops.new_vector()
        self._ready = False

    def _pattern_changed(self, pattern):
        """The positions of the diagonal blocks (the Hessian's pattern grew)."""
        self._diag = to_device(np.asarray(pattern.diag_index).astype(np.int32), wp.int32, self.sim.device)

    def __len__(self):
        return len(self.colliders)

    def exclude_vertices(self, vertices):
        """Leave ``vertices`` out of the collider contact (those of a kinematic body, whose motion is
        prescribed: the colliders neither push them nor bound their step); the body measures of the
        defaults (mean surface edge, diagonal) are then those of the remaining surface. Call it
        before adding colliders."""
        if self.colliders:
            raise RuntimeError("ContactSet.exclude_vertices: call it before adding colliders")
        mesh = self.sim.model.mesh
        faces = np.asarray(mesh.boundary_faces())
        gone = np.zeros(int(self.sim.num_vertices), dtype=bool)
        gone[np.asarray(vertices, dtype=np.int64)] = True
        faces = faces[~gone[faces].any(axis=1)]
        self.surface = np.unique(faces)
        X = self.sim.model.rest_positions
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        self.mean_edge = float(np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1).mean())
        self.diagonal = float(np.linalg.norm(np.ptp(X[self.surface], axis=0)))
        self._surf = to_device(self.surface.astype(np.int32), wp.int32, self.sim.device)

    # -- set-up ---------------------------------------------------------------------------------------
    def defaults(self, c: Collider):
        """(dhat, kappa, eps_v) of a collider with the body-based defaults filled in; kappa is None
        when it is adaptive (``stiffness="auto"``: :mod:`warpfem.contact.stiffness`); the one
        formula: :func:`warpfem.contact.colliders.contact_parameters`."""
        return contact_parameters(c.dhat, c.stiffness, c.friction_velocity,
                                  adaptive=bool(getattr(c, "adaptive_stiffness", False)), **self.body_measures())

    def body_measures(self) -> dict:
        """The body's measures the default contact parameters follow (keywords of
        :func:`~warpfem.contact.colliders.contact_parameters`)."""
        E = float(getattr(self.sim.model.material, "youngs_modulus", 0.0) or 0.0)
        return dict(mean_edge=self.mean_edge, diagonal=self.diagonal, total_mass=self.total_mass,
                    surface_vertices=len(self.surface), youngs_modulus=E, precision=self.sim.precision)

    def default_stiffness(self, dhat):
        """The default barrier stiffness kappa (N/m) at ``dhat``
        (:func:`warpfem.contact.colliders.default_stiffness`)."""
        m = self.body_measures()
        return _default_stiffness(m["youngs_modulus"], m["mean_edge"], m["total_mass"], m["surface_vertices"], dhat)

    def add(self, collider: Collider):
        if not isinstance(collider, Collider):
            raise TypeError(f"add_collider expects a warpfem collider (Plane, Sphere, Box, MeshCollider), got {collider!r}")
        if not any(isinstance(collider, c) and collider.kind == c.kind for c in registered_colliders()):
            raise TypeError(f"collider {collider.name!r}: its class {type(collider).__name__} (kind {collider.kind}) is "
                            "not a registered collider type (warpfem.contact.colliders.register_collider)")
        collider.name = unique_name(collider.name, {c.name for c in self.colliders})
        self.colliders.append(collider)
        self._ready = False
        self._upload()
        try:
            self.check(self.sim.x, self.sim.time, what="starts intersecting the body")
        except CollisionError:
            self.colliders.pop()
            self._ready = False
            self._upload() if self.colliders else None
            raise

    def _upload(self):
        ops, dev = self.ops, self.sim.device
        cs = self.colliders
        nc = len(cs)
        self.nc = nc
        tris, start, count = [], [], []
        off = 0
        for c in cs:
            t = c.triangles()
            start.append(off)
            count.append(c.num_primitives())  # the kernel's loop over the collider's primitives
            off += len(t)
            tris.append(t.reshape(-1, 3))
        tri = np.concatenate(tris) if off else np.zeros((3, 3))
        pars = [c.params() for c in cs]
        d = [self.defaults(c) for c in cs]
        self.dhat = np.array([x[0] for x in d])
        # an adaptive kappa per collider without a given stiffness (kept when the colliders are uploaded again)
        prev = {id(c): a for c, a in zip(getattr(self, "_stiffness_of", ()), getattr(self, "stiffness", ()))}
        mean_mass = self.total_mass / max(int(self.sim.num_vertices), 1)
        h = float(getattr(self.sim, "dt", 1.0) or 1.0)
        self.stiffness, kappa = [], []  # per collider: its AdaptiveStiffness (or None: fixed)
        for c, (dh, k, _) in zip(cs, d):
            a = None
            if k is None:
                a = prev.get(id(c))
                if a is None or a.dhat != dh:
                    a = AdaptiveStiffness(mean_mass, self.diagonal, dh, squared=False)
                    a.initial(h)
                k = a.kappa
            self.stiffness.append(a)
            kappa.append(k)
        self._stiffness_of = list(cs)
        self.kappa = np.array(kappa, dtype=np.float64)
        self.epsv = np.array([x[2] for x in d])
        S, V, M = ops.scalar, ops.vec, ops.mat
        npt = ops.np_dtype
        self._kinds = to_device(np.array([c.kind for c in cs], dtype=np.int32), wp.int32, dev)
        self._pa = to_device(np.array([p[0] for p in pars], dtype=npt).reshape(-1, 3), V, dev)
        self._pb = to_device(np.array([p[1] for p in pars], dtype=npt).reshape(-1, 3), V, dev)
        self._tri_start = to_device(np.array(start, dtype=np.int32), wp.int32, dev)
        self._tri_count = to_device(np.array(count, dtype=np.int32), wp.int32, dev)
        self._tris = to_device(tri.astype(npt), V, dev)
        self._kappa = to_device(self.kappa.astype(npt), S, dev)
        self._dhat = to_device(self.dhat.astype(npt), S, dev)
        self._mu = to_device(np.array([c.friction for c in cs], dtype=npt), S, dev)
        self._mu_zero = wp.zeros(nc, dtype=S, device=dev)
        self._epsf = wp.zeros(nc, dtype=S, device=dev)
        m = len(self.surface) * nc
        self._lam = wp.zeros(m, dtype=S, device=dev)
        self._lam_zero = wp.zeros(m, dtype=S, device=dev)
        self._dist = wp.zeros(m, dtype=S, device=dev)
        self._nrm = wp.zeros(m, dtype=V, device=dev)
        self._w = wp.zeros(m, dtype=V, device=dev)
        # a lag taken at an iterate before it is kept (``lag_candidate`` / ``commit_lag``)
        self._lam_c = wp.zeros(m, dtype=S, device=dev)
        self._nrm_c = wp.zeros(m, dtype=V, device=dev)
        self._w_c = wp.zeros(m, dtype=V, device=dev)
        self._acc = wp.zeros(4, dtype=wp.float64, device=dev)
        self._R0, self._R1 = (wp.zeros(nc, dtype=M, device=dev) for _ in range(2))
        self._t0, self._t1 = (wp.zeros(nc, dtype=V, device=dev) for _ in range(2))
        wp.copy(self._x0, self.sim.x)
        ops.lincomb(-1.0, self._x0, 0.0, self._x0, self._neg_x0)
        self.set_poses(self.sim.time, self.sim.time)
        self._ready = True

    def set_poses(self, t0, t1):
        """Poses of the colliders at the start (t0) and end (t1) of a step (written in place)."""
        npt = self.ops.np_dtype
        p0 = [c.pose(t0) for c in self.colliders]
        p1 = [c.pose(t1) for c in self.colliders]
        upload(self._R0, np.array([p[0] for p in p0], dtype=npt).reshape(-1, 3, 3))
        upload(self._t0, np.array([p[1] for p in p0], dtype=npt).reshape(-1, 3))
        upload(self._R1, np.array([p[0] for p in p1], dtype=npt).reshape(-1, 3, 3))
        upload(self._t1, np.array([p[1] for p in p1], dtype=npt).reshape(-1, 3))

    # -- kernel launch --------------------------------------------------------------------------------
    def run(self, mode, x, *, scale=1.0, g=None, values=None, acc=None, slot=0, lam=None, y=None, sy=1.0, dbase=None,
            friction=True, kappa=None, nrm=None, wdisp=None):
        """Launch the contact kernel in ``mode`` (``kernels.MODE_*``) at positions x; friction's step
        displacement is dbase + sy * y (default: x - x_n); ``friction=False`` evaluates the barrier
        alone; ``kappa``: a device array of per-collider stiffnesses to use instead."""
        ops = self.ops
        if y is None:
            y, sy, dbase = x, 1.0, self._neg_x0
        launch(CK.contact_kernel, len(self.surface), [
            x, self._surf, self.nc, self._kinds, self._R1, self._t1, self._R0, self._t0, self._pa, self._pb,
            self._tri_start, self._tri_count, self._tris, self._kappa if kappa is None else kappa, self._dhat, self._mu if friction else self._mu_zero,
            self._epsf, self._lam if lam is None else lam, self._nrm if nrm is None else nrm,
            self._w if wdisp is None else wdisp, dbase, y, ops.scalar(sy),
            ops.scalar(STEP_ETA), ops.scalar(scale), int(mode), ops.zero if g is None else g, self._diag,
            self.system.hessian_values if values is None else values, self._acc if acc is None else acc, int(slot)],
            self.sim.device)

    # -- adaptive stiffness (warpfem.contact.stiffness) ----------------------------------------------
    def adaptive(self) -> bool:
        """Whether a collider's kappa is adaptive (no ``stiffness`` given)."""
        return any(a is not None for a in self.stiffness)

    def sync_kappa(self):
        """The adaptive stiffnesses' current values onto the device."""
        self.kappa = np.array([k if a is None else a.kappa for k, a in zip(self.kappa, self.stiffness)], dtype=np.float64)
        upload(self._kappa, self.kappa.astype(self.ops.np_dtype))

    def unit_kappa(self, j):
        """A device array of per-collider stiffnesses: 1 for collider j, 0 for the others."""
        cache = getattr(self, "_unit", None)
        if cache is None or len(cache) != self.nc:
            cache = self._unit = [None] * self.nc
        if cache[j] is None:
            e = np.zeros(self.nc, dtype=self.ops.np_dtype)
            e[j] = 1.0
            cache[j] = to_device(e, self.ops.scalar, self.sim.device)
        return cache[j]

    def distances(self, x=None) -> np.ndarray:
        """(surface vertices, colliders) distances (m) at x (default: the current positions), with
        the colliders at their current pose."""
        self.run(CK.MODE_DISTANCE, self.sim.x if x is None else x, lam=self._dist)
        return read(self._dist).astype(np.float64).reshape(len(self.surface), self.nc)

    def check(self, x, t, *, what):
        """Raise :class:`CollisionError` naming the collider if a surface vertex of x is at distance <= 0
        from a collider at its pose at time t."""
        self.set_poses(t, t)
        D = self.distances(x)
        bad = np.argwhere(D <= 0.0)
        if len(bad):
            v, j = bad[0]
            c = self.colliders[j]
            raise CollisionError(f"collider {c.name!r} ({c.type_name}) {what}: {len(bad)} surface vertices inside it "
                                 f"(first: vertex {int(self.surface[v])}, distance {D[v, j]:.3g} m)")

    def begin_step(self, t0, t1, dt, x0=None):
        """Poses for the step [t0, t1] and the friction data lagged from the positions x0 at its
        start (default: the current positions)."""
        self.set_poses(t0, t1)
        upload(self._epsf, (self.epsv * dt).astype(self.ops.np_dtype))
        wp.copy(self._x0, self.sim.x if x0 is None else x0)
        self.ops.lincomb(-1.0, self._x0, 0.0, self._x0, self._neg_x0)
        self.run(CK.MODE_LAG, self._x0)
        self._cuts.zero_()

    def has_friction(self) -> bool:
        return any(c.friction > 0.0 for c in self.colliders)

    def filter_direction(self, dbase, y, sy, d, tally=None):
        """The stick/slip-aware step (:mod:`warpfem.contact.friction`): d's tangential part cut at
        the vertices whose frictional contact the step would carry past its point closest to u = 0, with
        the step displacement x - x_n = dbase + sy y. Counts the cut contacts in
        :attr:`filtered_contacts` (since the step start) and, with ``tally`` = (float64 device
        array, index), adds this call's cut contacts to that entry (no read-back)."""
        acc, at = (self._tally, 0) if tally is None else tally
        launch(FR.collider_filter_kernel, len(self.surface), [
            self._surf, self.nc, self._lam, self._nrm, self._w, dbase, y, self.ops.scalar(sy), self._epsf, self._mu,
            d, self._cuts, acc, int(at)], self.sim.device)

    def pin_direction(self, dbase, y, sy, d_raw, d, values, rhs, weight, count=True):
        """Tangential springs for a second Newton solve (``NewtonOptions.friction_pin``): at the
        vertices whose contact the unfiltered step ``d_raw`` carries past its point closest to u = 0, k P
        added to their Newton blocks in ``values`` and k P d to ``rhs`` (d the filtered step), k =
        ``weight`` x the block's mean diagonal. Returns the number of such contacts (one read-back);
        with ``count`` False, None and no read-back (the caller knows from :meth:`filter_direction`'s
        tally: a vertex's contacts are pinned exactly when the filter cut one of them, the filter
        having run on ``d_raw``)."""
        cnt = self._pins
        cnt.zero_()
        launch(FR.collider_pin_kernel, len(self.surface), [
            self._surf, self.nc, self._lam, self._nrm, self._w, dbase, y, self.ops.scalar(sy), self._epsf, self._mu,
            d_raw, d, self._diag, values, rhs, self.ops.scalar(weight), cnt], self.sim.device)
        return read_int(cnt) if count else None

    @property
    def filtered_contacts(self) -> int:
        """Contacts whose tangential step the friction filter cut since the start of the step."""
        return read_int(self._cuts)

    def collider(self, name) -> Collider:
        """The collider named ``name``; a ``KeyError`` listing the names otherwise."""
        for c in self.colliders:
            if c.name == name:
                return c
        raise KeyError(f"no collider named {name!r}; the colliders are "
                       f"{', '.join(repr(c.name) for c in self.colliders) or 'none'}")

    def set_friction(self, name, mu):
        """Change the Coulomb coefficient of the collider named ``name`` in place (the collider's
        ``friction`` and the device array the contact kernel reads), without uploading the colliders
        again: for runs that differentiate or fit it (``warpfem.diff``)."""
        mu = float(mu)
        if not (np.isfinite(mu) and mu >= 0.0):
            raise ValueError(f"collider {name!r}: friction must be >= 0, got {mu!r}")
        self.collider(name).friction = mu
        upload(self._mu, np.array([c.friction for c in self.colliders], dtype=self.ops.np_dtype))

    def normal_forces(self) -> np.ndarray:
        """The lagged normal forces (N) per (surface vertex, collider)."""
        return read(self._lam).astype(np.float64)

    def lag_candidate(self, x) -> np.ndarray:
        """Friction's normal forces, normals and collider motion taken at the positions x into a
        candidate lag, not yet used (:meth:`commit_lag`); returns its normal forces."""
        self.run(CK.MODE_LAG, x, lam=self._lam_c, nrm=self._nrm_c, wdisp=self._w_c)
        return read(self._lam_c).astype(np.float64)

    def commit_lag(self):
        """The candidate lag of :meth:`lag_candidate` becomes the step's lag."""
        wp.copy(self._lam, self._lam_c)
        wp.copy(self._nrm, self._nrm_c)
        wp.copy(self._w, self._w_c)

    @property
    def step_start(self):
        """The positions the friction of the current step is lagged from (device array)."""
        return self._x0

    @property
    def negated_step_start(self):
        """-x_n (device array): friction's displacement base x - x_n when x is the unknown (static)."""
        return self._neg_x0

    def barrier_energy(self, x=None) -> float:
        """Barrier energy (J) of x (default: current positions) with the colliders at their current
        poses (friction excluded)."""
        self._acc.zero_()
        self.run(CK.MODE_ENERGY, self.sim.x if x is None else x, lam=self._lam_zero, friction=False)
        a = read(self._acc)
        return float("inf") if a[1] > 0 else float(a[0])

    def forces(self, x=None) -> np.ndarray:
        """Contact forces (N) on the vertices at x (barrier + lagged friction of the last step), (n, 3)."""
        f = self.ops.new_vector()
        self._acc.zero_()
        self.run(CK.MODE_GRADIENT, self.sim.x if x is None else x, scale=-1.0, g=f)
        return read(f).astype(np.float64)


    # -- the step-to-step state (Simulator.state_dict) --------------------------------------------------
    def state_dict(self) -> dict:
        """The colliders' names, each adaptive stiffness ("stiffness/J/...": kappa, its bounds, the last
        smallest distance), and friction's lagged data of the last step (normal forces, normals,
        closest-point offsets, the step start): what a later step reads besides the state."""
        d = {"colliders": np.array([c.name for c in self.colliders], dtype=str)}
        for j, a in enumerate(getattr(self, "stiffness", ())):
            if a is not None:
                d.update({f"stiffness/{j}/{k}": v for k, v in a.state_dict().items()})
        if self.colliders:
            d.update(lag_normal_force=self._lam.numpy().copy(), lag_normal=self._nrm.numpy().copy(),
                     lag_offset=self._w.numpy().copy(), step_start=self._x0.numpy().copy())
        return d

    def load_state_dict(self, view):
        names = view.array("colliders", (None,))
        mine = [c.name for c in self.colliders]
        if names.tolist() != mine:
            raise view.error("colliders", f"saved with colliders {names.tolist()}, this simulator has {mine}")
        stiff = {}
        for j, a in enumerate(getattr(self, "stiffness", ())):
            if a is not None:
                stiff[j] = AdaptiveStiffness.read_state(view.view(f"stiffness/{j}"))
        if not self.colliders:
            return
        arrays = {}
        for key, buf in (("lag_normal_force", self._lam), ("lag_normal", self._nrm), ("lag_offset", self._w),
                         ("step_start", self._x0)):
            ref = buf.numpy()
            arrays[key] = (buf, view.array(key, ref.shape, ref.dtype))
        for j, values in stiff.items():
            self.stiffness[j].set_state(values)
        self.sync_kappa()
        for buf, a in arrays.values():
            buf.assign(a)
        self.ops.lincomb(-1.0, self._x0, 0.0, self._x0, self._neg_x0)
        self.set_poses(self.sim.time, self.sim.time)


#: ``max_iters`` of a simulator with contact when none is given (``Form.newton_iterations``)
CONTACT_MAX_ITERS = 100


class LaggedFrictionForm(Form):
    """What the collider and the surface contact forms share: the step's x_b and s, and the
    displacement base x_b - x_n of lagged friction (x - x_n = (x_b - x_n) + s y); friction's
    lagging taken again from a step's end (``update_lagging``). ``contact`` has ``ops``,
    ``step_start`` (x_n), ``has_friction()``, ``normal_forces()``, ``lag_candidate(x)`` and
    ``commit_lag()`` (optionally ``lag_change(before, after)``: the change of a candidate lag)."""

    variable = "x"
    #: impacts take tens of Newton iterations (the default 30 stopped 9 of 48 frames of a scan dropped
    #: on a floor and a sphere short; with 100 every frame converged, at most 50: docs/contact.md)
    newton_iterations = CONTACT_MAX_ITERS

    def __init__(self, contact):
        self.contact = contact
        self.s = 1.0
        self._dbase = contact.ops.new_vector()
        self._use_dbase = False

    def begin(self, xb, s):
        """The step's x_b and s; ``xb=None``: x is the unknown itself (static)."""
        self.s = float(s)
        self._use_dbase = xb is not None
        if xb is not None:
            self.contact.ops.lincomb(1.0, xb, -1.0, self.contact.step_start, self._dbase)

    def begin_step(self, ctx):
        """The step's x_b and s (a subclass lags its contact's friction first)."""
        self.begin(ctx.xb, ctx.s)

    def uses_lagging(self) -> bool:
        c = self.contact
        return c.has_friction() and bool(len(getattr(c, "colliders", [0])))

    def update_lagging(self, x, keep_below=0.0):
        """Friction's normal forces and normals lagged again from the positions x (an iterate of
        the step; the step start and the colliders' motion stay): (largest change of a normal
        force, largest normal force before or after), or None when nothing changed (no friction, no
        contact). With ``keep_below`` > 0 the lag is kept as it is when that change is at most
        ``keep_below`` x the largest force (the step's lag is consistent to that tolerance): then
        (change, scale, False) is returned."""
        if not self.uses_lagging():
            return None
        c = self.contact
        before = c.normal_forces()
        after = c.lag_candidate(x)
        change, scale = (c.lag_change(before, after) if hasattr(c, "lag_change") else lagged_change(before, after))
        if 0.0 < change <= keep_below * scale:
            return change, scale, False
        c.commit_lag()
        return None if change == 0.0 else (change, scale)  # None: nothing changed (e.g. no contact)


class ContactForm(LaggedFrictionForm):
    """Barrier + lagged friction of a :class:`ContactSet`, as a form of the positions x = x_b + s y
    (static: x = y, s = 1) in the potential (``warpfem.solvers.forms``): the potential applies the
    chain factors (gradient s dE/dx, Hessian s^2 d2E/dx2, vertex-diagonal: colliders are kinematic)
    and reads the line-search bound from :meth:`max_step`."""

    name = "contact"
    order = 10  # after the elastic form, before the load

    def enabled(self) -> bool:
        return len(self.contact) > 0

    def begin_step(self, ctx):
        """The colliders' poses over [t0, t1] and friction lagged from the step's start x_n."""
        self.contact.begin_step(ctx.t0, ctx.t1, ctx.dt, x0=ctx.state.x)
        super().begin_step(ctx)

    def check_start(self, x, ctx):
        """Raise :class:`InfeasibleStart` naming the collider when a surface vertex of the start x
        is inside a collider at its end-of-step pose (it moved into the body within the step)."""
        try:
            self.contact.check(x, ctx.t1, what="moved into the body within one step (reduce dt or slow the collider)")
        except CollisionError as e:
            raise InfeasibleStart(str(e), reason="collider intersects the body") from e
        self.contact.set_poses(ctx.t0, ctx.t1)  # check() posed the colliders at t1 only

    def static_error(self):
        return ("solve_static does not handle colliders (contact is a dynamic term here); use a damped time "
                "integration to reach rest on a collider")

    def _disp(self, y):
        if not self._use_dbase or y is None:
            return {}
        return {"y": y, "sy": self.s, "dbase": self._dbase}

    def read(self, row):
        e = float(row[0])
        return e, e, not (row[1] > 0)  # a vertex on or inside a collider: outside the barrier's domain

    def gradient_magnitude(self, row, scale):
        return float(np.sqrt(row[2]))

    def energy(self, y, x, acc):
        self.contact.run(CK.MODE_ENERGY, x, acc=acc, slot=self.acc_slot, **self._disp(y))

    def gradient(self, y, x, scale, g, acc):
        self.contact.run(CK.MODE_GRADIENT, x, scale=scale, g=g, acc=acc, slot=self.acc_slot, **self._disp(y))

    def hessian(self, y, x, scale, values):
        self.contact.run(CK.MODE_HESSIAN, x, scale=scale, values=values, **self._disp(y))

    def filters_direction(self) -> bool:
        """Whether :meth:`filter_direction` can change a direction (only with friction)."""
        return self.contact.has_friction()

    def filter_direction(self, y, x, d, tally=None):
        """Cut the tangential step of each frictional contact that the Newton step ``d`` (in y)
        would carry past its point closest to u = 0 (:mod:`warpfem.contact.friction`), in place; with
        ``tally`` = (float64 device array, index), the cut contacts are added to that entry."""
        c = self.contact
        if not c.has_friction():
            return
        if self._use_dbase and y is not None:
            dbase, yv, sy = self._dbase, y, self.s
        else:  # static: x is the unknown
            dbase, yv, sy = c.negated_step_start, x, 1.0
        c.filter_direction(dbase, yv, sy, d, tally)

    def pin_direction(self, y, x, d_raw, d, values, rhs, weight, count=True):
        """The tangential springs of a second Newton solve at the contacts the unfiltered step
        ``d_raw`` carries across their sticking zones (:meth:`ContactSet.pin_direction`); returns
        how many (0 without friction; None with ``count`` False: no read-back)."""
        c = self.contact
        if not c.has_friction():
            return 0 if count else None
        if self._use_dbase and y is not None:
            dbase, yv, sy = self._dbase, y, self.s
        else:  # static: x is the unknown
            dbase, yv, sy = c.negated_step_start, x, 1.0
        return c.pin_direction(dbase, yv, sy, d_raw, d, values, rhs, weight, count)

    def max_step(self, x, d, s, acc):
        """Largest alpha <= 1 with no vertex crossing (or coming closer than STEP_ETA of its distance
        to) a collider along x + alpha s d (into acc[slot + 3], initialised by the caller)."""
        self.contact.run(CK.MODE_MAX_STEP, x, scale=s, g=d, acc=acc, slot=self.acc_slot)

    # -- adaptive stiffness (warpfem.contact.stiffness) ----------------------------------------------
    def adaptive_stiffness(self) -> bool:
        return self.contact.adaptive()

    def begin_stiffness(self, pot, y, g_rest) -> bool:
        """Each adaptive collider's kappa at the step's start y (``g_rest``: the gradient of the other
        forms there, masked, flat): balanced against its barrier's gradient when a vertex is within
        its dhat; friction is lagged again with it. Returns whether a kappa changed."""
        c = self.contact
        x = pot.x_of(y)
        D = c.distances(x)
        scale = pot.scales(self)[0]
        changed = False
        for j, a in enumerate(c.stiffness):
            if a is None:
                continue
            dmin = float(D[:, j].min()) if len(D) else float("inf")
            gb = None
            if dmin < c.dhat[j]:
                gb = pot.masked_gradient(y, add=lambda x, g, acc, j=j: c.run(
                    CK.MODE_GRADIENT, x, scale=scale, g=g, friction=False, kappa=c.unit_kappa(j)))
            before = a.kappa
            a.begin_step(pot.s, dmin, g_rest, gb)
            changed = changed or a.kappa != before
        if changed:
            c.sync_kappa()
            if c.has_friction():
                c.run(CK.MODE_LAG, c.step_start)
        return changed

    def after_iteration(self, x, alpha=1.0) -> bool:
        """After an accepted Newton iteration at x (step length alpha): an adaptive kappa whose
        collider's smallest distance keeps shrinking below a fraction of dhat doubles. Returns
        whether a kappa changed."""
        c = self.contact
        if not c.adaptive():
            return False
        D = c.distances(x)
        changed = False
        for j, a in enumerate(c.stiffness):
            if a is not None and len(D) and a.update(float(D[:, j].min())):
                changed = True
        if changed:
            c.sync_kappa()
        return changed

    def state_dict(self) -> dict:
        return self.contact.state_dict()

    def load_state_dict(self, state):
        self.contact.load_state_dict(state)

    def stiffness_state(self):
        return [None if a is None else a.state() for a in self.contact.stiffness]

    def restore_stiffness(self, state):
        for a, st in zip(self.contact.stiffness, state):
            if a is not None and st is not None:
                a.restore(st)
        self.contact.sync_kappa()
