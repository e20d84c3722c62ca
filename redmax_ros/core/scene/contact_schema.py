"""Scene-file keys of contact and friction (docs/scenes.md "Contact and friction", docs/friction.md).

    ground:    planes n . x >= offset (world frame) with a friction coefficient mu
    contacts:  contact primitives on bodies (point, sphere, capsule, box) that collide with the planes
    joints[i].friction: {mu, radius, length, points}   implicit joint contact geometry (BISP, paper §5.2);
                        prismatic joints also {mu, shape: box, size: [w1, w2], length} (box cross-section)
    loops[i].friction, loops[i].axis                   friction in a loop-closing pin joint (paper §5.3)
    friction:  settings of the staggered loop (max_iter, tol, erp, margin, epsilon)

Parsed by the scene validator (scene._Validator) into a :class:`FrictionSpec`; ``None`` when the
scene has none of these keys (the frictionless, contactless step then runs unchanged).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

CONTACT_TYPES = ("point", "sphere", "capsule", "box")
FRICTION_JOINT_TYPES = ("revolute", "prismatic", "spherical", "spherical_exp")
MAX_POINTS = 1000  # joints[].friction.points: contact points per end circle
JOINT_SECTIONS = ("cylinder", "box")  # cross-sections of a prismatic joint's bearing


@dataclass
class PlaneSpec:
    name: str
    normal: np.ndarray  # (3,) unit, world frame, pointing out of the solid (into the free half-space)
    offset: float  # m: the plane is n . x = offset
    mu: float  # Coulomb friction coefficient of contacts on this plane


@dataclass
class ContactSpec:
    name: str
    body: str
    type: str  # point | sphere | capsule | box
    pos: np.ndarray  # (3,) centre in the body frame [m]
    rpy: np.ndarray  # (3,) orientation in the body frame (capsule axis = local z; box axes)
    radius: float = 0.0  # m (sphere, capsule)
    length: float = 0.0  # m (capsule: distance between the two hemisphere centres)
    size: np.ndarray | None = None  # (3,) full extents [m] (box)
    mu: float | None = None  # overrides the plane's mu when given


@dataclass
class JointFrictionSpec:
    mu: float
    radius: float  # m: cylinder (revolute, prismatic) or ball (spherical, spherical_exp) radius; 0 for a box
    length: float  # m: cylinder/box length (distance between the two end circles or corner squares)
    points: int  # implicit contact points per end circle (revolute, prismatic cylinder)
    shape: str = "cylinder"  # cross-section of a prismatic joint: cylinder | box
    size: np.ndarray | None = None  # (2,) full widths [m] of a box cross-section along u1, u2 (contact.box_section_axes)


@dataclass
class LoopFrictionSpec:
    axis: np.ndarray  # (3,) world direction of the loop-closing pin
    friction: JointFrictionSpec


@dataclass
class FrictionSettings:
    max_iter: int = 50  # staggered iterations per step (Alg. 2/3 "max iterations")
    tol: float = 1e-6  # convergence: max velocity change the change of contact impulses would make [m/s]
    erp: float = 0.2  # fraction of a penetration removed per step (velocity-level stabilization)
    margin: float = 0.01  # m: contacts closer than this are in the contact QP (speculative, no early stop)
    epsilon: float = 1e-6  # regularization of the local joint least squares (Eq. 16)
    joint_mu: float | None = None  # when given, replaces mu of every frictional joint and loop pin
    qp: str = "pgs"  # box QP solver of the contact and friction stages: pgs | proxsuite
    anderson: int = 5  # depth of the Anderson acceleration of the staggered loop with joint friction (0: off)


@dataclass
class FrictionSpec:
    planes: list = field(default_factory=list)
    contacts: list = field(default_factory=list)
    joints: dict = field(default_factory=dict)  # joint name -> JointFrictionSpec
    loops: dict = field(default_factory=dict)  # loop name -> LoopFrictionSpec
    settings: FrictionSettings = field(default_factory=FrictionSettings)


TOP_KEYS = {"ground", "contacts", "friction"}


def parse(v, raw: dict, spec, bodies: set):
    """Validate the contact/friction keys of a scene dict (``v``: the scene._Validator, for messages)."""
    has_joint = any(isinstance(j, dict) and "friction" in j for j in (raw.get("joints") or []))
    has_loop = any(isinstance(lp, dict) and ("friction" in lp or "axis" in lp) for lp in (raw.get("loops") or []))
    if not (TOP_KEYS & set(raw) or has_joint or has_loop):
        return None
    out = FrictionSpec()
    for entry, d in v.entries(raw, "ground"):
        v.keys(entry, d, {"name", "normal", "offset", "point", "mu"})
        n = v.vector(entry, "normal", d.get("normal", [0, 0, 1]), 3)
        nn = np.linalg.norm(n)
        if nn < 1e-12:
            v.err(entry, "'normal' must not be the zero vector")
        n = n / nn
        if "point" in d and "offset" in d:
            v.err(entry, "give either 'offset' or 'point', not both")
        off = float(n @ v.vector(entry, "point", d["point"], 3)) if "point" in d else \
            v.number(entry, "offset", d.get("offset", 0.0))
        out.planes.append(PlaneSpec(d["name"], n, off, v.number(entry, "mu", d.get("mu", 0.5), nonneg=True)))
    for entry, d in v.entries(raw, "contacts"):
        v.keys(entry, d, {"name", "body", "type", "pos", "rpy", "radius", "length", "size", "mu"},
               required=("body", "type"))
        if not isinstance(d["body"], str) or d["body"] not in bodies or d["body"] == "world":
            v.err(entry, f"unknown body '{d['body']}'")
        t = d["type"]
        if t not in CONTACT_TYPES:
            v.err(entry, f"unknown contact type '{t}' (known: {', '.join(CONTACT_TYPES)})")
        c = ContactSpec(d["name"], d["body"], t, v.vector(entry, "pos", d.get("pos", [0, 0, 0]), 3),
                        v.vector(entry, "rpy", d.get("rpy", [0, 0, 0]), 3))
        if t in ("sphere", "capsule"):
            if "radius" not in d:
                v.err(entry, f"a {t} contact needs 'radius'")
            c.radius = v.number(entry, "radius", d["radius"], positive=True)
        if t == "capsule":
            if "length" not in d:
                v.err(entry, "a capsule contact needs 'length'")
            c.length = v.number(entry, "length", d["length"], positive=True)
        if t == "box":
            if "size" not in d:
                v.err(entry, "a box contact needs 'size' (full extents [x, y, z])")
            c.size = v.vector(entry, "size", d["size"], 3)
            if np.any(c.size <= 0):
                v.err(entry, f"'size' must be positive, got {c.size.tolist()}")
        for k in ("radius", "length", "size"):
            if k in d and not ((k == "radius" and t in ("sphere", "capsule")) or (k == "length" and t == "capsule")
                               or (k == "size" and t == "box")):
                v.err(entry, f"a {t} contact takes no '{k}'")
        if "mu" in d:
            c.mu = v.number(entry, "mu", d["mu"], nonneg=True)
        out.contacts.append(c)
    if out.contacts and not out.planes:
        v.err("contacts", "contact primitives need at least one 'ground' plane to collide with")
    types = {j.name: j.type for j in spec.joints}
    for i, d in enumerate(raw.get("joints") or []):
        if isinstance(d, dict) and "friction" in d:
            entry = f"joints[{i}] '{d.get('name')}'"
            jt = types.get(d.get("name"), d.get("type"))
            if jt not in FRICTION_JOINT_TYPES:
                v.err(entry, f"joint friction is supported on {', '.join(FRICTION_JOINT_TYPES)} joints, not {jt}")
            out.joints[d["name"]] = _joint_friction(v, f"{entry} friction", d["friction"], jt)
    for i, d in enumerate(raw.get("loops") or []):
        if isinstance(d, dict) and ("friction" in d or "axis" in d):
            entry = f"loops[{i}] '{d.get('name')}'"
            if "friction" not in d:
                continue
            if "axis" not in d:
                v.err(entry, "loop friction needs the pin 'axis' (world direction of the loop-closing revolute joint)")
            out.loops[d["name"]] = LoopFrictionSpec(v.axis(entry, "axis", d["axis"]),
                                                    _joint_friction(v, f"{entry} friction", d["friction"], "revolute"))
    s = raw.get("friction") or {}
    v.keys("friction", s, {"max_iter", "tol", "erp", "margin", "epsilon", "joint_mu", "qp", "anderson"})
    if s.get("qp", "pgs") not in ("pgs", "proxsuite"):
        v.err("friction", f"'qp' must be pgs or proxsuite, got {s.get('qp')!r}")
    out.settings.qp = s.get("qp", "pgs")
    an = s.get("anderson", out.settings.anderson)
    if isinstance(an, bool) or not isinstance(an, int) or an < 0:
        v.err("friction", f"'anderson' must be an integer >= 0, got {an!r}")
    out.settings.anderson = an
    st = out.settings
    if "max_iter" in s:
        mi = s["max_iter"]
        if isinstance(mi, bool) or not isinstance(mi, int) or mi < 1:
            v.err("friction", f"'max_iter' must be an integer >= 1, got {mi!r}")
        st.max_iter = mi
    st.tol = v.number("friction", "tol", s.get("tol", st.tol), positive=True)
    st.erp = v.number("friction", "erp", s.get("erp", st.erp), nonneg=True)
    if st.erp > 1:
        v.err("friction", f"'erp' must be in [0, 1], got {st.erp}")
    st.margin = v.number("friction", "margin", s.get("margin", st.margin), nonneg=True)
    st.epsilon = v.number("friction", "epsilon", s.get("epsilon", st.epsilon), positive=True)
    if s.get("joint_mu") is not None:
        st.joint_mu = v.number("friction", "joint_mu", s["joint_mu"], nonneg=True)
    return out


def _joint_friction(v, entry, d, jt) -> JointFrictionSpec:
    ball = jt in ("spherical", "spherical_exp")
    if not isinstance(d, dict):
        v.keys(entry, d, set())  # names the entry: "must be a mapping"
    shape = d.get("shape", "cylinder")
    if shape not in JOINT_SECTIONS:
        v.err(entry, f"'shape' must be one of {', '.join(JOINT_SECTIONS)}, got {shape!r}")
    if shape == "box":
        return _box_friction(v, entry, d, jt)
    v.keys(entry, d, {"mu", "radius", "length", "points", "shape"}, required=("mu", "radius"))
    v.number(entry, "radius", d["radius"], positive=True)
    pts = d.get("points", 8)
    if isinstance(pts, bool) or not isinstance(pts, int) or not 3 <= pts <= MAX_POINTS:
        v.err(entry, f"'points' must be an integer from 3 to {MAX_POINTS}, got {pts!r}")
    length = v.number(entry, "length", d.get("length", 0.0 if ball else 2 * float(d["radius"])),
                      nonneg=True)
    if not ball and length <= 0:
        v.err(entry, "'length' of a revolute/prismatic joint cylinder must be positive")
    return JointFrictionSpec(v.number(entry, "mu", d["mu"], nonneg=True), v.number(entry, "radius", d["radius"],
                                                                                   positive=True), length, pts)


def _box_friction(v, entry, d, jt) -> JointFrictionSpec:
    """A prismatic joint's box cross-section: ``size`` [w1, w2] full widths [m], ``length`` [m] (default the
    larger width) between the two squares of corners (docs/friction.md)."""
    if jt != "prismatic":
        v.err(entry, f"a box cross-section ('shape: box') is for prismatic joints, not {jt}")
    v.keys(entry, d, {"mu", "shape", "size", "length"}, required=("mu", "size"))
    size = v.vector(entry, "size", d["size"], 2)
    if np.any(size <= 0):
        v.err(entry, f"'size' (full widths [w1, w2] of the box cross-section) must be positive, got {size.tolist()}")
    length = v.number(entry, "length", d.get("length", float(size.max())), positive=True)
    return JointFrictionSpec(v.number(entry, "mu", d["mu"], nonneg=True), 0.0, length, 0, "box", size)
