"""Builders of the contact/friction scenes (docs/friction.md): incline, friction_chain, wheel.

``klann_walker`` (the six-leg walker with feet contact and joint friction) is in
scripts/klann/genwalker.py's output plus overrides; see scenes/klann.yaml.
"""
from __future__ import annotations

import math

from redmax_ros.core.scene.registry import int_param, register_builder, take


@register_builder("incline")
def incline(params: dict) -> dict:
    """A box on a free joint resting on a plane inclined by ``angle`` degrees about world y (the slope
    descends along +x), box contact (8 corners) against the plane with Coulomb coefficient ``mu``.
    Analytic: sticks when tan(angle) <= mu, else slides with a = g (sin - mu cos)."""
    p = take(params, dict(angle=30.0, mu=0.5, size=0.1, mass=1.0, v0=0.0, max_iter=100, tol=1e-7))
    th = math.radians(float(p["angle"]))
    s = float(p["size"])
    n = [math.sin(th), 0.0, math.cos(th)]
    t = [math.cos(th), 0.0, -math.sin(th)]  # down the slope
    c = [0.5 * s * v for v in n]
    v0 = float(p["v0"])
    return {
        "description": f"box on a {p['angle']} deg incline, mu = {p['mu']}",
        "bodies": [{"name": "block", "shape": {"type": "box", "size": [s, s, s]}, "mass": p["mass"]}],
        "joints": [{"name": "free", "type": "free", "parent": "world", "child": "block",
                    "q0": c + [0.0, th, 0.0], "v0": [v0 * t[0], 0.0, v0 * t[2], 0.0, 0.0, 0.0]}],
        "ground": [{"name": "slope", "normal": n, "offset": 0.0, "mu": p["mu"]}],
        "contacts": [{"name": "block", "body": "block", "type": "box", "size": [s, s, s]}],
        "friction": {"max_iter": p["max_iter"], "tol": p["tol"]},
        "sites": [{"name": "centre", "body": "block", "pos": [0, 0, 0]}],
    }


@register_builder("wheel")
def wheel(params: dict) -> dict:
    """A disc on a horizontal axle (revolute about y, at the disc's centre) with joint friction: the
    normal load is the weight, so the static friction torque is mu r sum|alpha| (docs/friction.md)."""
    p = take(params, dict(mass=2.0, disc_radius=0.1, mu=0.3, radius=0.01, length=0.02, points=8, q0=0.0,
                           torque=0.0))
    R = float(p["disc_radius"])
    m = float(p["mass"])
    return {
        "description": "disc on a frictional axle",
        "bodies": [{"name": "disc", "mass": m, "inertia": [m * R * R / 4, m * R * R / 2, m * R * R / 4, 0, 0, 0]}],
        "joints": [{"name": "axle", "type": "revolute", "axis": "y", "parent": "world", "child": "disc",
                    "q0": p["q0"], "torque": p["torque"],
                    "friction": {"mu": p["mu"], "radius": p["radius"], "length": p["length"],
                                 "points": int_param(p, "points", 3)}}],
    }


@register_builder("friction_chain")
def friction_chain(params: dict) -> dict:
    """The paper's CHAIN (Fig. 5a/b): ``n`` box links in a horizontal line (along +x) on revolute joints
    whose axes (0, sin tilt, cos tilt) are normal to the chain and at ``tilt`` degrees (45) from gravity,
    released from rest; every joint has friction ``mu`` on a pin cylinder of radius ``radius`` and length
    ``pin_length``. The gravity component along the axes loads the pins with bending moments that grow
    towards the root, so the root joints hold the most friction (Fig. 5a/b)."""
    p = take(params, dict(n=5, length=0.1, width=0.02, density=1000.0, tilt=45.0, mu=0.3, radius=0.001,
                           pin_length=0.004, points=8, damping=0.0))
    n = int_param(p, "n", 1)
    L, w = float(p["length"]), float(p["width"])
    a = math.radians(float(p["tilt"]))
    axis = [0.0, math.sin(a), math.cos(a)]  # normal to the chain (x), at `tilt` from gravity (-z)
    bodies, joints, sites = [], [], []
    for i in range(n):
        bodies.append({"name": f"link{i}", "shape": {"type": "box", "size": [L, w, w]}, "density": p["density"]})
        joints.append({
            "name": f"j{i}", "type": "revolute", "parent": "world" if i == 0 else f"link{i - 1}",
            "child": f"link{i}", "axis": axis, "placement": {"pos": [0 if i == 0 else L / 2, 0, 0]},
            "body_placement": {"pos": [L / 2, 0, 0]}, "damping": p["damping"],
            "friction": {"mu": p["mu"], "radius": p["radius"], "length": p["pin_length"],
                         "points": int_param(p, "points", 3)}})
        sites.append({"name": f"tip{i}", "body": f"link{i}", "pos": [L / 2, 0, 0]})
    return {"description": f"horizontal chain of {n} links, joint axes {p['tilt']} deg from gravity, joint friction",
            "bodies": bodies, "joints": joints, "sites": sites, "friction": {"max_iter": 100, "tol": 1e-7}}
