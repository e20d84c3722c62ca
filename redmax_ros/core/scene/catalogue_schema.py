"""Scene-file schema of the RedMax catalogue (docs/scenes.md): the joint types added by joints.py and
joint_maps.py, composite/mesh bodies (bodies.py), and the top-level ``constraints`` (linear equality
constraints between joint coordinates) and ``forces`` (force elements) sections.

Called from scene._Validator; ``v`` is the validator (its number/vector/axis/pose/keys/err helpers
name the file and entry of every problem).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from redmax_ros.core.geometry import joints as jt
from redmax_ros.core.scene import timefunctions
from redmax_ros.core.spatial import placement
from redmax_ros.core.scene.spec import JointSpec, SpringSpec
from redmax_ros.core.geometry.spline_joints import SplineCurve, SplineSurface
from redmax_ros.core.scene import bodies

TOP_KEYS = {"constraints", "forces"}

# type: (nv, length of q0 in the file); composite: computed
TYPES = {
    "planar_translation": (2, 2),
    "translational": (3, 3),
    "spherical_euler": (3, 3),
    "spherical_exp": (3, 3),
    "free2d": (3, 3),
    "free3d": (6, 6),
    "free3d_exp": (6, 6),
    "composite": (None, None),
    "spline_curve": (1, 1),
    "spline_surface": (2, 2),
}
# types that may appear inside a composite joint, with (nv, nq0)
SUB_TYPES = {"revolute": (1, 1), "prismatic": (1, 1), "universal": (2, 2), "spherical": (3, 3), "planar": (3, 3),
             "free": (6, 6), "planar_translation": (2, 2), "translational": (3, 3), "spherical_euler": (3, 3),
             "free2d": (3, 3), "free3d": (6, 6)}
COMMON_KEYS = {"name", "type", "parent", "child", "placement", "body_placement", "q0", "v0", "limits", "stiffness",
               "rest", "damping", "armature", "torque"}
SPECIFIC_KEYS = {"planar_translation": {"axes"}, "translational": set(), "spherical_euler": {"chart", "switch_charts"},
                 "spherical_exp": {"reparam_threshold", "friction"}, "free2d": set(), "free3d": {"conserve_momentum"},
                 "free3d_exp": {"reparam_threshold"}, "composite": {"joints"},
                 "spline_curve": {"control_frames", "cyclic"}, "spline_surface": {"control_grid"}}


def coordinate_dofs(jtype: str, nv: int, parts=()) -> list:
    """Which velocity DOFs are time derivatives of one joint coordinate (limits and linear
    constraints apply to those): a list of bools."""
    if jtype in ("spherical", "planar", "free"):
        return [False] * nv
    if jtype == "free3d":
        return [True] * 3 + [False] * 3
    if jtype == "spherical_exp":
        return [False] * 3  # reparameterisation jumps the coordinates: no limits/linear constraints
    if jtype == "free3d_exp":
        return [False] * 3 + [True] * 3  # r jumps at reparameterisation, t does not
    if jtype == "composite":
        return [b for p in parts for b in coordinate_dofs(p.type, p.extra["nv"])]
    return [True] * nv


def _axes(v, entry, d, key, n, default):
    ax = d.get(key, default)
    if not isinstance(ax, list) or len(ax) != n:
        v.err(entry, f"'{key}' must be a list of {n} axes")
    return np.array([v.axis(entry, key, a) for a in ax])


def _sub_joint(v, entry, d):
    v.keys(entry, d, {"type", "axis", "axes", "chart", "placement"}, required=("type",))
    t = d["type"]
    if not isinstance(t, str) or t not in SUB_TYPES:
        v.err(entry, f"type '{t}' cannot be part of a composite joint (allowed: {', '.join(SUB_TYPES)})")
    nv, nq0 = SUB_TYPES[t]
    axes, extra = np.zeros((0, 3)), {"nv": nv, "nq0": nq0}
    if t in ("revolute", "prismatic"):
        axes = v.axis(entry, "axis", d.get("axis", "z"))[None, :]
    elif t == "universal":
        axes = _axes(v, entry, d, "axes", 2, ["x", "y"])
        if abs(axes[0] @ axes[1]) > 1e-9:
            v.err(entry, "the two axes of a universal joint must be orthogonal")
    elif t == "planar_translation":
        axes = _axes(v, entry, d, "axes", 2, ["x", "y"])
        if np.linalg.matrix_rank(axes, tol=1e-9) < 2:
            v.err(entry, "the two axes of a planar_translation joint must be linearly independent")
    elif t == "spherical_euler":
        extra["chart"] = _chart(v, entry, d)
    elif "axis" in d or "axes" in d:
        v.err(entry, f"a {t} joint takes no axis")
    if t != "spherical_euler" and "chart" in d:
        v.err(entry, "'chart' applies to spherical_euler joints only")
    pose = v.pose(entry, "placement", d.get("placement", {}))
    z = np.zeros(nv)
    return JointSpec("", t, "", "", pose, (np.zeros(3), np.zeros(3)), axes, np.zeros(nq0), z, z, z, z, np.zeros(nq0),
                     z, z, z, extra)


def _chart(v, entry, d):
    chart = str(d.get("chart", "XYZ")).upper()
    if chart not in jt.EULER_CHARTS:
        v.err(entry, f"'chart' must be one of {', '.join(jt.EULER_CHARTS)}, got {d.get('chart')!r}")
    return chart


def validate_joint(v, entry, d, base_dir=None):
    """JointSpec of a joint whose type is in TYPES."""
    t = d["type"]
    req = ("type", "parent", "child") + {"composite": ("joints",), "spline_curve": ("control_frames",),
                                         "spline_surface": ("control_grid",)}.get(t, ())
    v.keys(entry, d, COMMON_KEYS | SPECIFIC_KEYS[t], required=req)
    for k in ("parent", "child"):
        if not isinstance(d[k], str):
            v.err(entry, f"'{k}' must be a body name")
    nv, nq0 = TYPES[t]
    axes, extra = np.zeros((0, 3)), {}
    if t == "planar_translation":
        axes = _axes(v, entry, d, "axes", 2, ["x", "y"])
        if np.linalg.matrix_rank(axes, tol=1e-9) < 2:
            v.err(entry, "the two axes of a planar_translation joint must be linearly independent")
    elif t == "spherical_euler":
        extra["chart"] = _chart(v, entry, d)
        if d.get("switch_charts", False):
            if d["switch_charts"] is not True:
                v.err(entry, "'switch_charts' must be true or false")
            for k in ("limits", "stiffness", "torque"):
                if k == "limits" and k in d or k != "limits" and np.any(np.asarray(d.get(k, 0.0), dtype=float) != 0):
                    v.err(entry, f"'{k}' is not allowed with switch_charts: true (the angles jump at a chart "
                                 "switch; euler_charts.py)")
            extra["switch_charts"] = True
    elif t in ("spherical_exp", "free3d_exp") and "reparam_threshold" in d:
        # Grassia's reparameterisation q <- (1 - 2 pi/||q||) q when ||q|| > threshold (notes §2.5.8; the
        # reference uses 1.5 pi). ||q_new|| = 2 pi - ||q|| is then below the threshold only if it is >= pi,
        # and S(q) is singular on the 2 pi shell: pi <= threshold < 2 pi.
        thr = v.number(entry, "reparam_threshold", d["reparam_threshold"])
        if not (math.pi <= thr < 2.0 * math.pi):
            v.err(entry, f"'reparam_threshold' must be in [pi, 2 pi) rad = [3.14159..., 6.28318...), got {thr}")
        extra["reparam_threshold"] = thr
    elif t == "composite":
        subs = d["joints"]
        if not isinstance(subs, list) or len(subs) < 2:
            v.err(entry, "'joints' of a composite joint must list at least two sub-joints")
        parts = [_sub_joint(v, f"{entry} joints[{i}]", s) for i, s in enumerate(subs)]
        extra["parts"] = parts
        nv = sum(p.extra["nv"] for p in parts)
        nq0 = sum(p.extra["nq0"] for p in parts)
    elif t == "spline_curve":
        cyclic = d.get("cyclic", False)
        if not isinstance(cyclic, bool):
            v.err(entry, f"'cyclic' must be true or false, got {cyclic!r}")
        extra["geometry"], lo_hi = _curve(v, entry, d["control_frames"], cyclic)
    elif t == "spline_surface":
        extra["geometry"], lo_hi = _surface(v, entry, d["control_grid"])
    extra["nv"], extra["nq0"] = nv, nq0
    if d.get("conserve_momentum", False):
        if d["conserve_momentum"] is not True:
            v.err(entry, "'conserve_momentum' must be true or false")
        if d["parent"] != "world":
            v.err(entry, "'conserve_momentum' needs a root joint (parent: world)")
        extra["conserve_momentum"] = True
    pose = v.pose(entry, "placement", d.get("placement", {}))
    body_pose = v.pose(entry, "body_placement", d.get("body_placement", {}))
    q0 = v.vector(entry, "q0", d.get("q0", [0.0] * nq0), nq0, allow_scalar=nq0 == 1)
    v0 = v.vector(entry, "v0", d.get("v0", [0.0] * nv), nv, allow_scalar=nv == 1)
    rest = v.vector(entry, "rest", d.get("rest", list(q0) if t.startswith("spline") else [0.0] * nq0), nq0,
                    allow_scalar=nq0 == 1)
    lower, upper = np.full(nv, -np.inf), np.full(nv, np.inf)
    coord = coordinate_dofs(t, nv, extra.get("parts", ()))
    if "limits" in d:
        lim = d["limits"]
        v.keys(f"{entry} limits", lim, {"lower", "upper"})
        lower = v.vector(entry, "limits.lower", lim.get("lower", -np.inf), nv, allow_scalar=True, allow_inf=True)
        upper = v.vector(entry, "limits.upper", lim.get("upper", np.inf), nv, allow_scalar=True, allow_inf=True)
        bad = [k for k in range(nv) if not coord[k] and (np.isfinite(lower[k]) or np.isfinite(upper[k]))]
        if bad:
            v.err(entry, f"limits on DOF(s) {bad} of a {t} joint are not supported: those DOFs are rotation "
                         "velocities of a quaternion (or exponential-coordinate) rotation, not time derivatives of "
                         "a coordinate; use a spherical_euler or composite joint to limit angles")
        if np.any(lower >= upper):
            v.err(entry, f"limits.lower must be below limits.upper ({lower.tolist()} vs {upper.tolist()})")
    if t.startswith("spline"):  # the parameter domain is a hard limit
        lo, hi = lo_hi
        if np.any(q0 < lo - 1e-12) or np.any(q0 > hi + 1e-12):
            v.err(entry, f"q0 {q0.tolist()} lies outside the spline parameter domain [{lo.tolist()}, {hi.tolist()}]")
        lower, upper = np.maximum(lower, lo), np.minimum(upper, hi)

    def per_dof(key, nonneg=True):
        x = v.vector(entry, key, d.get(key, 0.0), nv, allow_scalar=True)
        if nonneg and np.any(x < 0):
            v.err(entry, f"'{key}' must be non-negative, got {x.tolist()}")
        return x

    return JointSpec(d["name"], t, d["parent"], d["child"], pose, body_pose, axes, q0, v0, lower, upper,
                     per_dof("stiffness"), rest, per_dof("damping"), per_dof("armature"), per_dof("torque", False),
                     extra)


def _curve(v, entry, frames, cyclic=False):
    if not isinstance(frames, list) or len(frames) < 4:
        v.err(entry, "'control_frames' must list at least 4 frames ({pos: [x, y, z], rpy: [r, p, y]})")
    Ms = [placement(*v.pose(f"{entry} control_frames[{i}]", "control frame", f)) for i, f in enumerate(frames)]
    for i in range(0 if cyclic else 1, len(Ms)):  # cyclic: also the wrap-around pair (n-1, 0)
        dR = Ms[i - 1].rotation.T @ Ms[i].rotation
        if np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)) > 3.0:
            v.err(entry, f"control frames {(i - 1) % len(Ms)} and {i} differ by a rotation near pi (log is ambiguous)")
    if cyclic and np.allclose(Ms[-1].homogeneous, Ms[0].homogeneous, atol=1e-12):
        v.err(entry, "a cyclic curve wraps around by itself: do not repeat the first control frame at the end")
    curve = SplineCurve(Ms, cyclic)
    lo, hi = curve.domain
    return curve, (np.array([lo]), np.array([hi]))


def _surface(v, entry, grid):
    ok = (isinstance(grid, list) and len(grid) >= 4 and all(isinstance(r, list) and len(r) == len(grid[0]) for r in grid)
          and len(grid[0]) >= 4)
    if not ok:
        v.err(entry, "'control_grid' must be an n1 x n2 grid (n1, n2 >= 4, rows of equal length) of "
                     "[x, y, z, rx, ry, rz] control values")
    G = np.array([[v.vector(entry, f"control_grid[{i}][{j}]", c, 6) for j, c in enumerate(r)] for i, r in enumerate(grid)])
    surf = SplineSurface(G)
    (l1, h1), (l2, h2) = surf.domain
    return surf, (np.array([l1, l2]), np.array([h1, h2]))


# ----------------------------------------------------------------------------------------------
# constraints and forces sections


@dataclass
class LinearConstraintSpec:
    name: str
    terms: list  # (joint name, dof index within the joint, coefficient)
    value: float | None  # sum c_i q_i = value; None = value at the initial configuration
    kind: str  # 'linear', 'equal' or 'gear' (for messages)


@dataclass
class DirectionSpringSpec:
    name: str
    a: str
    b: str
    direction: np.ndarray  # unit world direction
    stiffness: float  # N/m
    damping: float  # N s/m
    rest: float | None  # m (signed length along direction); None = initial
    implicit: bool = True  # False: explicit force -(k (s - L0) + c d.(v_a - v_b)) d at step k, no K/D in Eq. (2)'s LHS


@dataclass
class TimedWrenchSpec:
    name: str
    body: str
    site: str | None
    force: list  # 3 TimeFunctions [N], world frame
    torque: list  # 3 TimeFunctions [N m], world frame


@dataclass
class TimedTorqueSpec:
    name: str
    joint: str
    torque: list  # nv TimeFunctions [N m or N]


@dataclass
class CatalogueSpec:
    constraints: list = field(default_factory=list)
    direction_springs: list = field(default_factory=list)
    wrenches: list = field(default_factory=list)
    torques: list = field(default_factory=list)

    @property
    def empty(self) -> bool:
        return not (self.constraints or self.direction_springs or self.wrenches or self.torques)


def _joint_dof(v, entry, spec, name, dof):
    if spec.urdf:
        return
    known = {j.name: j for j in spec.joints}
    if not isinstance(name, str) or name not in known or known[name].type == "fixed":
        v.err(entry, f"unknown (or fixed) joint '{name}'")
    j = known[name]
    nv = j.nv
    if not 0 <= dof < nv:
        v.err(entry, f"joint '{name}' has {nv} DOF(s); dof {dof} does not exist")
    if not coordinate_dofs(j.type, nv, j.extra.get("parts", ()))[dof]:
        v.err(entry, f"DOF {dof} of {j.type} joint '{name}' is not the time derivative of a coordinate "
                     "(quaternion rotation or body-frame velocity); linear constraints need coordinates")


def _constraint(v, entry, d, spec):
    t = d.get("type")
    if t == "linear":
        v.keys(entry, d, {"name", "type", "terms", "value"}, required=("terms",))
        terms = d["terms"]
        if not isinstance(terms, list) or not terms:
            v.err(entry, "'terms' must list {joint, coef[, dof]} entries")
        out = []
        for i, tm in enumerate(terms):
            v.keys(f"{entry} terms[{i}]", tm, {"joint", "dof", "coef"}, required=("joint", "coef"))
            dof = int(v.number(entry, f"terms[{i}].dof", tm.get("dof", 0)))
            _joint_dof(v, entry, spec, tm["joint"], dof)
            out.append((tm["joint"], dof, v.number(entry, f"terms[{i}].coef", tm["coef"])))
        if all(c == 0 for _, _, c in out):
            v.err(entry, "all coefficients are zero")
    elif t in ("equal", "gear"):
        keys = {"name", "type", "joints", "dofs", "value"} | ({"ratio"} if t == "gear" else set())
        v.keys(entry, d, keys, required=("joints",) + (("ratio",) if t == "gear" else ()))
        js = d["joints"]
        if not isinstance(js, list) or len(js) != 2 or not all(isinstance(x, str) for x in js):
            v.err(entry, "'joints' must name two joints [a, b]")
        dofs = d.get("dofs", [0, 0])
        dofs = [int(x) for x in v.vector(entry, "dofs", dofs, 2)]
        r = v.number(entry, "ratio", d["ratio"]) if t == "gear" else 1.0
        if r == 0:
            v.err(entry, "'ratio' must be non-zero")
        for jn, k in zip(js, dofs):
            _joint_dof(v, entry, spec, jn, k)
        if js[0] == js[1] and dofs[0] == dofs[1]:
            v.err(entry, "a joint DOF cannot be constrained to itself")
        out = [(js[0], dofs[0], 1.0), (js[1], dofs[1], -r)]  # q_a - r q_b = value
    else:
        v.err(entry, f"unknown constraint type {t!r} (linear, equal, gear)")
    value = d.get("value")
    value = None if value is None or value == "initial" else v.number(entry, "value", value)
    return LinearConstraintSpec(d["name"], out, value, t)


def _force(v, entry, d, spec, sites, bodies, cat):
    t = d.get("type")
    if t == "spring_damper":
        v.keys(entry, d, {"name", "type", "a", "b", "stiffness", "damping", "rest_length", "implicit"})
        s = v.spring(entry, {k: x for k, x in d.items() if k != "type"}, sites)
        spec.springs.append(s if isinstance(s, SpringSpec) else s)
    elif t == "direction_spring":
        v.keys(entry, d, {"name", "type", "a", "b", "direction", "stiffness", "damping", "rest_length", "implicit"},
               required=("a", "b", "direction"))
        implicit = d.get("implicit", True)
        if not isinstance(implicit, bool):
            v.err(entry, f"'implicit' must be true or false, got {implicit!r}")
        a, b = v.site_ref(entry, "a", d, sites), v.site_ref(entry, "b", d, sites)
        if a == b:
            v.err(entry, "a spring needs two different sites")
        rl = d.get("rest_length")
        cat.direction_springs.append(DirectionSpringSpec(
            d["name"], a, b, v.axis(entry, "direction", d["direction"]),
            v.number(entry, "stiffness", d.get("stiffness", 0.0), nonneg=True),
            v.number(entry, "damping", d.get("damping", 0.0), nonneg=True),
            None if rl is None else v.number(entry, "rest_length", rl), implicit))
    elif t == "wrench":
        v.keys(entry, d, {"name", "type", "body", "site", "force", "torque"}, required=("body",))
        if not isinstance(d["body"], str) or d["body"] not in bodies or d["body"] == "world":
            v.err(entry, f"unknown body '{d['body']}'")
        site = d.get("site")
        if site is not None:
            if not isinstance(site, str) or site not in sites:
                v.err(entry, f"unknown site '{site}'")
            owner = {s.name: s.body for s in spec.sites}[site]
            if owner != d["body"]:
                v.err(entry, f"site '{site}' is on body '{owner}', not on '{d['body']}'")
        cat.wrenches.append(TimedWrenchSpec(
            d["name"], d["body"], site, timefunctions.parse_vector(v, entry, "force", d.get("force", 0.0), 3),
            timefunctions.parse_vector(v, entry, "torque", d.get("torque", 0.0), 3)))
    elif t == "joint_torque":
        v.keys(entry, d, {"name", "type", "joint", "torque"}, required=("joint", "torque"))
        known = {j.name: j for j in spec.joints}
        jn = d["joint"]
        if not isinstance(jn, str) or not spec.urdf and (jn not in known or known[jn].type == "fixed"):
            v.err(entry, f"unknown (or fixed) joint '{jn}'")
        nv = known[jn].nv if jn in known else 1
        cat.torques.append(TimedTorqueSpec(d["name"], jn, timefunctions.parse_vector(v, entry, "torque", d["torque"], nv)))
    else:
        v.err(entry, f"unknown force element type {t!r} (spring_damper, direction_spring, wrench, joint_torque)")


def parse(v, raw, spec, body_names) -> CatalogueSpec | None:
    """Validate the ``constraints`` and ``forces`` sections; convert principal-frame bodies."""
    cat = CatalogueSpec()
    sites = {s.name for s in spec.sites}
    for e, d in v.entries(raw, "constraints"):
        cat.constraints.append(_constraint(v, e, d, spec))
    names = {s.name for s in spec.springs}
    for e, d in v.entries(raw, "forces"):
        if d["name"] in names:
            v.err(e, f"name '{d['name']}' is already used by a spring")
        _force(v, e, d, spec, sites, body_names, cat)
    bodies.apply_principal_frames(spec)
    return None if cat.empty else cat
