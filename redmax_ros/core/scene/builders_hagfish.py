"""The paper's HAGFISH (Fig. 3, §6): ``builder: hagfish`` (scenes/hagfish.yaml, docs/collisions.md).

    "We model the animal by placing Z-revolute and XY-universal joints in an alternating fashion, for a
    total of 100 joints. We set the length, mass, radii, and joint limits with data taken from real
    measurements [Evans et al. 2018]. ... The collisions are turned into inequality constraints,
    resulting in a quadratic program (Eq. (5)). We do not model friction, since hagfish are slimy."

The measurements of Evans, Hwang, Sueda and Uyeno 2018 (SICB abstract, "Estimating Whole Body
Flexibility in Pacific Hagfish") are not reproduced in the paper and not available here, so the values
are plausible ones for an adult Pacific hagfish (Eptatretus stoutii, ~0.5 m, ~0.15 kg), stated with
their assumptions (all SI):

* ``length`` 0.45 m of body behind a ``head_length`` 0.05 m head; the head is fixed to the world inside
  the jar (a cylindrical shell obstacle, ``jar_*``), the body leaves the jar mouth along +x at height
  ``height`` above a floor plane;
* ``n`` = 100 segments on 100 joints: segment i (0 = behind the head) on a Z revolute joint for even i,
  an XY universal joint for odd i (150 DOFs); segment lengths taper linearly from ``seg_taper[0]`` to
  ``seg_taper[1]`` times the mean length (body + tail: the tail is slender);
* radius tapers from ``radius_head`` 0.011 m to ``radius_tail`` 0.004 m (a round body ~2.2 cm thick);
  capsules (the body shape) of cylinder length = segment length;
* mass from density 1050 kg/m^3 (fish tissue) over each segment's cylinder slice (0.09 kg of body, 0.12 kg
  with the head);
* joint limits taper from ``limit_head`` 0.20 rad to ``limit_tail`` 0.45 rad per joint axis (hagfish can
  bend to a radius of a few body widths; the knotting tail is the most flexible part); joint stiffness
  ``stiffness`` N m/rad and damping ``damping`` N m s/rad per DOF (a soft, damped body);
* self-collision: every pair of segments more than ``skip`` apart along the body (nearer ones overlap by
  construction: radius > segment length) plus the floor and the jar; margin ``margin``.

A tip site ``tail_tip`` (end of the last segment) and sites ``s<i>`` every 10 segments for procedural
driving (prescribed site velocities, redmax_bench/hagfish.py).
"""
from __future__ import annotations

import math

from redmax_ros.core.scene.registry import bool_param, int_param, register_builder, take


@register_builder("hagfish")
def hagfish(params: dict) -> dict:
    p = take(params, dict(n=100, length=0.45, head_length=0.05, radius_head=0.011, radius_tail=0.004,
                           seg_taper=[1.2, 0.8], density=1050.0, limit_head=0.20, limit_tail=0.45,
                           stiffness=2e-3, damping=2e-4, height=0.12, jar_radius=0.0125, jar_length=0.07,
                           jar_thickness=0.003, margin=0.003, skip=None, floor=True))
    n = int_param(p, "n", 2)
    Lb, r0, r1 = float(p["length"]), float(p["radius_head"]), float(p["radius_tail"])
    ta, tb = (float(x) for x in p["seg_taper"])
    if not (r0 > 0 and r1 > 0 and Lb > 0 and ta > 0 and tb > 0):
        raise ValueError("'length', radii and 'seg_taper' must be positive")
    u = [i / max(n - 1, 1) for i in range(n)]
    w = [ta + (tb - ta) * x for x in u]
    seg = [Lb * wi / sum(w) for wi in w]  # segment lengths [m], sum = length
    rad = [r0 + (r1 - r0) * x for x in u]
    lim = [float(p["limit_head"]) + (float(p["limit_tail"]) - float(p["limit_head"])) * x for x in u]
    skip = None if p["skip"] is None else int_param(p, "skip", 1, n)
    if skip is None:  # segments whose capsules overlap in the straight body (centres nearer than 2 r)
        skip = max(1, max(math.ceil(2.0 * r / l) for r, l in zip(rad, seg)) + 1)
    skip = int(skip)
    hl, z = float(p["head_length"]), float(p["height"])
    # the head: fixed in the jar, its capsule along x ending at the jar mouth (x = 0)
    bodies = [{"name": "head", "shape": {"type": "capsule", "radius": r0, "length": hl}, "density": p["density"]}]
    joints = [{"name": "jar_grip", "type": "fixed", "parent": "world", "child": "head",
               "placement": {"pos": [-hl / 2, 0, z], "rpy": [0, math.pi / 2, 0]}}]
    sites = []
    exclude = []
    for i in range(n):
        name = f"seg{i}"
        # mass of the body's own slice (a cylinder of the segment length: the capsules' hemispheres overlap
        # their neighbours), inertia from the capsule shape with that mass
        bodies.append({"name": name, "shape": {"type": "capsule", "radius": rad[i], "length": seg[i]},
                       "mass": float(p["density"]) * math.pi * rad[i] ** 2 * seg[i]})
        parent = "head" if i == 0 else f"seg{i - 1}"
        off = hl / 2 if i == 0 else seg[i - 1] / 2
        j = {"name": f"j{i}", "parent": parent, "child": name, "placement": {"pos": [0, 0, off]},
             "body_placement": {"pos": [0, 0, seg[i] / 2]}, "stiffness": p["stiffness"], "damping": p["damping"]}
        if i % 2 == 0:  # Z revolute (about the body's local x after the head's pitch: the world's vertical z)
            j.update(type="revolute", axis="x", limits={"lower": -lim[i], "upper": lim[i]})
        else:  # XY universal
            j.update(type="universal", axes=["x", "y"], limits={"lower": -lim[i], "upper": lim[i]})
        joints.append(j)
        if i % 10 == 9:
            sites.append({"name": f"s{i}", "body": name, "pos": [0, 0, 0]})
        for k in range(max(0, i - skip), i):
            exclude.append([f"seg{k}", name])
        if i < skip:
            exclude.append(["head", name])
    sites.append({"name": "tail_tip", "body": f"seg{n - 1}", "pos": [0, 0, seg[-1] / 2]})
    obstacles = [{"name": "jar", "type": "shell", "radius": float(p["jar_radius"]), "length": float(p["jar_length"]),
                  "thickness": float(p["jar_thickness"]), "segments": 16,
                  "pos": [-float(p["jar_length"]) / 2 + 0.005, 0, z], "rpy": [0, math.pi / 2, 0]}]
    if bool_param(p, "floor"):
        obstacles.append({"name": "floor", "type": "plane", "normal": [0, 0, 1], "offset": 0.0})
    return {"bodies": bodies, "joints": joints, "sites": sites,
            "collision": {"margin": float(p["margin"]), "exclude": exclude, "obstacles": obstacles}}
