"""Write the closed surfaces of the contact example scenes (our own shapes, same licence as warpfem):

* ``ball.obj``: a sphere of radius 0.1 m centred at the origin (an icosphere: 642 vertices);
* ``bowl.obj``: a hemispherical bowl, outer radius 0.3 m, wall 0.04 m thick, its rim in the plane
  z = 0 and its bottom at z = -0.3 m (outer and inner caps of 24 rings x 48 segments and the rim).

Both are watertight with outward normals; scenes tetrahedralise them on load (TetGen, the ``mesh``
extra). Run ``python examples/meshes/make_shapes.py`` to write them again (deterministic).
"""

from __future__ import annotations

import os

import numpy as np

from warpfem.mesh import icosphere_surface

HERE = os.path.dirname(os.path.abspath(__file__))


def bowl(outer: float, wall: float, rings: int, segments: int):
    """Outer cap (outward normals pointing away from the centre), inner cap (pointing to the
    centre, i.e. out of the solid wall) and the flat rim between them at z = 0."""
    inner = outer - wall
    verts, faces = [], []

    def cap(radius):
        start = len(verts)
        verts.append((0.0, 0.0, -radius))  # the pole
        for i in range(1, rings + 1):
            polar = 0.5 * np.pi * i / rings  # 0 at the bottom pole, pi/2 at the rim
            for j in range(segments):
                az = 2.0 * np.pi * j / segments
                verts.append((radius * np.sin(polar) * np.cos(az), radius * np.sin(polar) * np.sin(az),
                              -radius * np.cos(polar)))
        return start

    def ring(start, i, j):  # vertex j of ring i (1-based rings) of a cap
        return start + 1 + (i - 1) * segments + (j % segments)

    o, n = cap(outer), cap(inner)
    for s, flip in ((o, False), (n, True)):
        for j in range(segments):
            tri = (s, ring(s, 1, j + 1), ring(s, 1, j))  # seen from below: outward for the outer cap
            faces.append(tri[::-1] if flip else tri)
        for i in range(1, rings):
            for j in range(segments):
                a, b = ring(s, i, j), ring(s, i, j + 1)
                c, d = ring(s, i + 1, j), ring(s, i + 1, j + 1)
                for tri in ((a, b, d), (a, d, c)):
                    faces.append(tri[::-1] if flip else tri)
    for j in range(segments):  # the rim, facing +z
        a, b = ring(o, rings, j), ring(o, rings, j + 1)
        c, d = ring(n, rings, j), ring(n, rings, j + 1)
        faces += [(a, b, d), (a, d, c)]
    return np.array(verts), np.array(faces, dtype=np.int64)


def write_obj(path, verts, faces):
    with open(path, "w") as f:
        f.write(f"# {os.path.basename(path)}: written by make_shapes.py (warpfem)\n")
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in verts)
        f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)


def _check_closed_outward(verts, faces):
    edges = {}
    for a, b, c in faces:
        for e in ((a, b), (b, c), (c, a)):
            edges[e] = edges.get(e, 0) + 1
    assert all(edges.get((b, a), 0) == 1 and k == 1 for (a, b), k in edges.items()), "not a closed oriented surface"
    p = verts[faces]
    volume = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0
    assert volume > 0.0, "normals point inward"
    return volume


if __name__ == "__main__":
    for name, (v, f) in {"ball.obj": icosphere_surface(0.1, 3), "bowl.obj": bowl(0.3, 0.04, 24, 48)}.items():
        vol = _check_closed_outward(v, f)
        write_obj(os.path.join(HERE, name), v, f)
        print(f"{name}: {len(v)} vertices, {len(f)} triangles, volume {vol:.6f} m^3")
