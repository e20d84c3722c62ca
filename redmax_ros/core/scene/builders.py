"""Parametric scene builders (``builder: NAME`` + ``params:`` in a scene file).

Each builder maps a parameter dict to a scene dict of the schema in docs/scenes.md, so the result
goes through the same validation as a hand-written file. Unknown parameters are rejected.
"""
from __future__ import annotations

import math

from redmax_ros.core.scene.registry import bool_param, int_param, register_builder, take


@register_builder("chain")
def chain(params: dict) -> dict:
    """n box links hanging along -z from revolute joints about ``axis`` (tree: a serial chain).

    ``springs`` maximal springs brace link k's tip to link k+2's tip (k = 0, 1, ...), rest length
    = initial distance: they stiffen the chain and couple non-adjacent bodies (breaking the tree
    structure of Eq. 2's LHS, as maximal springs do in the paper's BRIDGE).
    """
    p = take(params, dict(n=5, length=0.1, width=0.02, density=1000.0, axis="y", q0=0.5, q0_rest=0.0,
                           joint_damping=0.0, joint_stiffness=0.0, springs=0, spring_k=100.0, spring_d=0.0,
                           spring_rest=None))
    n, m = int_param(p, "n", 1), int_param(p, "springs", 0)
    L, w = float(p["length"]), float(p["width"])
    bodies, joints, sites, springs = [], [], [], []
    for i in range(n):
        bodies.append({"name": f"link{i}", "shape": {"type": "box", "size": [w, w, L]}, "density": p["density"]})
        joints.append({
            "name": f"j{i}", "type": "revolute", "parent": "world" if i == 0 else f"link{i - 1}",
            "child": f"link{i}", "axis": p["axis"],
            "placement": {"pos": [0, 0, 0 if i == 0 else -L / 2]},
            "body_placement": {"pos": [0, 0, -L / 2]},
            "q0": p["q0"] if i == 0 else p["q0_rest"],
            "damping": p["joint_damping"], "stiffness": p["joint_stiffness"],
        })
        sites.append({"name": f"tip{i}", "body": f"link{i}", "pos": [0, 0, -L / 2]})
    if m > max(n - 2, 0):
        raise ValueError(f"'springs' = {m} needs n >= springs + 2 (n = {n})")
    for k in range(m):
        s = {"name": f"brace{k}", "a": f"tip{k}", "b": f"tip{k + 2}", "stiffness": p["spring_k"],
             "damping": p["spring_d"]}
        if p["spring_rest"] is not None:
            s["rest_length"] = p["spring_rest"]
        springs.append(s)
    return {"bodies": bodies, "joints": joints, "sites": sites, "springs": springs}


@register_builder("mass_springs")
def mass_springs(params: dict) -> dict:
    """``n`` boxes on free joints, each hung from world anchors by two springs and tied to its
    neighbour by a spring: every force is a maximal (point-to-point) spring.

    ``attach: center`` (default) fixes the springs at the box centres (forces through the COM);
    ``attach: corners`` at the top corners, which couples rotation to the springs.
    """
    p = take(params, dict(n=3, k=1000.0, d=0.0, mass=1.0, size=0.1, spacing=0.3, drop=0.05, attach="center"))
    if p["attach"] not in ("corners", "center"):
        raise ValueError(f"'attach' must be 'corners' or 'center', got {p['attach']!r}")
    dz = 0.0 if p["attach"] == "center" else None
    n = int_param(p, "n", 1)
    s, sp = float(p["size"]), float(p["spacing"])
    bodies, joints, sites, springs = [], [], [], []
    for i in range(n):
        x = i * sp
        bodies.append({"name": f"box{i}", "shape": {"type": "box", "size": [s, s, s]}, "mass": p["mass"]})
        # start slightly below the spring rest position so the system oscillates
        joints.append({"name": f"free{i}", "type": "free", "parent": "world", "child": f"box{i}",
                       "q0": [x, 0.0, -p["drop"] * (1 + 0.5 * i), 0.05 * i, 0.0, 0.1 * i]})
        for side, dx in (("l", -s / 2), ("r", s / 2)):
            local = [0.0, 0.0, 0.0] if dz is not None else [dx, 0, s / 2]
            sites.append({"name": f"box{i}_{side}", "body": f"box{i}", "pos": local})
            sites.append({"name": f"anchor{i}_{side}", "body": "world", "pos": [x + dx, 0, 0.3]})
            springs.append({"name": f"hang{i}_{side}", "a": f"box{i}_{side}", "b": f"anchor{i}_{side}",
                            "stiffness": p["k"], "damping": p["d"], "rest_length": 0.25})
        if i:
            springs.append({"name": f"tie{i - 1}_{i}", "a": f"box{i - 1}_r", "b": f"box{i}_l",
                            "stiffness": p["k"], "damping": p["d"], "rest_length": sp - s})
    return {"bodies": bodies, "joints": joints, "sites": sites, "springs": springs}


_FINGERS = {  # name: (y offset on the palm [m], phalanx lengths proximal/middle/distal [m])
    "index": (0.030, (0.045, 0.025, 0.020)),
    "middle": (0.010, (0.050, 0.030, 0.022)),
    "ring": (-0.010, (0.047, 0.028, 0.021)),
    "little": (-0.030, (0.035, 0.020, 0.018)),
}


