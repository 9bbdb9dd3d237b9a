"""What the friction velocity eps_v and the adaptive barrier stiffness cost in accuracy: the 30
degree incline of tests/test_contact.py (a 0.1 m block dropped 1 cm, h = 0.01 s, mu = 0.8: motion
in the 0.5 s after landing; mu = 0.3: sliding acceleration against g (sin - mu cos)), with the
default eps_v, about 8x it (1e-2 body diagonals per second), stiffness = "auto", in float64 and
float32 (docs/contact.md, "Friction in float32").

    .venv/bin/python kernels_bench/incline_friction_velocity.py kernels_bench/results/adaptive_kappa/incline_friction_velocity.json
"""

import json
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from warpfem import Model, Plane, Simulator, TetMesh, box_tet_mesh, make_material  # noqa: E402

L, G = 0.1, 9.81
def drop(mu, theta, steps, epsv=None, stiffness=None, precision="float64"):
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    box = box_tet_mesh(size=(L, L, L), cells=(2, 2, 2), origin=(-0.5 * L, 0.01, -0.5 * L))
    mesh = TetMesh(np.asarray(box.vertices) @ R.T, box.tets)
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0), gravity=(0.0, -G, 0.0))
    t = -R[:, 0]
    sim = Simulator(m, dt=0.01, max_iters=200, precision=precision,
                    colliders=[Plane(point=(0, 0, 0), normal=R[:, 1], friction=mu, friction_velocity=epsv, stiffness=stiffness)])
    Mv = m.lumped_mass / m.lumped_mass.sum()
    pos, vel, land, newton, bad = [], [], None, 0, 0
    for k in range(steps):
        st = sim.step(); newton += st.newton_iterations; bad += not st.converged
        pos.append(float((Mv[:, None] * sim.positions()).sum(axis=0) @ t)); vel.append(float((Mv[:, None] * sim.velocities()).sum(axis=0) @ t))
        if land is None and sim.contact.distances().min() < sim.contact.dhat[0]: land = k
    return np.array(pos), np.array(vel), land, newton / steps, bad, float(sim.contact.epsv[0])
th = math.radians(30)
out = {"device": "cpu (x86_64), 2 cores shared with other jobs"}
for name, kw in (("default", {}), ("epsv_x10", {"epsv": "x10"}), ("auto", {"stiffness": "auto"}), ("default_f32", {"precision": "float32"}), ("epsv_x10_f32", {"epsv": "x10", "precision": "float32"})):
    kw = dict(kw)
    if kw.get("epsv") == "x10":
        kw["epsv"] = 10 * 1e-3 * float(np.linalg.norm([L, L, L]))
    p, _, land, n1, b1, ev = drop(0.8, th, 56, **kw)
    _, v, land2, n2, b2, _ = drop(0.3, th, 40, **kw)
    a = (v[land2 + 30] - v[land2 + 10]) / 0.2
    ref = G * (math.sin(th) - 0.3 * math.cos(th))
    out[name] = {"eps_v": ev, "stick_motion_mm": 1e3 * abs(p[land + 50] - p[land]), "slide_accel_error_pct": 100 * (a / ref - 1),
                 "newton_per_step": [n1, n2], "not_converged": [b1, b2]}
    print(name, out[name], flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
