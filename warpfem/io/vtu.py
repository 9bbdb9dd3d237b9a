"""The volume mesh over time as a ParaView collection: one ``.vtu`` per frame plus a ``.pvd`` index.

For ``out/run.pvd`` the writer produces::

    out/run.pvd                      the collection: one <DataSet timestep=t file=...> per frame
    out/run.vtu/frame_000000.vtu     frame 0 (the rest state)
    out/run.vtu/frame_000001.vtu     ...

Each ``.vtu`` (written with meshio, binary, zlib-compressed) holds the **current** node positions
as its points (so ParaView shows the deformed body as it plays the collection), the elements as
VTK cells (``tet4`` -> VTK_TETRA, ``tet10`` -> VTK_QUADRATIC_TETRA, ``hex8`` -> VTK_HEXAHEDRON,
``hex27`` -> VTK_TRIQUADRATIC_HEXAHEDRON; warpfem's node order is VTK's, see
``warpfem.mesh.element_types``), and

* point data ``displacement`` (x - X, m) and ``velocity`` (m/s);
* cell data ``J`` (det F, rest-volume weighted mean over the element's quadrature points, i.e.
  deformed volume / rest volume), ``von_mises`` (Pa) and ``cauchy_stress`` (Pa, 9 components,
  row-major) of the element's volume-averaged Cauchy stress (see :func:`element_stress_fields`).

Written incrementally: each frame's file is written (to a temporary name, then renamed) when the
frame is done, and the ``.pvd`` is then rewritten atomically (temporary file + rename). A run that
fails or is interrupted therefore leaves a valid collection of the frames written so far. The
``.pvd`` carries an XML comment ``<!-- warpfem {...} -->`` with ``complete``, ``frames``,
``version`` and, for an incomplete run, ``reason`` (ParaView ignores it; :func:`read_pvd` returns it).
"""

from __future__ import annotations

import json
import os
import re

import numpy as np

from .writers import FrameWriter

__all__ = ["VtuSeriesWriter", "VtuBodiesWriter", "ParaViewOutput", "VtuWriterError", "read_pvd", "frame_directory",
           "deformation_gradients", "element_stress_fields", "element_stress_fields_by_body", "von_mises",
           "warpfem_version"]

_FRAME_RE = re.compile(r"^frame_\d{6}\.vtu$")
_META_RE = re.compile(r"<!--\s*warpfem\s+(\{.*?\})\s*-->", re.S)



def _write_text_atomic(path, text):
    """Write ``text`` to ``path`` through ``path.partial`` and a rename: a reader never sees half a file."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".partial"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)

class VtuWriterError(ValueError):
    """Bad input to :class:`VtuSeriesWriter` (path, shapes, closed writer)."""


def warpfem_version() -> str:
    """The package version: ``warpfem.__version__``, else the installed distribution's metadata."""
    try:
        import warpfem

        v = getattr(warpfem, "__version__", None)
        if v:
            return str(v)
    except ImportError:  # pragma: no cover
        pass
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("warpfem")
    except PackageNotFoundError:  # pragma: no cover
        return "unknown"


def frame_directory(path) -> str:
    """Folder of the per-frame ``.vtu`` files of collection ``path`` (``out/run.pvd`` -> ``out/run.vtu``)."""
    return os.path.splitext(os.fspath(path))[0] + ".vtu"


# ----------------------------------------------------------------------------- fields
def deformation_gradients(model, x) -> np.ndarray:
    """F = I + sum_a (x_a - X_a) dN_a/dX^T at every (main) quadrature point of ``model``, (Q, 3, 3)."""
    qd = model.quadrature
    k = qd.nodes_per_element
    u = np.asarray(x, dtype=np.float64) - model.rest_positions
    E = np.asarray(qd.elements, dtype=np.int64).reshape(-1, k)
    dN = np.asarray(qd.qp_dNdX, dtype=np.float64).reshape(-1, k, 3)  # (Q, k, 3)
    ue = u[E[np.asarray(qd.qp_element, dtype=np.int64)]]  # (Q, k, 3)
    return np.eye(3)[None] + np.einsum("qai,qaj->qij", ue, dN)


