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

__all__ = ["VtuSeriesWriter", "VtuBodiesWriter", "VtuWriterError", "read_pvd", "frame_directory", "deformation_gradients",
           "element_stress_fields", "von_mises", "warpfem_version"]

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


def _pk1(sim, model, x, F):
    """First Piola-Kirchhoff stress (Q, 3, 3) at the main quadrature points, from whatever the simulator offers."""
    if hasattr(sim, "stresses"):  # warpfem.Simulator: the material on the device
        return np.asarray(sim.stresses(np.asarray(x, dtype=np.float64)), dtype=np.float64)
    if hasattr(sim, "rotations"):  # stiffness warping: corotational linear stress P = R (2 mu e + lam tr(e) I)
        mat = model.material
        R = np.asarray(sim.rotations(np.asarray(x, dtype=np.float64)), dtype=np.float64)
        R = R[np.asarray(model.quadrature.qp_element, dtype=np.int64)]
        G = np.einsum("qji,qjk->qik", R, F) - np.eye(3)  # R^T F - I
        e = 0.5 * (G + np.swapaxes(G, 1, 2))
        s = 2.0 * mat.mu_lame * e + mat.lam_lame * np.trace(e, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        return R @ s
    return np.asarray(model.material.pk1(F), dtype=np.float64)  # e.g. the reduced simulator: the full material


def element_stress_fields(sim, model, x=None) -> dict:
    """Per-element ``J`` (m,), ``cauchy_stress`` (m, 3, 3) and ``von_mises`` (m,) at positions x (default the
    simulator's current positions).

    The first Piola-Kirchhoff stress P comes from ``sim.stresses()`` (:class:`warpfem.Simulator`: the
    material at its quadrature points), from the corotational linear stress R (2 mu e + lam tr(e) I),
    e = sym(R^T F) - I, with the simulator's element rotations (stiffness warping), or else from the
    model's material evaluated at F (e.g. the reduced simulator, at the reconstructed positions).
    Cauchy sigma = P F^T / J. With w_q the rest-volume quadrature weights of an element:
    J_e = sum w_q J_q / sum w_q (deformed / rest volume) and sigma_e = sum w_q J_q sigma_q / sum w_q J_q
    (the deformed-volume mean of the Cauchy stress); von Mises from sigma_e.
    """
    x = sim.positions() if x is None else np.asarray(x, dtype=np.float64)
    F = deformation_gradients(model, x)
    return _element_fields(model.quadrature, F, _pk1(sim, model, x, F))


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

    def __init__(self, path, *, cells, element_type: str, compression: str | None = "zlib"):
        from warpfem.mesh.element_types import ELEMENTS

        path = os.fspath(path)
        if not path.lower().endswith(".pvd"):
            raise VtuWriterError(f"{path}: a ParaView collection must end in .pvd")
        if element_type not in ELEMENTS:
            raise VtuWriterError(f"element_type must be one of {sorted(ELEMENTS)}, got {element_type!r}")
        element = ELEMENTS[element_type]
        k = element.nodes_per_element
        cells = np.asarray(cells, dtype=np.int64)
        if cells.ndim == 1 and cells.size % k == 0:
            cells = cells.reshape(-1, k)
        if cells.ndim != 2 or cells.shape[1] != k or len(cells) == 0:
            raise VtuWriterError(f"cells must have shape (m, {k}) for {element_type}, got {cells.shape}")
        self.path = path
        self.cell_type = element.meshio_cell
        self.cells = cells
        self.num_points = int(cells.max()) + 1
        self.compression = compression
        self.frame_dir = frame_directory(path)
        os.makedirs(self.frame_dir, exist_ok=True)
        for f in os.listdir(self.frame_dir):
            if _FRAME_RE.match(f) or f.endswith(".partial"):
                os.remove(os.path.join(self.frame_dir, f))
        self.entries: list[tuple[float, str]] = []  # (time, file relative to the .pvd's folder)
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

    def write_state(self, time: float, sim, model):
        """Write a frame of a simulator's state: positions, displacement, velocity and the element fields
        of :func:`element_stress_fields`."""
        x = np.asarray(sim.positions(), dtype=np.float64)
        v = np.asarray(sim.velocities(), dtype=np.float64) if hasattr(sim, "velocities") else np.zeros_like(x)
        fields = element_stress_fields(sim, model, x)
        self.write_frame(time, x, point_data={"displacement": x - model.rest_positions, "velocity": v},
                         cell_data={"J": fields["J"], "von_mises": fields["von_mises"],
                                    "cauchy_stress": fields["cauchy_stress"].reshape(-1, 9)})

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

    def __init__(self, path, *, bodies, compression: str | None = "zlib"):
        path = os.fspath(path)
        if not path.lower().endswith(".pvd"):
            raise VtuWriterError(f"{path}: a ParaView collection must end in .pvd")
        self.path = path
        self.names = [b[0] for b in bodies]
        self.ranges = [(int(b[3]), int(b[4])) for b in bodies]
        folder = frame_directory(path)
        self.writers = [VtuSeriesWriter(os.path.join(folder, f"{name}.pvd"), cells=cells, element_type=etype,
                                        compression=compression) for name, cells, etype, _, _ in bodies]
        self.version = warpfem_version()
        self.closed = False
        self._write_pvd(complete=False, reason="")

    @property
    def frames_written(self) -> int:
        return self.writers[0].frames_written

    def write_state(self, time: float, sim, model):
        """Write a frame of every body: positions, displacement, velocity and the element fields of
        :func:`element_stress_fields` (``model``: a ``Model.from_bodies`` model)."""
        x = np.asarray(sim.positions(), dtype=np.float64)
        v = np.asarray(sim.velocities(), dtype=np.float64) if hasattr(sim, "velocities") else np.zeros_like(x)
        P_all = np.asarray(sim.stresses(x), dtype=np.float64) if hasattr(sim, "stresses") else None
        start = 0
        import dataclasses

        for b, (w, (lo, hi)) in enumerate(zip(self.writers, self.ranges)):
            qd = model.quadratures[b]
            local = dataclasses.replace(qd, elements=np.asarray(qd.elements, dtype=np.int64) - lo, volumetric=None)
            view = _BodyView(local, model.rest_positions[lo:hi])
            xb = x[lo:hi]
            F = deformation_gradients(view, xb)
            if P_all is not None:
                P = P_all[start:start + qd.num_points]
            else:
                P = np.asarray(model.materials[b].pk1(F), dtype=np.float64)
            start += qd.num_points
            fields = _element_fields(local, F, P)
            w.write_frame(time, xb, point_data={"displacement": xb - view.rest_positions, "velocity": v[lo:hi]},
                          cell_data={"J": fields["J"], "von_mises": fields["von_mises"],
                                     "cauchy_stress": fields["cauchy_stress"].reshape(-1, 9)})
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
