"""Scenes: what a validated scene file builds, and running it frame by frame with output.

``load_scene(path)`` validates the file (nothing loaded or allocated yet); ``Scene.describe()``
loads the mesh (numpy only, no kernels) and reports what will be built; ``Scene.build()`` builds
only what the scene names (no surface embedding without ``[surface]``, ...) and returns a
:class:`SceneRun`, whose :meth:`SceneRun.run` writes the USD / npz / JSON-lines outputs.

Split by concern: the schema and validation are ``schema.py``, the integrator registry is the
package ``__init__``, loads as nodal data (handles, tractions, render surface) are ``loads.py``,
the describe-time estimates (points per element, device memory) are ``memory.py``, running a built
scene frame by frame (``SceneRun``, ``FrameStats``) is ``run.py``.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from .schema import ELEMENTS, ELEMENTS_FROM_TETS, ELEMENTS_WITH_BOX, SceneError, SceneSpec, parse_scene_file

__all__ = ["Scene", "BodyScene", "SceneRun", "FrameStats", "load_scene", "traction_forces", "element_traction_forces",
           "handle_targets", "estimate_device_memory", "boundary_surface", "quadrature_points_per_element"]


# loads (handles, tractions, render surface) and the describe-time estimates live in their own modules
from .loads import (_element_faces, _rotation, boundary_surface, element_traction_forces,  # noqa: E402, F401
                    handle_targets, traction_forces)
from .memory import (_block_nnz, _fmt_bytes, _volume_cell_types, estimate_device_memory,  # noqa: E402, F401
                     quadrature_points_per_element)
from .run import FrameStats, SceneRun  # noqa: E402, F401 - running a built scene


def _body_plain(v):
    return list(v) if isinstance(v, tuple) else v



class _SceneBodies:
    """What a scene of ``[[body]]`` tables builds and describes (mixed into :class:`Scene`)."""

    def _model(self):
        """The model of the scene's bodies (``Model.from_bodies``, one :class:`warpfem.Body` per body:
        its mesh, material, element type, mass matrix kind; a scene of the top-level form is the
        one-body case). A body's error names the body's section; overlapping bodies are a
        SceneError naming both and the first crossing."""
        from warpfem.model import Model

        try:
            return Model.from_bodies([b.model_body() for b in self.bodies], gravity=self.spec.top["gravity"],
                                     mass_matrix=self.spec.material["mass_matrix"])
        except ValueError as e:
            i = getattr(e, "body", None)
            if i is None:
                self._fail("[[body]]", str(e))
            msg = str(e.__cause__)  # e.g. an element with det J <= 0 at a quadrature point (named)
            self.bodies[i].fail("[mesh]" if "element" in msg.lower() else "[material]", msg)

    def model_body(self):
        """This scene's own body (its [mesh] and [material]) as a :class:`warpfem.Body`."""
        from warpfem.materials import make_material
        from warpfem.model import Body

        mat = self.spec.material
        material = make_material(mat["model"], youngs_modulus=mat["youngs_modulus"], poisson_ratio=mat["poisson_ratio"],
                                 density=mat["density"])
        body = Body(self.own_mesh(), material, initial_velocity=self.initial_velocity,
                    volumetric_integration=mat["volumetric_integration"], mass_matrix=mat["mass_matrix"])
        body.name = self.body_name
        body.offset = self.offset  # the mesh is already moved (selections were made on it)
        return body

    def _describe_bodies(self) -> str:
        """``warpfem describe`` of a ``[[body]]`` scene: every body, then the shared sections."""
        from . import INTEGRATORS, section_entries

        sp = self.spec
        mesh, offsets = self.mesh(), self.body_offsets
        rigid = [b for b in self.bodies if getattr(b, "kind", "soft") == "rigid"]
        nodes = mesh.num_vertices - sum(b.own_mesh().num_vertices for b in rigid) + 4 * len(rigid)  # 4 per rigid body
        lines = [f"scene {self.name!r} ({self.path}): {len(self.bodies)} bodies, {mesh.num_elements} elements, "
                 f"{mesh.num_vertices} vertices, {3 * nodes} DOFs in all"]
        memory = {"float32": 0, "float64": 0}
        nnz_total = 0
        for b, lo, hi in zip(self.bodies, offsets[:-1], offsets[1:]):
            if getattr(b, "kind", "soft") == "rigid":
                r = b.rigid_summary()
                lines.append(f"body {b.body_name!r} ({b.label}): rigid, vertices {lo}..{hi - 1}: {r['source']}")
                lines.append(f"  {r['surface_triangles']} surface triangles; density {r['density']:g} kg/m^3, mass "
                             f"{r['mass']:.6g} kg, centre of mass {r['center_of_mass']} m, volume {r['volume']:.6g} m^3")
                lines.append(f"  initial velocity {r['initial_velocity']} m/s, angular velocity "
                             f"{r['initial_angular_velocity']} rad/s, orthogonality stiffness {r['stiffness']:g} Pa; "
                             f"4 nodes (p, A) of the unknown")
                for i, ids in enumerate(b.selections()["force"]):
                    lines.append(f"  force #{i + 1}: {ids.size} vertices, {list(b.spec.force[i]['force'])} N each")
                nnz_total += 16
                for prec in memory:
                    memory[prec] += _rigid_memory(int(hi - lo), prec)
                continue
            bs, bm = b.spec, b.mesh()
            etype, vi = bs.mesh["element"], bs.material["volumetric_integration"]
            qpe = quadrature_points_per_element(etype, vi)
            src = (f"box generator size {list(bs.mesh['size'])} m, cells {list(bs.mesh['cells'])}" if bs.mesh["generator"]
                   else f"file {bs.mesh['path']}" + (f" prim {bs.mesh['prim']}" if bs.mesh.get("prim") else ""))
            lines.append(f"body {b.body_name!r} ({b.label}): vertices {lo}..{hi - 1}: {src}")
            if getattr(bm, "tetrahedralization", None) is not None:
                lines.append(f"  {bm.tetrahedralization.describe()}")
            lines += [f"  warning: {w}" for w in b.mesh_warnings]
            lines.append(f"  element {etype} ({ELEMENTS[etype]}): {bm.num_elements} elements, {bm.num_vertices} vertices, "
                         f"{bm.num_elements * qpe} quadrature points")
            mat = bs.material
            lines.append(f"  material: {mat['model']} E = {mat['youngs_modulus']:g} Pa, nu = {mat['poisson_ratio']:g}, "
                         f"density = {mat['density']:g} kg/m^3, {mat['mass_matrix']} mass, {vi} volumetric integration")
            lines.append(f"  offset {b.offset.tolist()} m, initial velocity {b.initial_velocity.tolist()} m/s, "
                         f"bounds {np.round(bm.bounds()[0], 6).tolist()} .. {np.round(bm.bounds()[1], 6).tolist()}")
            sel = b.selections()
            for s in ("fixed", "handle", "force"):
                for i, (e, ids) in enumerate(zip(getattr(bs, s), sel[s])):
                    extra = f", components {e['components']}" if s in ("fixed", "handle") else f", {list(e['force'])} N each"
                    if s == "handle":
                        extra += f", translation {list(e['translation'])} m"
                    lines.append(f"  {s} #{i + 1}: {ids.size} vertices{extra}")
            for i, (f, faces, area) in enumerate(b.tractions()):
                lines.append(f"  traction #{i + 1}: {faces.size} faces, area {area:.6g} m^2")
            if bs.surface is not None:
                lines.append(f"  render surface: {bs.surface['path']} (USD prim {b.body_name}), embedded in its elements")
            else:
                ids, tri = boundary_surface(bm)
                lines.append(f"  render surface: its boundary ({ids.size} vertices, {len(tri)} triangles; USD prim "
                             f"{b.body_name})")
            k = bm.nodes_per_element
            nnz = _block_nnz(bm.elements, k, bm.num_vertices)
            nnz_total += nnz
            for prec in memory:
                memory[prec] += estimate_device_memory(num_vertices=bm.num_vertices, num_elements=bm.num_elements,
                                                       nodes_per_element=k, num_points=bm.num_elements * qpe, block_nnz=nnz,
                                                       precision=prec, weights_per_point=k,
                                                       stiffness_damping=sp.integrator.get("damping_stiffness", 0.0) > 0)
        lines.append(f"gravity: {list(sp.top['gravity'])} m/s^2")
        entry = INTEGRATORS[self.integrator_type]
        integ = sp.integrator
        if entry.dynamic:
            lines.append(f"integrator: {self.integrator_type}, dt = {integ['dt']:g} s, {integ['substeps']} step(s) per frame")
        else:
            lines.append(f"integrator: {self.integrator_type}, {integ.get('load_steps', 1)} load step(s) per frame")
        lines.append(f"  builds: {', '.join(entry.builds)} (one vertex space, one quadrature set per body)")
        ls = self.linear_solver_plan()
        if ls is not None:
            lines.append(f"  linear solver: {ls['name']}: cpu: {ls['cpu']}; cuda: {ls['cuda']}")
        for i, c in enumerate(self.collider_plan()):
            lines.append(f"collider #{i + 1}: {c['text']}")
        lines += self._contact_lines()
        for extra in section_entries(self):
            if extra.describe is not None:
                lines.append(extra.describe(self))
        out = sp.output
        lines.append(f"frames: {out['frames']} at {out['fps']:g} fps ({out['frames'] / out['fps']:g} s)")
        lines.append(f"outputs: usd {out['usd'] or '-'} (one prim per body{', with its TetMesh' if out.get('usd_volume') else ''}), "
                     f"states {out['states'] or '-'} (bodies concatenated, body_offsets), "
                     f"stats {self.stats_path(out['usd'], out['stats']) or '-'}")
        if out.get("vtu"):
            lines.append(f"  vtu: {out['vtu']} (ParaView collection, one block per body)")
        for prec, b in memory.items():
            lines.append(f"estimated device memory ({prec}): {_fmt_bytes(b)} ({nnz_total} 3x3 matrix blocks)")
        lines += self._cost_lines()
        return "\n".join(lines)


    def _summary_bodies(self) -> dict:
        """``describe --json`` of a ``[[body]]`` scene: the shared keys and one entry per body."""
        from warpfem.io.vtu import warpfem_version

        from . import INTEGRATORS

        sp, mesh, offsets = self.spec, self.mesh(), self.body_offsets
        entry = INTEGRATORS[self.integrator_type]
        out = sp.output
        bodies = []
        for b, lo, hi in zip(self.bodies, offsets[:-1], offsets[1:]):
            if getattr(b, "kind", "soft") == "rigid":
                bodies.append({"name": b.body_name, "kind": "rigid", "offset": b.offset.tolist(),
                               "initial_velocity": b.initial_velocity.tolist(), "first_vertex": int(lo),
                               "vertices": int(hi - lo), "rigid": b.rigid_summary(), "matrix_blocks": 16,
                               "estimated_device_memory_bytes": {p: _rigid_memory(int(hi - lo), p)
                                                                 for p in ("float32", "float64")}})
                continue
            s = b.summary()
            bodies.append({"name": b.body_name, "offset": b.offset.tolist(), "initial_velocity": b.initial_velocity.tolist(),
                           "first_vertex": int(lo), "vertices": int(hi - lo), "mesh": s["mesh"], "material": s["material"],
                           "selections": s["selections"], "tractions": s["tractions"], "render_surface": s["render_surface"],
                           "matrix_blocks": s["matrix_blocks"], "estimated_device_memory_bytes": s["estimated_device_memory_bytes"]})
        return {
            "scene": self.name, "path": self.path, "warpfem_version": warpfem_version(),
            "bodies": bodies, "body_offsets": [int(o) for o in offsets],
            "vertices": int(mesh.num_vertices), "elements": int(mesh.num_elements), "dofs": int(3 * mesh.num_vertices),
            "gravity": list(sp.top["gravity"]),
            "integrator": {**{key: _body_plain(val) for key, val in sp.integrator.items()}, "dynamic": bool(entry.dynamic),
                           "builds": list(entry.builds), "linear_solver_plan": self.linear_solver_plan()},
            "colliders": [{k: v for k, v in c.items() if k != "text"} for c in self.collider_plan()],
            "frames": int(out["frames"]), "fps": float(out["fps"]), "duration": float(out["frames"] / out["fps"]),
            "outputs": {"usd": out["usd"], "usd_clip_frames": out["clip_frames"] if out["usd"] else None,
                        "usd_volume": bool(out.get("usd_volume")), "states": out["states"],
                        "stats": self.stats_path(out["usd"], out["stats"]), "vtu": out.get("vtu")},
            "matrix_blocks": int(sum(b["matrix_blocks"] for b in bodies)),
            "estimated_device_memory_bytes": {p: int(sum(b["estimated_device_memory_bytes"][p] for b in bodies))
                                              for p in ("float32", "float64")},
        }