def von_mises(sigma) -> np.ndarray:
    """sqrt(3/2 s:s), s the deviatoric part of the (..., 3, 3) stress."""
    sigma = np.asarray(sigma, dtype=np.float64)
    s = sigma - np.trace(sigma, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("...ij,...ij->...", s, s))


def element_stress_fields(sim, model, x=None) -> dict:
    """Per-element ``J`` (m,), ``cauchy_stress`` (m, 3, 3) and ``von_mises`` (m,) at positions x (default the
    simulator's current positions).

    The first Piola-Kirchhoff stress P at the quadrature points is the simulator's own,
    ``sim.stresses(x)`` (:class:`warpfem.Simulator`: its material; stiffness warping: the corotational
    linear stress; the reduced simulator: the full material at the reconstructed positions); an
    object without ``stresses`` (positions only) gets the model's material evaluated at F.
    Cauchy sigma = P F^T / J. With w_q the rest-volume quadrature weights of an element:
    J_e = sum w_q J_q / sum w_q (deformed / rest volume) and sigma_e = sum w_q J_q sigma_q / sum w_q J_q
    (the deformed-volume mean of the Cauchy stress); von Mises from sigma_e.
    """
    x = sim.positions() if x is None else np.asarray(x, dtype=np.float64)
    F = deformation_gradients(model, x)
    stresses = getattr(sim, "stresses", None)
    P = model.material.pk1(F) if stresses is None else stresses(x)
    return _element_fields(model.quadrature, F, np.asarray(P, dtype=np.float64))


def element_stress_fields_by_body(model, x, P) -> list:
    """:func:`element_stress_fields` of every body of a ``Model.from_bodies`` model: a list of dicts
    in body order, from positions ``x`` (n, 3) and the first Piola-Kirchhoff stress ``P`` (Q, 3, 3) of
    all bodies' quadrature points in body order (``Simulator.stresses(x)``)."""
    import dataclasses

    x = np.asarray(x, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64)
    out, start = [], 0
    offs = model.body_offsets
    for b, (lo, hi) in enumerate(zip(offs[:-1], offs[1:])):
        lo, hi = int(lo), int(hi)
        if b >= len(model.quadratures):  # a rigid body (after the soft ones): undeformed, no stress
            mesh = model.bodies[b].mesh
            m = int(mesh.num_elements) or len(mesh.boundary_faces())  # its tets, or its triangles
            sigma = np.zeros((m, 3, 3))
            out.append({"J": np.ones(m), "cauchy_stress": sigma, "von_mises": np.zeros(m)})
            continue
        qd = model.quadratures[b]
        local = dataclasses.replace(qd, elements=np.asarray(qd.elements, dtype=np.int64) - lo, volumetric=None)
        view = _BodyView(local, model.rest_positions[lo:hi])
        F = deformation_gradients(view, x[lo:hi])
        out.append(_element_fields(local, F, P[start:start + qd.num_points]))
        start += qd.num_points
    return out


def _element_fields(qd, F, P) -> dict:
    """J, Cauchy stress and von Mises per element from F and P at the quadrature points of ``qd``."""
    J = np.linalg.det(F)
    tau = P @ np.swapaxes(F, 1, 2)  # Kirchhoff stress J sigma
    m = qd.num_elements
    el = np.asarray(qd.qp_element, dtype=np.int64)
    w = np.asarray(qd.qp_weight, dtype=np.float64)
    vol0 = np.bincount(el, weights=w, minlength=m)
    vol = np.bincount(el, weights=w * J, minlength=m)
    tau_e = np.zeros((m, 9))
    for c in range(9):
        tau_e[:, c] = np.bincount(el, weights=w * tau.reshape(-1, 9)[:, c], minlength=m)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = (tau_e / vol[:, None]).reshape(m, 3, 3)
    return {"J": vol / vol0, "cauchy_stress": sigma, "von_mises": von_mises(sigma)}