@register_builder("hand")
def hand(params: dict) -> dict:
    """Forearm, palm, four fingers (MCP universal, PIP and DIP revolute with DIP coupled to PIP at 1:2
    by hyper-reduced coordinates, Eq. 8) and a thumb (CMC universal, MCP, IP), as the paper's HAND.

    Reduced DOFs: elbow 1 + wrist 2 + 4 x (2 + 1 + 1) + thumb 4 = 23; hyper-reduced: 19.
    The forearm lies along +x from the elbow (axis y); fingers point along +x and flex about y.
    """
    p = take(params, dict(ratio=2.0, finger_damping=0.002, finger_stiffness=0.02, wrist_damping=0.05,
                           elbow_damping=0.1, density=1100.0, mcp=0.3, pip=0.6, limits=True))
    r = float(p["ratio"])
    if r == 0:
        raise ValueError("'ratio' must be non-zero")
    lim = bool_param(p, "limits")
    fd, fk = p["finger_damping"], p["finger_stiffness"]
    bodies = [
        {"name": "forearm", "shape": {"type": "box", "size": [0.25, 0.06, 0.04]}, "mass": 1.2},
        {"name": "palm", "shape": {"type": "box", "size": [0.10, 0.08, 0.025]}, "mass": 0.4},
    ]
    joints = [
        {"name": "elbow", "type": "revolute", "parent": "world", "child": "forearm", "axis": "y",
         "body_placement": {"pos": [0.125, 0, 0]}, "damping": p["elbow_damping"]},
        {"name": "wrist", "type": "universal", "parent": "forearm", "child": "palm", "axes": ["y", "z"],
         "placement": {"pos": [0.125, 0, 0]}, "body_placement": {"pos": [0.05, 0, 0]},
         "damping": p["wrist_damping"], "stiffness": 0.5,
         **({"limits": {"lower": [-1.2, -0.5], "upper": [1.2, 0.5]}} if lim else {})},
    ]
    sites, couplings = [], []
    w = 0.016
    for fname, (y, lengths) in _FINGERS.items():
        segs = ["prox", "mid", "dist"]
        parent, ppos = "palm", [0.05, y, 0]
        for k, (seg, L) in enumerate(zip(segs, lengths)):
            body = f"{fname}_{seg}"
            bodies.append({"name": body, "shape": {"type": "box", "size": [L, w, w]}, "density": p["density"]})
            jname = f"{fname}_{['mcp', 'pip', 'dip'][k]}"
            j = {"name": jname, "parent": parent, "child": body, "placement": {"pos": ppos},
                 "body_placement": {"pos": [L / 2, 0, 0]}, "damping": fd, "stiffness": fk}
            if k == 0:
                j.update(type="universal", axes=["y", "z"], q0=[p["mcp"], 0.0])
                if lim:
                    j["limits"] = {"lower": [-0.6, -0.4], "upper": [1.6, 0.4]}
            else:
                j.update(type="revolute", axis="y", q0=p["pip"] if k == 1 else p["pip"] / r)
                if lim and k == 1:
                    j["limits"] = {"lower": -0.3, "upper": 2.0}
            joints.append(j)
            parent, ppos = body, [L / 2, 0, 0]
        sites.append({"name": f"{fname}_tip", "body": f"{fname}_dist", "pos": [lengths[2] / 2, 0, 0]})
        couplings.append({"name": f"{fname}_pip_dip", "joints": [f"{fname}_pip", f"{fname}_dip"],
                          "ratios": [r, 1.0]})
    # thumb: CMC at the palm's side, pointing forward-outward
    tl = (0.040, 0.032, 0.025)
    parent, ppos, rpy = "palm", [-0.02, 0.045, 0], [0, 0, math.radians(50)]
    for k, (seg, L) in enumerate(zip(["meta", "prox", "dist"], tl)):
        body = f"thumb_{seg}"
        bodies.append({"name": body, "shape": {"type": "box", "size": [L, w, w]}, "density": p["density"]})
        jname = ["thumb_cmc", "thumb_mcp", "thumb_ip"][k]
        j = {"name": jname, "parent": parent, "child": body, "placement": {"pos": ppos, "rpy": rpy},
             "body_placement": {"pos": [L / 2, 0, 0]}, "damping": fd, "stiffness": fk}
        if k == 0:
            j.update(type="universal", axes=["y", "z"], q0=[0.3, 0.2])
        else:
            j.update(type="revolute", axis="y", q0=0.3 if k == 1 else 0.2)
        joints.append(j)
        parent, ppos, rpy = body, [L / 2, 0, 0], [0, 0, 0]
    sites.append({"name": "thumb_tip", "body": "thumb_dist", "pos": [tl[2] / 2, 0, 0]})
    sites.append({"name": "palm_center", "body": "palm", "pos": [0, 0, 0]})
    tips = [f"{f}_tip" for f in _FINGERS] + ["thumb_tip"]
    return {
        "bodies": bodies, "joints": joints, "sites": sites, "couplings": couplings,
        "prescribable": {"joints": ["elbow", "wrist"], "sites": tips},
    }
