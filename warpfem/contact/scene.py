"""Scene support of colliders: ``[[collider]]`` tables -> colliders on the simulator, and their
geometry in the USD output (one mesh prim per collider, its points written every frame)."""

from __future__ import annotations

import numpy as np

from warpfem.contact.colliders import collider_class, make_collider
from warpfem.contact.contact import CollisionError, unique_name

_COMMON = ("name", "friction", "dhat", "stiffness", "friction_velocity", "translation", "rotation_axis",
           "rotation_angle", "rotation_center", "ramp_time")


def scene_collider_names(entries) -> list:
    """The names the colliders of ``[[collider]]`` ``entries`` (a scene spec's ``collider`` list)
    get on the simulator: their ``name``, default ``<type><position>`` (``plane1``, ``box2``, ...),
    a repeated name numbered from 2 on as ``ContactSet.add`` does (``floor``, ``floor2``)."""
    names = []
    for i, c in enumerate(entries):
        names.append(unique_name(c.get("name") or f"{c['type']}{i + 1}", names))
    return names


def add_scene_colliders(scene, sim, *, duration):
    """Add the scene's ``[[collider]]`` entries to ``sim`` (ramp_time default: ``duration``), named
    by :func:`scene_collider_names`."""
    if not hasattr(sim, "add_collider"):
        scene.fail("[[collider]] #1", f"{type(sim).__name__} does not handle colliders")
    names = scene_collider_names(scene.spec.collider)
    for i, c in enumerate(scene.spec.collider):
        kw = {k: c[k] for k in collider_class(c["type"]).geometry_keys() + _COMMON if c.get(k) is not None}
        if c["type"] == "sphere":
            kw["center"] = tuple(kw["center"])
        if kw.get("ramp_time") is None:
            kw["ramp_time"] = duration
        kw["name"] = names[i]
        try:
            col = make_collider(c["type"], **kw)
            sim.add_collider(col)
        except (CollisionError, ValueError) as e:
            scene.fail(f"[[collider]] #{i + 1}", str(e))


def set_scene_contact(scene, sim, table=None):
    """The scene's ``[contact]`` table on ``sim`` (``Simulator.set_contact`` and the friction
    lagging iterations); ``table``: the keys to use instead (a scene of several bodies without a
    table: its defaults)."""
    c = scene.spec.contact if table is None else table
    if not hasattr(sim, "set_contact"):
        scene.fail("[contact]", f"{type(sim).__name__} does not handle contact")
    try:
        sim.friction_iterations, sim.friction_tol = int(c["friction_iterations"]), float(c["friction_tol"])
        tol = float(c["friction_update_tol"])
        if not tol < 1.0:
            raise ValueError(f"friction_update_tol must be in [0, 1), got {tol!r}")
        sim.friction_update_tol = tol
        if c.get("friction_lag_below") is not None:
            sim.friction_lag_below = c["friction_lag_below"]  # (checked by the simulator)
        sim.set_contact(**{k: c[k] for k in ("bodies", "self", "friction", "dhat", "stiffness", "friction_velocity")})
    except (TypeError, ValueError) as e:
        scene.fail("[contact]", str(e))


def posed_points(collider, vertices, t):
    """``vertices`` (k, 3) of ``collider`` in its t = 0 frame, moved by its pose at time ``t`` (s)."""
    return collider.posed(vertices, t)


def collider_prims(sim, extent):
    """[(prim name, faces, points_at() -> (k, 3))] for the simulator's colliders (``extent``: half
    size of the drawn floor square); the points are each collider's :meth:`~Collider.surface` at its
    pose at the simulator's time."""
    contact = getattr(sim, "contact", None)
    if contact is None:
        return []
    out = []
    for c in contact.colliders:
        V, F = c.surface(extent)

        def points(c=c, V=V):
            return posed_points(c, V, sim.time)

        out.append((f"collider_{c.name}", np.asarray(F), points))
    return out