# ----------------------------------------------------------------------------- writer
class VtuSeriesWriter:
    """Write a mesh's frames to a ParaView collection ``path`` (``.pvd``) incrementally.

    Usage::

        w = VtuSeriesWriter("out/run.pvd", cells=mesh.elements, element_type="tet4")
        w.write_frame(0.0, x0, point_data={...}, cell_data={...})
        ...
        w.close(complete=True)

    Parameters
    ----------
    path : the ``.pvd`` file; parent folders are created; frames go to :func:`frame_directory` (stale
        ``frame_*.vtu`` files of a previous run there are removed).
    cells : (m, k) element node ids (VTK node order).
    element_type : "tet4", "tet10", "hex8" or "hex27".
    compression : meshio's VTU compression ("zlib", "lzma" or None).
    """

    def __init__(self, path, *, cells, element_type: str, compression: str | None = "zlib",
                 keep_frames: int | None = None):
        from warpfem.mesh.element_types import ELEMENTS

        path = os.fspath(path)
        if not path.lower().endswith(".pvd"):
            raise VtuWriterError(f"{path}: a ParaView collection must end in .pvd")
        if element_type not in ELEMENTS and element_type != "tri3":
            raise VtuWriterError(f"element_type must be one of {sorted(ELEMENTS)} or 'tri3', got {element_type!r}")
        # "tri3": a rigid body given by its closed surface (triangle cells)
        k = 3 if element_type == "tri3" else ELEMENTS[element_type].nodes_per_element
        cells = np.asarray(cells, dtype=np.int64)
        if cells.ndim == 1 and cells.size % k == 0:
            cells = cells.reshape(-1, k)
        if cells.ndim != 2 or cells.shape[1] != k or len(cells) == 0:
            raise VtuWriterError(f"cells must have shape (m, {k}) for {element_type}, got {cells.shape}")
        self.path = path
        self.cell_type = "triangle" if element_type == "tri3" else ELEMENTS[element_type].meshio_cell
        self.cells = cells
        self.num_points = int(cells.max()) + 1
        self.compression = compression
        self.frame_dir = frame_directory(path)
        os.makedirs(self.frame_dir, exist_ok=True)
        self.entries: list[tuple[float, str]] = []  # (time, file relative to the .pvd's folder)
        keep = set()
        if keep_frames is not None:  # continue a collection: its first keep_frames frames stay
            have = read_pvd(path)[0] if os.path.exists(path) else []
            if len(have) < keep_frames:
                raise VtuWriterError(f"{path}: cannot continue it: it lists {len(have)} frames, {keep_frames} needed")
            base = os.path.dirname(os.path.abspath(path))
            self.entries = [(t, os.path.relpath(f, base).replace(os.sep, "/")) for t, f in have[:keep_frames]]
            keep = {os.path.basename(f) for _, f in self.entries}
        for f in os.listdir(self.frame_dir):
            if (_FRAME_RE.match(f) and f not in keep) or f.endswith(".partial"):
                os.remove(os.path.join(self.frame_dir, f))
        self.closed = False
        self.version = warpfem_version()
        self._write_pvd(complete=False, reason="")

    @property
    def frames_written(self) -> int:
        return len(self.entries)

    def write_frame(self, time: float, points, *, point_data=None, cell_data=None):
        """Write the next frame: ``points`` (n, 3) current positions (m) at ``time`` (s); ``point_data`` /
        ``cell_data``: {name: (n, ...) / (m, ...) array}. Then rewrite the ``.pvd``."""
        import meshio

        if self.closed:
            raise VtuWriterError(f"{self.path}: writer is closed")
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < self.num_points:
            raise VtuWriterError(f"points must have shape (n >= {self.num_points}, 3), got {pts.shape}")
        pd, cd = {}, {}
        for name, a in (point_data or {}).items():
            a = np.asarray(a, dtype=np.float64)
            if len(a) != len(pts):
                raise VtuWriterError(f"point data {name!r} has {len(a)} rows, expected {len(pts)}")
            pd[name] = a.reshape(len(a), -1) if a.ndim > 2 else a
        for name, a in (cell_data or {}).items():
            a = np.asarray(a, dtype=np.float64)
            if len(a) != len(self.cells):
                raise VtuWriterError(f"cell data {name!r} has {len(a)} rows, expected {len(self.cells)}")
            cd[name] = [a.reshape(len(a), -1) if a.ndim > 2 else a]
        name = f"frame_{len(self.entries):06d}.vtu"
        target = os.path.join(self.frame_dir, name)
        mesh = meshio.Mesh(pts, [(self.cell_type, self.cells)], point_data=pd, cell_data=cd)
        tmp = target + ".partial"
        meshio.write(tmp, mesh, file_format="vtu", binary=True, compression=self.compression)
        os.replace(tmp, target)
        rel = os.path.relpath(target, os.path.dirname(os.path.abspath(self.path))).replace(os.sep, "/")
        self.entries.append((float(time), rel))
        self._write_pvd(complete=False, reason="")

    def _write_pvd(self, *, complete: bool, reason: str):
        meta = {"complete": bool(complete), "frames": len(self.entries), "version": self.version}
        if reason:
            meta["reason"] = reason
        comment = json.dumps(meta).replace("--", "- -")
        lines = ['<?xml version="1.0"?>',
                 '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
                 f"  <!-- warpfem {comment} -->",
                 "  <Collection>"]
        from xml.sax.saxutils import quoteattr  # here: it imports urllib, http and email

        lines += [f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(f)}/>' for t, f in self.entries]
        lines += ["  </Collection>", "</VTKFile>", ""]
        _write_text_atomic(self.path, "\n".join(lines))

    def close(self, *, complete: bool = True, reason: str = ""):
        """Mark the collection complete (or not, with ``reason``). Idempotent."""
        if self.closed:
            return
        self.closed = True
        self._write_pvd(complete=complete, reason="" if complete else str(reason))

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close(complete=exc_type is None, reason="" if exc is None else f"{exc_type.__name__}: {exc}")
        return False