def _rigid_memory(surface_vertices: int, precision: str) -> int:
    """Estimated device bytes of a rigid body: its 4 nodes (state, work vectors, a 4 x 4 block
    mass and Hessian) and the embedding of its surface vertices (node ids, weights, world positions
    and ~4 vec3 contact work vectors per vertex)."""
    s = 4 if precision == "float32" else 8
    nodes = estimate_device_memory(num_vertices=4, num_elements=0, nodes_per_element=0, num_points=0,
                                   block_nnz=16, precision=precision, surface_points=surface_vertices,
                                   weights_per_point=4)
    return int(nodes + surface_vertices * 4 * 3 * s)


# ----------------------------------------------------------------------------- Scene
class Scene(_SceneBodies):
    """A validated scene file. Nothing is loaded or allocated until :meth:`describe`/:meth:`build`."""

    def __init__(self, spec: SceneSpec):
        self.spec = spec
        self.path = spec.path
        self._mesh = None
        self._own = None  # this scene's own [mesh], loaded (a body's; own_mesh())
        self.own_mesh_warnings = []
        self.mesh_warnings = []  # the mesh loader's warnings (filled by mesh())

    @property
    def name(self) -> str:
        if self.spec.top.get("name"):
            return self.spec.top["name"]
        return os.path.splitext(os.path.basename(self.path))[0] if self.path else "scene"

    @property
    def integrator_type(self) -> str:
        return self.spec.integrator["type"]

    @property
    def dynamic(self) -> bool:
        from . import INTEGRATORS

        return INTEGRATORS[self.integrator_type].dynamic

    def fail(self, where, msg):
        """Raise a :class:`SceneError` naming the scene file and the section ``where``."""
        raise SceneError(f"{self.path or '<scene>'}: {where}: {msg}")

    _fail = fail

    # -- mesh and selections (numpy) --------------------------------------------------------------
    @property
    def bodies(self) -> list:
        """The scene's bodies, each a scene of its own (mesh, material, selections in its own vertex
        numbering): the ``[[body]]`` tables (:class:`BodyScene`: mesh moved by the body's offset,
        errors naming the body), or, for a scene of the top-level form ([mesh], [material]), the
        scene itself: a one-body scene is its own one body. Everything else runs over this list."""
        if getattr(self, "_bodies", None) is None:
            self._bodies = [BodyScene(self, b) for b in self.spec.bodies]
        return self._bodies or [self]  # not kept: a copy of the scene is its own body

    # -- the scene as a body (its own [mesh] and [material]; BodyScene: a [[body]] table) ------------
    label = None  # BodyScene: "[[body]] #2 'right'" (messages)

    @property
    def offset(self) -> np.ndarray:
        """The body's translation (m): zero for a scene of the top-level form."""
        return np.zeros(3)

    @property
    def initial_velocity(self) -> np.ndarray:
        """The body's velocity at t = 0 (m/s): zero for a scene of the top-level form."""
        return np.zeros(3)

    @property
    def body_name(self) -> str:
        """The body's name in the model: its mesh's name, or "body" (BodyScene: the table's name)."""
        return getattr(self.own_mesh(), "name", None) or "body"

    @property
    def surface_prim(self) -> str:
        """The USD prim of the body's render surface: the [surface] name, or "boundary"."""
        return self.spec.surface["name"] if self.spec.surface is not None else "boundary"

    @property
    def volume_prim(self) -> str:
        """The USD prim of the body's TetMesh (``[output] usd_volume``)."""
        return "volume"

    @property
    def block_name(self):
        """The body's ParaView block name (None: the collection holds the one body's cells)."""
        return None

    @property
    def named_bodies(self) -> bool:
        """Whether the outputs name each body: a scene of ``[[body]]`` tables (USD prims and ParaView
        blocks by body name, ``body_offsets`` / ``body_names`` in the states file)."""
        return bool(self.spec.bodies)

    @property
    def body_offsets(self) -> np.ndarray:
        """The first vertex of each body in the scene's vertex numbering, then the total."""
        return np.concatenate([[0], np.cumsum([b.own_mesh().num_vertices for b in self.bodies])]).astype(np.int64)

    @property
    def contact_by_default(self) -> bool:
        """Two or more bodies: contact between them without a [contact] section (its defaults)."""
        return len(self.bodies) >= 2

    def mesh(self):
        """The simulation mesh (loaded / generated once) as the model sees it: the one body's
        ``warpfem.mesh.VolumeMesh`` (of the scene's element type), or a
        :class:`warpfem.model.BodiesMesh` of every body's mesh (``warpfem.model.bodies_mesh``)."""
        if self._mesh is None:
            from warpfem.model import bodies_mesh

            meshes = [b.own_mesh() for b in self.bodies]
            self._mesh = bodies_mesh(meshes, self.body_offsets, [b.body_name for b in self.bodies])
            # the loader's notes (reoriented tets, removed vertices): `describe` lists them, `build` logs them
            self.mesh_warnings = [w if b is self else f"{b.label}: {w}" for b in self.bodies for w in b.own_mesh_warnings]
        return self._mesh

    def own_mesh(self):
        """This scene's own [mesh] (a body's; loaded / generated once), the loader's notes in
        ``own_mesh_warnings``."""
        if self._own is None:
            import warnings

            from warpfem.elements import ElementError
            from warpfem.mesh import MeshError

            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")  # reorientation / unreferenced notes: kept
                    self._own = self._make_mesh()
            except (MeshError, ElementError, ValueError) as e:
                if isinstance(e, SceneError):
                    raise
                self._fail("[mesh]", str(e))
            self.own_mesh_warnings = list(dict.fromkeys(str(w.message) for w in caught))
        return self._own

    def _make_mesh(self):
        from warpfem.mesh import MeshError, load_element_mesh, load_mesh
        from warpfem.mesh.element_types import get_element

        m = self.spec.mesh
        element = m["element"]
        etype = get_element(element)
        if m["generator"] == "box":  # the schema checked that this type has a box generator
            return etype.box_mesh(size=m["size"], cells=m["cells"], origin=m["origin"])
        path = m["path"]
        wanted = etype.meshio_cell
        if element in ELEMENTS_FROM_TETS:
            try:  # a surface file is tetrahedralised (warpfem.mesh.tetrahedralize; cached)
                tetra = {k: m[k] for k in ("max_edge_length", "max_radius_edge_ratio", "mesher", "target_tets", "prim")
                         if m.get(k) is not None}
                if m.get("target_tets_default"):  # the default is an upper bound; a value given is a target
                    tetra["coarsen_only"] = True
                mesh = load_mesh(path, inside_surface=m["inside_surface"], **tetra)
                self._tetrahedralization = getattr(mesh, "tetrahedralization", None)
            except MeshError:
                from warpfem.mesh.usd_in import is_usd_path

                if is_usd_path(path):  # a TetMesh or a closed Mesh, nothing else to try
                    raise
                cells = _volume_cell_types(path)
                if "tetra" in cells or not (wanted in cells):
                    raise
            else:
                return etype.from_tet4(mesh, name=path)
        cells = _volume_cell_types(path)  # only tetra10 / hex files get here (read twice: small files)
        if wanted in cells:
            if m["inside_surface"]:
                self._fail("[mesh].inside_surface", f"{path}: only applies to linear tetra cells (the file has {wanted})")
            return load_element_mesh(path, element_type=element)
        found = ", ".join(f"{k} ({v})" for k, v in sorted(cells.items())) or "none"
        if "tetra" in cells:
            tets = " or ".join(f"\"{n}\"" for n in ELEMENTS_FROM_TETS)
            boxes = ", ".join(ELEMENTS_WITH_BOX)
            hint = (f"a tet mesh cannot be turned into {element} elements; use element = {tets} with "
                    f"this file, generator = \"box\" ({boxes}), or a file with {wanted} cells")
        else:
            hint = f"element {element!r} needs {wanted} cells"
        self._fail("[mesh].element", f"{path} holds cells {found}: {hint}")

    def _select(self, section, i, entry):
        from warpfem.mesh import select_vertices_in_box

        mesh = self.own_mesh()
        if entry.get("indices") is not None:
            ids = np.unique(np.asarray(entry["indices"], dtype=np.int64))
            if ids.max() >= mesh.num_vertices:
                self._fail(f"[[{section}]] #{i + 1}.indices", f"vertex index {int(ids.max())} out of range [0, {mesh.num_vertices})")
        else:
            ids = select_vertices_in_box(mesh.vertices, entry["box_min"], entry["box_max"])
        if ids.size == 0:
            lo, hi = mesh.bounds()
            self._fail(f"[[{section}]] #{i + 1}", f"selects no vertices (mesh bounds {np.round(lo, 6).tolist()} .. {np.round(hi, 6).tolist()})")
        return ids

    def selections(self) -> dict:
        """Vertex ids per ``[[fixed]]``, ``[[handle]]``, ``[[force]]`` entry: {section: [ids, ...]}
        (every body's entries in body order, global vertex ids)."""
        out = {s: [] for s in ("fixed", "handle", "force")}
        for b, lo in zip(self.bodies, self.body_offsets[:-1]):
            for s, ids in b.own_selections().items():
                out[s] += [i + int(lo) for i in ids]
        return out

    def own_selections(self) -> dict:
        """The selections of this scene's own entries, in its own mesh's vertex numbering."""
        return {s: [self._select(s, i, e) for i, e in enumerate(getattr(self.spec, s))] for s in ("fixed", "handle", "force")}

    def tractions(self):
        """[(forces (n, 3), loaded faces, area)] per ``[[traction]]`` entry (consistent loads; every
        body's entries in body order, forces over every vertex)."""
        offsets = self.body_offsets
        out = []
        for b, lo, hi in zip(self.bodies, offsets[:-1], offsets[1:]):
            for f, faces, area in b.own_tractions():
                g = np.zeros((int(offsets[-1]), 3))
                g[lo:hi] = f
                out.append((g, faces, area))
        return out

    def own_tractions(self):
        """The tractions of this scene's own entries, over its own mesh's vertices."""
        if not self.spec.traction:  # (a rigid body has none: the schema refuses them)
            return []
        mesh = self.own_mesh()
        tet4 = mesh.element.is_linear_tet  # plain triangles; other types integrate N_a on their faces
        faces = mesh.boundary_faces() if tet4 and self.spec.traction else None
        out = []
        for i, t in enumerate(self.spec.traction):
            if tet4:
                f, sel, area = traction_forces(mesh.vertices, faces, t["box_min"], t["box_max"], t["force_per_area"])
            else:
                f, sel, area = element_traction_forces(mesh, t["box_min"], t["box_max"], t["force_per_area"])
            if sel.size == 0:
                self._fail(f"[[traction]] #{i + 1}", "no boundary face has all its nodes inside the box")
            out.append((f, sel, area))
        return out

    # -- describe ---------------------------------------------------------------------------------
    def _contact_lines(self) -> list[str]:
        """describe's line on surface contact ([contact], or its defaults in a scene of two or more bodies)."""
        c = self.spec.contact
        if c is None and not self.contact_by_default:
            return []
        c = dict.fromkeys(("bodies", "self", "friction", "dhat", "stiffness", "friction_velocity")) if c is None else c
        return ["contact: " + ", ".join(f"{k} = {('default' if c[k] is None else c[k])}"
                                        for k in ("bodies", "self", "friction", "dhat", "stiffness", "friction_velocity"))
                + (" ([contact] defaults: several bodies)" if self.spec.contact is None else "") + " (docs/contact.md)"]

    def cost_estimate(self) -> dict | None:
        """The estimated seconds per frame and for the run, with its basis
        (:func:`warpfem.scenes.cost.estimate_frame_cost`: steps per frame, Newton iterations, a
        per-iteration CPU cost by vertex count, a contact factor); None for a reduced run
        (``[subspace]``), which it does not model."""
        from . import INTEGRATORS
        from .cost import estimate_frame_cost

        sp = self.spec
        if getattr(sp, "subspace", None) is not None:
            return None
        integ = sp.integrator
        steps = int(integ["substeps"]) if INTEGRATORS[self.integrator_type].dynamic else int(integ.get("load_steps", 1))
        contact = bool(sp.collider) or sp.contact is not None or self.contact_by_default
        return estimate_frame_cost(vertices=self.mesh().num_vertices, steps_per_frame=steps, frames=int(sp.output["frames"]),
                                   contact=contact, newton=self.integrator_type != "stiffness_warping")

    def _cost_lines(self) -> list[str]:
        from warpfem.progress import format_duration

        c = self.cost_estimate()
        if c is None:
            return ["estimated cost: not estimated for a reduced run ([subspace])"]
        per = c["seconds_per_frame"]
        return [f"estimated cost (CPU, float64): {per:.3g} s per frame, {format_duration(c['seconds_total'])} for "
                f"{self.spec.output['frames']} frames (rough: within {c['stated_factor']:g}x on typical scenes, more "
                f"for hard contact or large rotations; no kernel compilation counted; {c['basis']})"]

    def describe(self, *, precision: str = "float64") -> str:
        """What :meth:`build` will build: counts, selections, integrator, outputs and memory."""
        from . import INTEGRATORS

        if self.named_bodies:  # the [[body]] form: a section per body
            return self._describe_bodies()
        sp = self.spec
        mesh = self.mesh()
        k = mesh.nodes_per_element
        n, m = mesh.num_vertices, mesh.num_elements
        entry = INTEGRATORS[self.integrator_type]
        sel = self.selections()
        lines = [f"scene {self.name!r} ({self.path})"]
        src = (f"box generator size {list(sp.mesh['size'])} m, cells {list(sp.mesh['cells'])}" if sp.mesh["generator"]
               else f"file {sp.mesh['path']}" + (" (tets inside its surface)" if sp.mesh["inside_surface"] else ""))
        lines.append(f"mesh: {src}")
        if getattr(self, "_tetrahedralization", None) is not None:
            lines.append(f"  {self._tetrahedralization.describe()}")
        lines += [f"warning: {w}" for w in self.mesh_warnings]  # the mesh loader's (reoriented tets, ...)
        etype = sp.mesh["element"]
        vi = sp.material["volumetric_integration"]
        qpe = quadrature_points_per_element(etype, vi)
        lines.append(f"  element {etype} ({ELEMENTS[etype]}): {m} elements, {n} vertices, {3 * n} DOFs")
        lines.append(f"  {k} nodes per element, {qpe} quadrature point(s) per element"
                     + (" (2x2x2 shear + 1 volumetric: selective reduced integration)" if vi == "reduced" else "")
                     + f", {m * qpe} quadrature points")
        mat = sp.material
        lines.append(f"material: {mat['model']} E = {mat['youngs_modulus']:g} Pa, nu = {mat['poisson_ratio']:g}, "
                     f"density = {mat['density']:g} kg/m^3, {mat['mass_matrix']} mass, {vi} volumetric integration")
        lines.append(f"gravity: {list(sp.top['gravity'])} m/s^2")
        for s in ("fixed", "handle", "force"):
            for i, (e, ids) in enumerate(zip(getattr(sp, s), sel[s])):
                extra = ""
                if s in ("fixed", "handle"):
                    extra = f", components {e['components']}"
                if s == "handle":
                    extra += f", translation {list(e['translation'])} m"
                    if e["rotation_angle"]:
                        extra += f", rotation {e['rotation_angle']:g} deg about {list(e['rotation_axis'])}"
                if s == "force":
                    extra = f", {list(e['force'])} N each"
                lines.append(f"{s} #{i + 1}: {ids.size} vertices{extra}")
        for i, (f, faces, area) in enumerate(self.tractions()):
            lines.append(f"traction #{i + 1}: {faces.size} faces, area {area:.6g} m^2, total force {f.sum(axis=0).round(9).tolist()} N")
        integ = sp.integrator
        if entry.dynamic:
            lines.append(f"integrator: {self.integrator_type}, dt = {integ['dt']:g} s, {integ['substeps']} step(s) per frame")
        else:
            lines.append(f"integrator: {self.integrator_type}, {integ.get('load_steps', 1)} load step(s) per frame")
        from . import section_entries

        reduced = [e for e in section_entries(self) if e.section == "subspace" and e.builds]
        lines.append(f"  builds: {', '.join(reduced[0].builds if reduced else entry.builds)}")
        ls = self.linear_solver_plan()
        if ls is not None:
            head = "  linear solver: "
            if reduced:
                head += "dense r x r (the reduced system); `warpfem train`'s full training run: "
                ls = ls["training_run"]
            lines.append(head + ls["name"] + (" (picks by size and device, docs/linear_solvers.md)"
                                              if ls["name"] == "auto" else "") + ":")
            lines.append(f"    cpu: {ls['cpu']}")
            lines.append(f"    cuda: {ls['cuda']}")
        for i, c in enumerate(self.collider_plan(precision)):
            lines.append(f"collider #{i + 1}: {c['text']}")
        lines += self._contact_lines()
        for extra in section_entries(self):  # e.g. [subspace]: the reduced run (warpfem.reduced.scene)
            if extra.describe is not None:
                lines.append(extra.describe(self))
        out = sp.output
        lines.append(f"frames: {out['frames']} at {out['fps']:g} fps ({out['frames'] / out['fps']:g} s)")
        if sp.surface is not None:
            from warpfem.skinning import load_surface

            sv, st = load_surface(sp.surface["path"])
            p = len(sv)
            how = "barycentric" if mesh.element.is_linear_tet else f"{k} shape functions"
            own = " (the [mesh] surface at full resolution)" if sp.surface.get("from_mesh") else ""
            lines.append(f"render surface: {sp.surface['path']}{own} ({p} vertices, {len(st)} triangles), embedded in "
                         f"the {etype} elements ({how} per vertex); physics mesh: {m} elements, {n} vertices")
        else:
            ids, tri = boundary_surface(mesh)
            p = 0
            lines.append(f"render surface: mesh boundary ({ids.size} vertices, {len(tri)} triangles); no embedding")
        clips = (f"value clips of {out['clip_frames']} frames in {os.path.splitext(out['usd'])[0]}.clips/"
                 if out["clip_frames"] else "one file") if out["usd"] else ""
        lines.append(f"outputs: usd {out['usd'] or '-'}{' (' + clips + ')' if clips else ''}, states {out['states'] or '-'}, "
                     f"stats {self.stats_path(out['usd'], out['stats']) or '-'}")
        if out.get("vtu"):
            lines.append(f"  vtu: {out['vtu']} (ParaView collection; one .vtu per frame in {os.path.splitext(out['vtu'])[0]}.vtu/)")
        nnz = _block_nnz(mesh.elements, k, n)
        for prec in ("float32", "float64"):
            b = estimate_device_memory(num_vertices=n, num_elements=m, nodes_per_element=k, num_points=m * qpe,
                                       block_nnz=nnz, precision=prec, surface_points=p, weights_per_point=k,
                                       stiffness_damping=sp.integrator.get("damping_stiffness", 0.0) > 0)
            lines.append(f"estimated device memory ({prec}): {_fmt_bytes(b)} ({nnz} 3x3 matrix blocks)")
        lines += self._cost_lines()
        return "\n".join(lines)

    def linear_solver_plan(self) -> dict | None:
        """The linear solver the run will use (``[integrator] linear_solver``) and, per device, what
        it will do on this mesh (``auto``: :func:`warpfem.solvers.linear.auto.describe_choice`, by the
        number of unknowns); None when the integrator takes no linear solver (a reduced run solves
        its r x r systems densely)."""
        from . import INTEGRATORS, section_entries

        entry = INTEGRATORS[self.integrator_type]
        if "linear_solver" not in entry.keys:
            return None
        name = self.spec.integrator.get("linear_solver") or "auto"
        dofs = 3 * self.mesh().num_vertices
        if name == "auto":
            from warpfem.solvers.linear.auto import describe_choice

            plan = {"name": name, "unknowns": dofs, **describe_choice(dofs)}
        else:
            import importlib

            from warpfem.solvers.linear.base import _REGISTRY

            mod, cls = _REGISTRY[name].split(":")
            doc = (getattr(importlib.import_module(mod), cls).__doc__ or name).strip().split("\n")[0].rstrip(".")
            plan = {"name": name, "unknowns": dofs, "cpu": doc, "cuda": doc}
        if any(e.section == "subspace" for e in section_entries(self)):  # reduced: dense r x r; training: full
            return {"name": "dense (reduced r x r)", "training_run": plan}
        return plan

    def collider_plan(self, precision: str = "float64") -> list:
        """The ``[[collider]]`` entries as they will run: type, name, geometry, motion, friction and
        the contact distance / barrier stiffness with the body-based defaults filled in (as
        :class:`warpfem.contact.contact.ContactSet` fills them, with the one formula
        :func:`warpfem.contact.colliders.contact_parameters`: dhat 0.1 x mean boundary edge, kappa
        max(E x mean edge, weight / (surface vertices x dhat)), friction velocity 1e-3 x diagonal per
        second, 1e-2 in float32)."""
        from warpfem.contact.colliders import collider_class, contact_parameters

        sp = self.spec
        if not sp.collider:
            return []
        mesh = self.mesh()
        X = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.boundary_faces())
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        mean_edge = float(np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1).mean())
        diagonal = float(np.linalg.norm(np.ptp(X, axis=0)))
        surface = int(np.unique(faces).size)
        # as the model: every body's mass, the stiffest body's E
        mass = sum(float(b.spec.material["density"]) * b.own_mesh().total_volume() for b in self.bodies)
        E = max(float(b.spec.material.get("youngs_modulus") or 0.0) for b in self.bodies)
        out = []
        for i, c in enumerate(sp.collider):
            auto = c.get("stiffness") == "auto"  # adaptive (warpfem.contact.stiffness): set per step
            dhat, kappa, epsv = contact_parameters(
                c.get("dhat"), None if auto else c.get("stiffness"), c.get("friction_velocity"), mean_edge=mean_edge,
                diagonal=diagonal, total_mass=mass, surface_vertices=surface, youngs_modulus=E, precision=precision)
            geo = {k: (list(c[k]) if isinstance(c[k], tuple) else c[k]) for k in collider_class(c["type"]).geometry_keys()
                   if c.get(k) is not None}
            moves = any(c.get("translation") or ()) or bool(c.get("rotation_angle"))
            d = {"type": c["type"], "name": c.get("name") or f"{c['type']}{i + 1}", **geo,
                 "friction": float(c["friction"]), "dhat": float(dhat), "dhat_default": c.get("dhat") is None,
                 "stiffness": "auto" if auto else float(kappa), "stiffness_default": c.get("stiffness") is None,
                 "friction_velocity": float(epsv), "moving": moves}
            if moves:
                d.update(translation=list(c["translation"]), rotation_angle=float(c["rotation_angle"] or 0.0),
                         rotation_axis=None if c.get("rotation_axis") is None else list(c["rotation_axis"]),
                         ramp_time=c.get("ramp_time"))
            text = (f"{d['type']} {d['name']!r}, " + ", ".join(f"{k} {v}" for k, v in geo.items())
                    + f", friction {d['friction']:g}"
                    + f", dhat {dhat:.4g} m{' (default: 0.1 x mean boundary edge)' if d['dhat_default'] else ''}"
                    + (", barrier stiffness adaptive" if auto else
                       f", barrier stiffness {kappa:.4g} N/m{' (default)' if d['stiffness_default'] else ''}")
                    + (f", moves by {list(c['translation'])} m" if any(c.get("translation") or ()) else "")
                    + (f", turns {c['rotation_angle']:g} deg" if c.get("rotation_angle") else "")
                    + (f" over {c['ramp_time']:g} s" if moves and c.get("ramp_time") else " over the run" if moves else ""))
            out.append({**d, "text": text})
        return out

    def summary(self) -> dict:
        """What :meth:`describe` prints, as a JSON-serialisable dict (``warpfem describe --json``)."""
        from warpfem.io.vtu import warpfem_version

        from . import INTEGRATORS

        if self.named_bodies:  # the [[body]] form: an entry per body
            return self._summary_bodies()
        sp, mesh = self.spec, self.mesh()
        k, n, m = mesh.nodes_per_element, mesh.num_vertices, mesh.num_elements
        etype, vi = sp.mesh["element"], sp.material["volumetric_integration"]
        qpe = quadrature_points_per_element(etype, vi)
        entry = INTEGRATORS[self.integrator_type]
        sel = self.selections()
        out = sp.output

        def plain(v):
            return list(v) if isinstance(v, tuple) else v

        selections = {}
        for s in ("fixed", "handle", "force"):
            selections[s] = [{**{key: plain(val) for key, val in e.items() if key not in ("indices",)},
                              "vertices": int(ids.size)} for e, ids in zip(getattr(sp, s), sel[s])]
        tractions = [{"faces": int(faces.size), "area": float(area), "total_force": f.sum(axis=0).round(9).tolist()}
                     for f, faces, area in self.tractions()]
        if sp.surface is not None:
            from warpfem.skinning import load_surface

            sv, st = load_surface(sp.surface["path"])
            p = len(sv)
            surface = {"source": sp.surface["path"], "vertices": int(len(sv)), "triangles": int(len(st)), "embedded": True}
        else:
            ids, tri = boundary_surface(mesh)
            p = 0
            surface = {"source": "boundary", "vertices": int(ids.size), "triangles": int(len(tri)), "embedded": False}
        nnz = _block_nnz(mesh.elements, k, n)
        memory = {prec: estimate_device_memory(num_vertices=n, num_elements=m, nodes_per_element=k, num_points=m * qpe,
                                               block_nnz=nnz, precision=prec, surface_points=p, weights_per_point=k,
                                               stiffness_damping=sp.integrator.get("damping_stiffness", 0.0) > 0)
                  for prec in ("float32", "float64")}
        subspace = None
        if sp.subspace is not None:
            from . import section_entries

            lines = [e.describe(self) for e in section_entries(self) if e.section == "subspace" and e.describe]
            subspace = {**{key: plain(val) for key, val in sp.subspace.items()}, "describe": "\n".join(lines)}
        return {
            "scene": self.name, "path": self.path, "warpfem_version": warpfem_version(),
            "mesh": {"source": "box" if sp.mesh["generator"] else sp.mesh["path"],
                     **({"size": list(sp.mesh["size"]), "cells": list(sp.mesh["cells"])} if sp.mesh["generator"] else
                        {"inside_surface": bool(sp.mesh["inside_surface"])}),
                     "element": etype, "element_description": ELEMENTS[etype], "elements": int(m), "vertices": int(n),
                     "dofs": int(3 * n), "nodes_per_element": int(k), "quadrature_points_per_element": int(qpe),
                     "quadrature_points": int(m * qpe), "warnings": list(self.mesh_warnings)},
            "material": {key: plain(val) for key, val in sp.material.items()},
            "gravity": list(sp.top["gravity"]),
            "selections": selections, "tractions": tractions,
            "integrator": {**{key: plain(val) for key, val in sp.integrator.items()}, "dynamic": bool(entry.dynamic),
                           "builds": list(entry.builds), "linear_solver_plan": self.linear_solver_plan()},
            "colliders": [{k: v for k, v in c.items() if k != "text"} for c in self.collider_plan()],
            "contact": dict(sp.contact) if sp.contact is not None else None,
            "subspace": subspace,
            "frames": int(out["frames"]), "fps": float(out["fps"]), "duration": float(out["frames"] / out["fps"]),
            "render_surface": surface,
            "outputs": {"usd": out["usd"], "usd_clip_frames": out["clip_frames"] if out["usd"] else None,
                        "states": out["states"], "stats": self.stats_path(out["usd"], out["stats"]),
                        "vtu": out.get("vtu")},
            "matrix_blocks": int(nnz),
            "estimated_device_memory_bytes": memory,
            "estimated_cost": self.cost_estimate(),
        }

    def output_paths(self, *, usd=None, states=None, stats=None, vtu=None) -> dict:
        """{``[output]`` key: path or None} of a run: each given path, else the scene's (the statistics
        log defaults to ``<usd>.stats.jsonl``; a USD given here moves it along)."""
        out = self.spec.output
        usd = out["usd"] if usd is None else usd
        return {"usd": usd, "states": out["states"] if states is None else states,
                "stats": self.stats_path(usd, out["stats"] if stats is None else stats),
                "vtu": out.get("vtu") if vtu is None else vtu}

    @staticmethod
    def stats_path(usd, stats):
        if stats:
            return stats
        if usd:
            return os.path.splitext(usd)[0] + ".stats.jsonl"
        return None

    # -- build ------------------------------------------------------------------------------------
    def build(self, *, device="cpu", precision="float64", full: bool = False) -> "SceneRun":
        """Build the model, the integrator and (only with ``[surface]``) the surface embedding.

        ``full=True``: the full-space simulator even when a section (``[subspace]``) would replace
        it (the training run of a reduced scene)."""
        from . import integrator_entry

        if precision not in ("float32", "float64"):
            raise ValueError(f"precision must be 'float32' or 'float64', got {precision!r}")
        from warpfem.device import resolve_device

        device = resolve_device(device)  # DeviceError (lists the devices) before any scene work
        sp = self.spec
        self.mesh()  # every body's mesh, and the loaders' notes
        for w in self.mesh_warnings:
            logging.getLogger(__name__).warning("%s: [mesh]: %s", self.path or "<scene>", w)
        sel = self.selections()
        tractions = self.tractions()
        model = self._model()
        for e, ids in zip(sp.fixed, sel["fixed"]):
            model.fix(ids, e["components"])
        for e, ids in zip(sp.force, sel["force"]):
            model.add_force(ids, e["force"])
        n_soft = int(model.rigid.num_soft) if getattr(model, "rigid", None) is not None else model.num_vertices
        for f, _, _ in tractions:  # vertex space; only soft bodies have tractions (same numbering in q)
            model.forces[:n_soft] += f[:n_soft]
        for e, ids in zip(sp.handle, sel["handle"]):
            model.fix(ids, e["components"])
        # the [integrator].type's entry, or one registered for a section the scene has ([subspace]:
        # the reduced simulator, warpfem.reduced.scene); full=True: always the full-space simulator
        entry = integrator_entry(self, full=full)
        try:
            sim = entry.build(self, model, device=device, precision=precision)
        except SceneError:
            raise
        except ValueError as e:
            self._fail("[integrator]", str(e))
        if sp.collider:  # kinematic colliders (warpfem.contact)
            from warpfem.contact.scene import add_scene_colliders

            add_scene_colliders(self, sim, duration=sp.output["frames"] / sp.output["fps"])
        if sp.contact is not None or (self.contact_by_default and hasattr(sim, "set_contact")):  # warpfem.contact.surface
            from warpfem.contact.scene import set_scene_contact
            from warpfem.scenes.schema import SCHEMA

            set_scene_contact(self, sim, sp.contact if sp.contact is not None
                              else {k: key.default for k, key in SCHEMA["contact"].items()})
        return SceneRun(self, model, sim, sel["handle"], device=device, precision=precision)


