"""The paper's STARFISH (Wang et al. 2019, Fig. 1c and §4: "a skeleton of 20 joints in a coarse FEM mesh of
221 vertices", fully two-way coupled, hybrid dynamics): a free core and five arms, each a chain of
universal / revolute / universal / revolute joints (20 joints, 30 + 6 DOFs), inside a star-shaped
tetrahedral mesh built procedurally (deformable/meshes.box_tets on a grid, cells kept inside the star).
The first (universal) joint of every arm follows a periodic gait (a joint trajectory): a sine in its lift axis
(y, amplitude ``amplitude``, phase 2 pi a / 5 for arm a) and a sine in its sweep axis (z) leading the lift by
``lag`` [rad], of amplitude ``sweep`` times -sin(phi_a - heading) (the arm's tangent along the heading), so
that the arms push along ``heading`` in stance and their torques about the core cancel; ``sweep: 0`` is the
lift-only gait, which gaits in place. The rest of the skeleton and the mesh are passive. Mesh vertices inside
each bone's box (and the core's cylinder) are attached to it; the others are free FEM DOFs kept above the
floor by contacts with Coulomb friction ``mu`` (docs/deformables.md). Parameters: docs/deformables.md
"starfish".
"""
from __future__ import annotations

import math

import numpy as np

from redmax_ros.core.deformable import meshes
from redmax_ros.core.scene.deformable_schema import MAX_VERTICES
from redmax_ros.core.scene.registry import int_param, register_builder, take

DEFAULTS = {"radius": 0.25, "core": 0.05, "width": 0.06, "thickness": 0.04, "cell": 0.028, "layers": 1,
            "young": 5.0e4, "poisson": 0.3, "density": 1000.0, "beta": 0.005, "bone_density": 400.0,
            "amplitude": 0.35, "frequency": 0.5, "stiffness": 0.3, "damping": 0.02, "mu": 0.8,
            "sweep": 0.6, "lag": 0.75 * math.pi, "heading": 0.0}
TYPES = ("universal", "revolute", "universal", "revolute")


def star_mesh(radius, core, width, thickness, cell, layers, z0=0.0):
    """(vertices, tets) of a five-armed star: arms of half-width width/2 tapering to 40 % at the tip."""
    angles = [2 * math.pi * a / 5 for a in range(5)]
    dirs = np.array([[math.cos(a), math.sin(a)] for a in angles])

    def keep(c):
        p = c[:2]
        if np.linalg.norm(p) <= core:
            return True
        for d in dirs:
            s = float(p @ d)
            if 0.0 <= s <= radius and abs(d[0] * p[1] - d[1] * p[0]) <= 0.5 * width * (1 - 0.6 * s / radius):
                return True
        return False

    n = math.ceil(2 * radius / cell)
    if (n + 1) ** 2 * (int(layers) + 1) > MAX_VERTICES:  # before the grid is allocated
        raise ValueError(f"radius {radius:g} m / cell {cell:g} m gives a {n} x {n} x {int(layers)} cell grid, above "
                         f"{MAX_VERTICES} vertices")
    lo = np.array([-radius, -radius, z0 - thickness / 2])
    return meshes.box_tets(lo, np.array([2 * radius, 2 * radius, thickness]), (n, n, int(layers)), keep)


@register_builder("starfish")
def starfish(params: dict) -> dict:
    p = take(params, DEFAULTS)
    int_param(p, "layers", 1)
    R, r0, w, t = float(p["radius"]), float(p["core"]), float(p["width"]), float(p["thickness"])
    if not (0 < r0 < R and w > 0 and t > 0 and p["cell"] > 0):
        raise ValueError("need 0 < core < radius, width > 0, thickness > 0, cell > 0")
    z0 = t / 2 + 1e-3
    x, tets = star_mesh(R, r0, w, t, float(p["cell"]), p["layers"], z0=0.0)
    bodies = [{"name": "core", "shape": {"type": "cylinder", "radius": 0.9 * r0, "length": t + 0.002},
               "density": p["bone_density"]}]
    joints = [{"name": "root", "type": "free", "parent": "world", "child": "core", "q0": [0, 0, z0, 0, 0, 0]}]
    gait = {}
    ls = (R - r0) / len(TYPES)
    for a in range(5):
        phi = 2 * math.pi * a / 5
        parent, pos, rpy = "core", [r0 * math.cos(phi), r0 * math.sin(phi), 0.0], [0, 0, phi]
        for k, typ in enumerate(TYPES):
            body, jname = f"arm{a}_{k}", f"arm{a}_j{k}"
            s_mid = r0 + (k + 0.5) * ls
            wk = w * (1 - 0.6 * s_mid / R)
            bodies.append({"name": body, "shape": {"type": "box", "size": [0.8 * ls, 0.8 * wk, t + 0.002]},
                           "density": p["bone_density"]})
            j = {"name": jname, "type": typ, "parent": parent, "child": body, "placement": {"pos": pos, "rpy": rpy},
                 "body_placement": {"pos": [ls / 2, 0, 0]}, "stiffness": p["stiffness"], "damping": p["damping"]}
            if typ == "universal":
                j["axes"] = ["y", "z"]
            else:
                j["axis"] = "y"
            joints.append(j)
            parent, pos, rpy = body, [ls / 2, 0, 0], [0, 0, 0]
        # sweep (the universal joint's second axis, z): amplitude scaled by the arm's tangent along the heading,
        # so the strokes push along it and cancel in torque; it leads the lift by ``lag``
        c = float(p["sweep"]) * -math.sin(phi - float(p["heading"]))
        sweep = 0.0 if c == 0.0 else {"type": "sine", "amplitude": c, "frequency": p["frequency"],
                                      "phase": phi + float(p["lag"])}
        gait[f"arm{a}_j0"] = {"position": [{"type": "sine", "amplitude": p["amplitude"], "frequency": p["frequency"],
                                            "phase": phi}, sweep], "b": 5.0}
    attachments = [{"body": b["name"], "inside": True} for b in bodies]
    return {
        "name": "starfish",
        "description": f"STARFISH: 20 joints in a star tet mesh of {len(x)} vertices, periodic gait on the first joint of each arm",
        "bodies": bodies, "joints": joints,
        "prescribed": {"joints": gait},
        "deformables": [{"name": "body", "type": "fem",
                         "mesh": {"vertices": (x + [0, 0, z0]).tolist(), "tets": tets.tolist()},
                         "young": p["young"], "poisson": p["poisson"], "density": p["density"],
                         "rayleigh": {"alpha": 0.0, "beta": p["beta"]}, "attachments": attachments, "floor": 0.0,
                         "floor_mu": p["mu"]}],
    }