class _BodyView:
    """One body of a multi-body model as :func:`deformation_gradients` reads a model (local indices)."""

    def __init__(self, qd, rest):
        self.quadrature, self.rest_positions = qd, rest


class VtuBodiesWriter:
    """Several bodies in one ParaView collection ``path`` (``.pvd``): one block per body, by name.

    Per frame the ``.pvd`` lists one ``<DataSet>`` per body (``part`` = body index, ``name`` = body
    name); body ``name``'s frames are ``<path>.vtu/<name>.vtu/frame_*.vtu`` (a per-body collection
    ``<path>.vtu/<name>.pvd`` is written beside them). Each block holds the body's own element type,
    points and the fields of :class:`VtuSeriesWriter`.

    bodies : [(name, cells (m, k) in the body's own vertex numbering, element_type, first vertex,
        end vertex)] in body order.
    """

    def __init__(self, path, *, bodies, compression: str | None = "zlib", keep_frames: int | None = None):
        path = os.fspath(path)
        if not path.lower().endswith(".pvd"):
            raise VtuWriterError(f"{path}: a ParaView collection must end in .pvd")
        self.path = path
        self.names = [b[0] for b in bodies]
        self.ranges = [(int(b[3]), int(b[4])) for b in bodies]
        folder = frame_directory(path)
        self.writers = [VtuSeriesWriter(os.path.join(folder, f"{name}.pvd"), cells=cells, element_type=etype,
                                        compression=compression, keep_frames=keep_frames)
                        for name, cells, etype, _, _ in bodies]
        self.version = warpfem_version()
        self.closed = False
        self._write_pvd(complete=False, reason="")

    @property
    def frames_written(self) -> int:
        return self.writers[0].frames_written

    def write_frame(self, time: float, points, *, point_data=None, cell_data=None):
        """Write the next frame of every body: ``points`` (n, 3) of all bodies, ``point_data`` {name:
        (n, ...)} over all bodies, ``cell_data`` [{name: (m_b, ...)} per body]."""
        for b, (w, (lo, hi)) in enumerate(zip(self.writers, self.ranges)):
            w.write_frame(time, np.asarray(points)[lo:hi],
                          point_data={k: np.asarray(a)[lo:hi] for k, a in (point_data or {}).items()},
                          cell_data=(cell_data or [{}] * len(self.writers))[b])
        self._write_pvd(complete=False, reason="")

    def _write_pvd(self, *, complete: bool, reason: str):
        meta = {"complete": bool(complete), "frames": self.frames_written, "version": self.version,
                "bodies": self.names}
        if reason:
            meta["reason"] = reason
        from xml.sax.saxutils import quoteattr

        comment = json.dumps(meta).replace("--", "- -")
        base = os.path.dirname(os.path.abspath(self.path))
        lines = ['<?xml version="1.0"?>',
                 '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
                 f"  <!-- warpfem {comment} -->",
                 "  <Collection>"]
        for k in range(self.frames_written):
            for part, (name, w) in enumerate(zip(self.names, self.writers)):
                t, f = w.entries[k]
                rel = os.path.relpath(os.path.join(os.path.dirname(os.path.abspath(w.path)), f), base).replace(os.sep, "/")
                lines.append(f'    <DataSet timestep="{t!r}" group="" part="{part}" name={quoteattr(name)} '
                             f'file={quoteattr(rel)}/>')
        lines += ["  </Collection>", "</VTKFile>", ""]
        _write_text_atomic(self.path, "\n".join(lines))

    def close(self, *, complete: bool = True, reason: str = ""):
        """Mark the collection (and each body's) complete, or not with ``reason``. Idempotent."""
        if self.closed:
            return
        self.closed = True
        for w in self.writers:
            w.close(complete=complete, reason=reason)
        self._write_pvd(complete=complete, reason="" if complete else str(reason))

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close(complete=exc_type is None, reason="" if exc is None else f"{exc_type.__name__}: {exc}")
        return False