# ----------------------------------------------------------------------------- several bodies
def _shifted(mesh, offset):
    """``mesh`` moved by ``offset`` (the same class of mesh; its loader's notes kept)."""
    from warpfem.mesh import VolumeMesh

    moved = VolumeMesh(np.asarray(mesh.vertices, dtype=np.float64) + offset, np.asarray(mesh.elements),
                       mesh.element_type, reorient=False, remove_unreferenced=False, name=getattr(mesh, "name", None))
    for attr in ("tetrahedralization", "vertex_map", "usd_surface"):
        if getattr(mesh, attr, None) is not None:
            value = getattr(mesh, attr)
            if attr == "usd_surface":
                value = (value[0] + offset, value[1])
            setattr(moved, attr, value)
    return moved


class BodyScene(Scene):
    """One ``[[body]]`` table of a scene, as a scene of its own: its spec holds the body's mesh,
    material, fixed / handle / force / traction entries and surface (and the shared sections); its
    mesh is moved by the body's ``offset`` (so selection boxes are in scene coordinates); errors
    name the body."""

    def __init__(self, parent: Scene, body: dict):
        super().__init__(body["spec"])
        self.parent, self.body = parent, body
        self.label = body["label"]
        self._offset = np.asarray(body["offset"], dtype=np.float64)
        self._initial_velocity = np.asarray(body["initial_velocity"], dtype=np.float64)

    offset = property(lambda self: self._offset, doc="The body's translation (m).")
    initial_velocity = property(lambda self: self._initial_velocity, doc="The body's velocity at t = 0 (m/s).")
    body_name = property(lambda self: self.body["name"], doc="The ``[[body]]`` table's name.")
    surface_prim = property(lambda self: self.body_name, doc="USD prims are named after the body.")
    volume_prim = property(lambda self: f"{self.body_name}_volume", doc="The body's TetMesh prim.")
    block_name = property(lambda self: self.body_name, doc="ParaView blocks are named after the body.")

    kind = property(lambda self: self.body.get("kind", "soft"), doc="'soft' or 'rigid' (``kind`` of the table).")

    def fail(self, where, msg):
        raise SceneError(f"{self.path or '<scene>'}: {self.label}: {where}: {msg}")

    _fail = fail

    def rigid_summary(self) -> dict:
        """A rigid body's mass properties and settings (``describe``)."""
        body = self.model_body()
        m = self.spec.mesh
        src = (f"box generator size {list(m['size'])} m, cells {list(m['cells'])}" if m["generator"]
               else f"file {m['path']}")
        r = self.body["rigid"]
        return {"source": src, "surface_triangles": int(len(body.mesh.boundary_faces())), "density": float(r["density"]),
                "mass": float(body.mass), "volume": float(body.volume),
                "center_of_mass": np.round(body.center_of_mass, 9).tolist(),
                "inertia_tensor": np.round(body.inertia_tensor, 12).tolist(),
                "initial_velocity": self.initial_velocity.tolist(),
                "initial_angular_velocity": list(r["initial_angular_velocity"]), "stiffness": float(r["stiffness"])}

    def model_body(self):
        """This body as :class:`warpfem.Body`, or a rigid one as :class:`warpfem.RigidBody` (its mesh's
        closed surface, density, velocities; an open surface is a SceneError naming the body)."""
        if self.kind != "rigid":
            return super().model_body()
        from warpfem.rigid import RigidBody

        r = self.body["rigid"]
        mesh = self.own_mesh()
        try:
            body = RigidBody(mesh, density=r["density"], name=self.body_name, initial_velocity=self.initial_velocity,
                             initial_angular_velocity=r["initial_angular_velocity"], stiffness=r["stiffness"])
        except ValueError as e:
            self.fail("[mesh]", str(e))
        return body

    def _make_mesh(self):
        m = self.spec.mesh
        if self.kind == "rigid" and m["path"] and os.path.splitext(m["path"])[1].lower() in (".obj", ".off", ".ply", ".stl"):
            # a rigid body needs its closed surface only: the file's triangles, not tetrahedralised
            from warpfem.rigid.body import SurfaceBodyMesh, _closed_surface_error
            from warpfem.skinning import load_surface

            v, f = load_surface(m["path"])
            problem = _closed_surface_error(f)
            if problem:
                self.fail("[mesh].path", f"{m['path']}: a rigid body's surface must be closed, but {problem}")
            return _RigidSurfaceMesh(np.asarray(v, dtype=np.float64) + self.offset, f, name=m["path"])
        mesh = super()._make_mesh()
        if self.kind == "rigid":  # a volume mesh: its boundary must be closed (checked before any work)
            from warpfem.rigid.body import _closed_surface_error

            problem = _closed_surface_error(mesh.boundary_faces())
            if problem:
                self.fail("[mesh]", f"a rigid body's mesh must bound a solid, but {problem}")
        return _shifted(mesh, self.offset) if np.any(self.offset != 0.0) else mesh


def _rigid_surface_mesh_class():
    from warpfem.rigid.body import SurfaceBodyMesh

    class RigidSurfaceMesh(SurfaceBodyMesh):
        """A rigid body's closed surface as a scene's body mesh: no elements, its triangles the boundary."""

        nodes_per_element = 3

        def corner_tets(self):
            return np.zeros((0, 4), dtype=np.int64)

    return RigidSurfaceMesh


def _RigidSurfaceMesh(vertices, faces, name=None):
    return _rigid_surface_mesh_class()(vertices, faces, name=name)


def load_scene(path) -> Scene:
    """Read and validate a TOML scene file; raises :class:`SceneError` before any work on failure."""
    return Scene(parse_scene_file(path))
