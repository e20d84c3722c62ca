"""Parametric scaling scenes of the paper's Table 2 (§6): BRIDGE and UMBRELLA.

Both are built from the ordinary scene schema (bodies, joints, sites, maximal ``springs``,
site-to-site ``loops``) so they go through the same validation as a hand-written file; the DOF
count is set by parameters, spanning the paper's Table 2.

``bridge`` (cable-stayed fan bridge, Fig. 1a/4a)
    x along the bridge, z up, y across. The deck (length ``span``, from x = 0 to x = span, at
    z = 0) is a chain of ``n_deck`` box pieces on revolute joints about y: the first piece is
    pinned to the ground at x = 0 by its root joint, the far end is grounded at x = span by a
    2-row loop closure (rows x, z; a y row would be redundant with the planar deck joints and is
    rejected by the loop rank check). Joint stiffness EI/l and damping model the deck's bending.
    The deck is cambered (pieces on a circular arc of rise ``camber``, its stress-free shape).
    Two towers stand at x = span/4 and 3 span/4; every deck piece within ``fan`` of a tower (and
    not closer than 0.05 span) gets two cables (one per deck side, y = +-width/2) to that tower, a
    semi-fan: the longest cables reach the tower top, shorter ones anchor lower, over the top
    ``anchor_spread`` fraction of the tower height (0 = pure fan, every cable at the top). Cables are
    maximal point-to-point springs with stiffness ``cable_k`` x (piece length) / 2 per cable (N/m per
    metre of deck), rest length = initial length.

    * ``variant: rigid``: towers are infinitely stiff, i.e. fixed bodies (merged into the world):
      every cable joins one deck body to the world, so the maximal stiffness matrix is block
      diagonal over bodies and the Projected Block Jacobi Preconditioner is the exact inverse of
      the LHS (the paper's single PCG iteration). DOF = n_deck, default 80 x ``scale``.
    * ``variant: flexy``: each tower is a chain of ``n_tower`` pieces on revolute joints about y
      with joint stiffness EI_t/l (flexible towers), the cables hang from the tower pieces at
      their anchor heights and the deck is ``weight`` times heavier (exaggerated weight).
      DOF = n_deck + 2 n_tower, default 40 x scale + 2 x 10 x scale = 60 x scale.

    ``scale`` 1, 2, 4, 8, 16 gives Table 2's DOF: rigid 80 ... 1280, flexy 60 ... 960.

``umbrella`` (deployable umbrella, Fig. 1b/4b)
    The tube (root body, fixed to the world) stands along z with its tip at z = 1 m. Eight ribs
    hang from the tip and eight stretchers from the runner, a body on a prismatic joint along the
    tube (joint spring holding it at its initial height). Ribs and stretchers are chains of
    ``ribs`` / ``stretchers`` bodies on universal joints (bending stiffness EI/l); each stretcher's
    tip is tied to a point on its rib by a 3-row site-to-site loop closure (bilateral
    constraint), and canopy springs join the tips of corresponding pieces of neighbouring ribs.
    DOF = 1 + 16 (ribs + stretchers); ribs = 10, 16, 22, 32, 46 with stretchers = ribs // 2 gives
    241, 385, 529, 769, 1105 (Table 2's 241 ... 1105).
"""
from __future__ import annotations

import math

from redmax_ros.core.scene.files import MAX_BODIES
from redmax_ros.core.scene.registry import int_param, register_builder, take
from redmax_ros.core.scene.spec import numeric


def _num(p, key, positive=True):
    v = numeric(p[key])  # YAML 1.1 reads 5e9 (no dot) as a string
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise ValueError(f"'{key}' must be a {'positive ' if positive else ''}number, got {v!r}")
    return float(v)