class ParaViewOutput(FrameWriter):
    """``[output] vtu``: the volume mesh of every frame (one block per body) as a ParaView collection
    with its point data ``displacement``, ``velocity`` and cell data ``J``, ``von_mises``,
    ``cauchy_stress`` from the snapshot's ``element_fields``."""

    label = "[output] vtu"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        self._w = None

    def open(self, run):
        keep = None if run.resume_after is None else run.resume_after + 1
        self._rest = run.rest
        if len(run.blocks) == 1 and run.blocks[0][0] is None:
            _, cells, etype, _, _ = run.blocks[0]
            self._w = VtuSeriesWriter(self.path, cells=cells, element_type=etype, keep_frames=keep)
        else:
            self._w = VtuBodiesWriter(self.path, bodies=run.blocks, keep_frames=keep)

    def write(self, snapshot):
        x = snapshot.positions
        cells = [{"J": f["J"], "von_mises": f["von_mises"], "cauchy_stress": f["cauchy_stress"].reshape(-1, 9)}
                 for f in snapshot.element_fields]
        points = {"displacement": x - self._rest, "velocity": snapshot.velocities}
        if isinstance(self._w, VtuBodiesWriter):
            self._w.write_frame(snapshot.time, x, point_data=points, cell_data=cells)
        else:
            self._w.write_frame(snapshot.time, x, point_data=points, cell_data=cells[0])

    def close(self, complete, reason=None):
        if self._w is not None:
            self._w.close(complete=complete, reason=reason or "")

    def abandon(self):
        self._w = None


def read_pvd(path) -> tuple[list[tuple[float, str]], dict]:
    """``([(time, absolute .vtu path), ...], warpfem metadata)`` of a ``.pvd`` collection."""
    import xml.etree.ElementTree as ET

    path = os.fspath(path)
    with open(path, encoding="utf-8") as f:
        text = f.read()
    root = ET.fromstring(text)
    if root.tag != "VTKFile" or root.get("type") != "Collection":
        raise ValueError(f"{path}: not a VTK collection (.pvd)")
    base = os.path.dirname(os.path.abspath(path))
    entries = [(float(d.get("timestep")), os.path.normpath(os.path.join(base, d.get("file"))))
               for d in root.iter("DataSet")]
    m = _META_RE.search(text)
    meta = json.loads(m.group(1)) if m else {}
    return entries, meta