@register_builder("bridge")
def bridge(params: dict) -> dict:
    p = take(params, dict(variant="rigid", scale=1, n_deck=None, n_tower=None, span=60.0, camber=1.0, width=4.0,
                           thickness=0.5, density=2500.0, weight=4.0, deck_EI=2.0e8, deck_damping=2.0e5,
                           tower_height=28.0, tower_base=-10.0, tower_density=2500.0, tower_EI=2.0e10, tower_damping=2.0e6,
                           cable_k=1.0e6, cable_d=1.0e4, fan=None, anchor_spread=0.3))
    variant = p["variant"]
    if variant not in ("rigid", "flexy"):
        raise ValueError(f"'variant' must be 'rigid' or 'flexy', got {variant!r}")
    scale = int_param(p, "scale", 1, MAX_BODIES // 40)  # 80 (rigid) or 50 (flexy) bodies per unit
    flexy = variant == "flexy"
    n_deck = int_param(p, "n_deck", 2) if p["n_deck"] is not None else (40 if flexy else 80) * scale
    n_tower = (int_param(p, "n_tower", 1) if p["n_tower"] is not None else 10 * scale) if flexy else 0
    L, W, T = _num(p, "span"), _num(p, "width"), _num(p, "thickness")
    rho = _num(p, "density") * (_num(p, "weight") if flexy else 1.0)
    H, zb = _num(p, "tower_height"), _num(p, "tower_base", positive=False)
    tower_rho = _num(p, "tower_density")
    fan = _num(p, "fan") if p["fan"] is not None else 0.25 * L
    # Cambered deck: the pieces are the chords of a circular arc of rise `camber` between the two
    # supports (a straight pinned-pinned chain would be a singular configuration for the x row of
    # the end loop). The cambered shape is the stress-free shape (joint rest = q0).
    rise = _num(p, "camber")
    R = (L * L / 4 + rise * rise) / (2 * rise)
    half = math.asin(L / (2 * R))
    dq = 2 * half / n_deck
    ld = 2 * R * math.sin(dq / 2)
    bodies, joints, sites, springs = [], [], [], []
    for k in range(n_deck):
        q0 = -(half - dq / 2) if k == 0 else dq
        bodies.append({"name": f"deck{k}", "shape": {"type": "box", "size": [ld, W, T]}, "density": rho})
        joints.append({"name": f"d{k}", "type": "revolute", "axis": "y",
                       "parent": "world" if k == 0 else f"deck{k - 1}", "child": f"deck{k}",
                       "placement": {"pos": [0.0 if k == 0 else ld / 2, 0.0, 0.0]},
                       "body_placement": {"pos": [ld / 2, 0.0, 0.0]}, "q0": q0, "rest": q0,
                       "stiffness": _num(p, "deck_EI") / ld, "damping": _num(p, "deck_damping") / ld})
    towers = [0.25 * L, 0.75 * L]
    lt = H / max(n_tower, 1)
    for t, xt in enumerate(towers):
        if not flexy:
            bodies.append({"name": f"tower{t}", "shape": {"type": "box", "size": [1.5, W, H]}, "density": 2500.0})
            joints.append({"name": f"tower{t}_fix", "type": "fixed", "parent": "world", "child": f"tower{t}",
                           "placement": {"pos": [xt, 0.0, zb + H / 2]}})
            continue
        for k in range(n_tower):
            b = f"tower{t}_{k}"
            bodies.append({"name": b, "shape": {"type": "box", "size": [1.5, W, lt]}, "density": tower_rho})
            joints.append({"name": f"t{t}_{k}", "type": "revolute", "axis": "y",
                           "parent": "world" if k == 0 else f"tower{t}_{k - 1}", "child": b,
                           "placement": {"pos": [xt, 0.0, zb] if k == 0 else [0.0, 0.0, lt / 2]},
                           "body_placement": {"pos": [0.0, 0.0, lt / 2]},
                           "stiffness": _num(p, "tower_EI") / lt, "damping": _num(p, "tower_damping") / lt})

    def anchor(t, z):
        """(body, position in its frame) of a cable anchor at height z on tower t."""
        if not flexy:
            return f"tower{t}", z - (zb + H / 2)
        k = min(n_tower - 1, max(0, int((z - zb) / lt)))
        return f"tower{t}_{k}", z - (zb + (k + 0.5) * lt)

    kc = _num(p, "cable_k") * ld / 2
    dc = _num(p, "cable_d", positive=False) * ld / 2
    spread = _num(p, "anchor_spread", positive=False)
    if not 0.0 <= spread < 1.0:
        raise ValueError(f"'anchor_spread' must be in [0, 1), got {spread}")
    near = 0.05 * L
    for k in range(n_deck):
        xc = (k + 0.5) * L / n_deck
        t = min(range(len(towers)), key=lambda i: abs(xc - towers[i]))
        dist = abs(xc - towers[t])
        if not near <= dist <= fan:
            continue
        # semi-fan: the longest cables reach the tower top, shorter ones anchor lower
        z = zb + H * (1.0 - spread * (fan - dist) / max(fan - near, 1e-12))
        body, zl = anchor(t, min(z, zb + H - 1e-9))
        for side, y in (("l", W / 2), ("r", -W / 2)):
            sites.append({"name": f"deck{k}_{side}", "body": f"deck{k}", "pos": [0.0, y, 0.0]})
            sites.append({"name": f"anchor{k}_{side}", "body": body, "pos": [0.0, y, zl]})
            springs.append({"name": f"cable{k}_{side}", "a": f"deck{k}_{side}", "b": f"anchor{k}_{side}",
                            "stiffness": kc, "damping": dc})
    sites.append({"name": "deck_end", "body": f"deck{n_deck - 1}", "pos": [ld / 2, 0.0, 0.0]})
    sites.append({"name": "abutment", "body": "world", "pos": [L, 0.0, 0.0]})
    loops = [{"name": "far_end", "a": "deck_end", "b": "abutment", "rows": ["x", "z"]}]
    return {"bodies": bodies, "joints": joints, "sites": sites, "springs": springs, "loops": loops}


@register_builder("umbrella")
def umbrella(params: dict) -> dict:
    p = take(params, dict(ribs=10, stretchers=None, arms=8, rib_length=0.9, droop=20.0, attach=0.45,
                           runner_height=0.55, rib_EI=2.0, stretcher_EI=2.0, joint_damping=0.002,
                           density=2000.0, thickness=0.01, canopy_k=200.0, canopy_d=0.5, canopy_rest=1.0,
                           runner_k=200.0, runner_d=5.0))
    nr = int_param(p, "ribs", 1)
    ns = int_param(p, "stretchers", 1) if p["stretchers"] is not None else max(1, nr // 2)
    arms = int_param(p, "arms", 3)
    Lr, th, rho = _num(p, "rib_length"), _num(p, "thickness"), _num(p, "density")
    beta = math.radians(_num(p, "droop", positive=False))
    s_att = _num(p, "attach")
    if not 0.0 < s_att <= 1.0:
        raise ValueError(f"'attach' must be in (0, 1], got {s_att}")
    zr = _num(p, "runner_height")
    if not zr < 1.0:
        raise ValueError(f"'runner_height' must be below the tube tip (1 m), got {zr}")
    lr = Lr / nr
    jd = _num(p, "joint_damping", positive=False)
    bodies = [{"name": "tube", "shape": {"type": "cylinder", "radius": 0.012, "length": 1.0}, "density": rho},
              {"name": "runner", "shape": {"type": "cylinder", "radius": 0.018, "length": 0.06}, "density": rho}]
    joints = [{"name": "tube_fix", "type": "fixed", "parent": "world", "child": "tube",
               "placement": {"pos": [0.0, 0.0, 0.5]}},
              {"name": "runner", "type": "prismatic", "axis": "z", "parent": "tube", "child": "runner",
               "placement": {"pos": [0.0, 0.0, zr - 0.5]}, "q0": 0.0, "rest": 0.0,
               "stiffness": _num(p, "runner_k", positive=False), "damping": _num(p, "runner_d", positive=False)}]
    sites, springs, loops = [], [], []
    kr = _num(p, "rib_EI") / lr
    k_att = min(nr - 1, int(s_att * nr - 1e-9))  # rib piece carrying the stretcher attachment
    s_on = s_att * Lr - k_att * lr - lr / 2  # attachment along that piece, from its centre
    for a in range(arms):
        phi = 2.0 * math.pi * a / arms
        d = (math.cos(phi) * math.cos(beta), math.sin(phi) * math.cos(beta), -math.sin(beta))
        for k in range(nr):
            b = f"rib{a}_{k}"
            bodies.append({"name": b, "shape": {"type": "box", "size": [lr, th, th]}, "density": rho})
            joints.append({"name": f"r{a}_{k}", "type": "universal", "axes": ["y", "z"],
                           "parent": "tube" if k == 0 else f"rib{a}_{k - 1}", "child": b,
                           "placement": ({"pos": [0.0, 0.0, 0.5], "rpy": [0.0, beta, phi]} if k == 0
                                         else {"pos": [lr / 2, 0.0, 0.0]}),
                           "body_placement": {"pos": [lr / 2, 0.0, 0.0]}, "stiffness": kr, "damping": jd})
            sites.append({"name": f"rib{a}_{k}_tip", "body": b, "pos": [lr / 2, 0.0, 0.0]})
        # stretcher from the runner to the attachment point on the rib (closes exactly at q0 = 0)
        A = [s_att * Lr * d[0], s_att * Lr * d[1], 1.0 + s_att * Lr * d[2]]
        e = [A[0], A[1], A[2] - zr]
        Ls = math.sqrt(sum(c * c for c in e))
        pitch = -math.atan2(e[2], math.hypot(e[0], e[1]))
        ls = Ls / ns
        ks = _num(p, "stretcher_EI") / ls
        for k in range(ns):
            b = f"stretcher{a}_{k}"
            bodies.append({"name": b, "shape": {"type": "box", "size": [ls, th, th]}, "density": rho})
            joints.append({"name": f"s{a}_{k}", "type": "universal", "axes": ["y", "z"],
                           "parent": "runner" if k == 0 else f"stretcher{a}_{k - 1}", "child": b,
                           "placement": ({"pos": [0.0, 0.0, 0.0], "rpy": [0.0, pitch, phi]} if k == 0
                                         else {"pos": [ls / 2, 0.0, 0.0]}),
                           "body_placement": {"pos": [ls / 2, 0.0, 0.0]}, "stiffness": ks, "damping": jd})
        sites.append({"name": f"stretcher{a}_tip", "body": f"stretcher{a}_{ns - 1}", "pos": [ls / 2, 0.0, 0.0]})
        sites.append({"name": f"rib{a}_notch", "body": f"rib{a}_{k_att}", "pos": [s_on, 0.0, 0.0]})
        loops.append({"name": f"notch{a}", "a": f"stretcher{a}_tip", "b": f"rib{a}_notch"})
    kc, dc = _num(p, "canopy_k", positive=False) / nr, _num(p, "canopy_d", positive=False) / nr
    rest = _num(p, "canopy_rest")
    for a in range(arms):
        b = (a + 1) % arms
        for k in range(nr):
            s = {"name": f"canopy{a}_{k}", "a": f"rib{a}_{k}_tip", "b": f"rib{b}_{k}_tip", "stiffness": kc,
                 "damping": dc}
            if rest != 1.0:
                chord = 2.0 * math.sin(math.pi / arms) * (k + 1) * lr * math.cos(beta)
                s["rest_length"] = rest * chord
            springs.append(s)
    return {"bodies": bodies, "joints": joints, "sites": sites, "springs": springs, "loops": loops,
            "prescribable": {"joints": ["runner"], "sites": []}}
