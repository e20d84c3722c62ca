"""Scene-file keys of self-collision (docs/collisions.md, docs/scenes.md "Self-collision").

    collision:
      margin: 0.005          # m: pairs whose distance is below it give a unilateral row (detection distance)
      offset: 0.0            # m: the gap the rows keep, d(t_k+1) ~ d + h ddot >= offset (position correction)
      restitution: 0.0       # Newton's coefficient on the normal velocity at impact (0: inelastic)
      bodies: [a, b, ...]    # bodies that collide (default: every body with a shape)
      shapes: {body: {type: capsule, radius: 0.01, length: 0.05, pos: [0,0,0], rpy: [0,0,0]}}
                             # collision shape of a body, instead of its (marker) shape
      exclude: [[a, b], ...] # pairs that never collide (parent-child pairs are always excluded)
      obstacles:             # static geometry on the world
        - {name: floor, type: plane, normal: [0, 0, 1], offset: 0.0}
        - {name: jar, type: shell, radius: 0.03, length: 0.08, thickness: 0.004, segments: 16, pos, rpy}
        - {name: block, type: box | sphere | capsule | cylinder | mesh, ..., pos, rpy}

Shapes are in the body frame (capsule and cylinder axes along local z, as the body shapes of
docs/scenes.md); SI units. Parsed into a :class:`CollisionSpec` (None when the scene has no
``collision`` key). The rows are the unilateral constraints of the QP of Eq. (5) (paper §6, HAGFISH).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

TOP_KEYS = {"collision"}
SHAPE_KEYS = {"box": ("size",), "sphere": ("radius",), "capsule": ("radius", "length"),
              "cylinder": ("radius", "length"), "mesh": ("file",)}
OBSTACLE_TYPES = tuple(SHAPE_KEYS) + ("plane", "shell")


@dataclass
class CollisionShape:
    type: str  # box | sphere | capsule | cylinder | mesh | plane | shell
    pos: np.ndarray  # (3,) in the body frame (world frame for obstacles) [m]
    rpy: np.ndarray  # (3,) [rad]
    radius: float = 0.0  # m (sphere, capsule, cylinder, shell: inner radius)
    length: float = 0.0  # m (capsule: between the hemisphere centres; cylinder, shell)
    size: np.ndarray | None = None  # (3,) full extents (box) [m]
    file: str | None = None  # mesh: OBJ path
    scale: np.ndarray | None = None  # mesh: (3,) scale
    normal: np.ndarray | None = None  # plane: unit normal (into the free half-space)
    offset: float = 0.0  # plane: n . x = offset [m]
    thickness: float = 0.0  # shell: wall thickness [m]
    segments: int = 0  # shell: number of wall staves (boxes)


@dataclass
class CollisionSpec:
    margin: float = 0.005  # m: detection distance
    offset: float = 0.0  # m: kept gap
    restitution: float = 0.0  # Newton's restitution coefficient in [0, 1]
    bodies: list | None = None  # colliding bodies (None: every body with a shape)
    shapes: dict = field(default_factory=dict)  # body -> CollisionShape
    exclude: list = field(default_factory=list)  # (a, b) body pairs
    obstacles: list = field(default_factory=list)  # (name, CollisionShape), world frame


def body_shape(shape: dict | None) -> CollisionShape | None:
    """The collision shape of a body's scene ``shape`` (its marker shape, centred on the body frame), or
    None when the body has no shape usable for collision."""
    if not isinstance(shape, dict) or shape.get("type") not in SHAPE_KEYS:
        return None
    t = shape["type"]
    z = np.zeros(3)
    if t == "box":
        return CollisionShape(t, z, z.copy(), size=np.asarray(shape["size"], float))
    if t == "mesh":
        sc = shape.get("scale", 1.0)
        return CollisionShape(t, z, z.copy(), file=str(shape["file"]),
                              scale=np.full(3, float(sc)) if np.isscalar(sc) else np.asarray(sc, float))
    return CollisionShape(t, z, z.copy(), radius=float(shape["radius"]), length=float(shape.get("length", 0.0)))


def _shape(v, entry, d, allowed_types) -> CollisionShape:
    v.keys(entry, d, {"name", "type", "size", "radius", "length", "pos", "rpy", "file", "scale", "normal", "offset",
                      "thickness", "segments"}, required=("type",))
    t = d["type"]
    if t not in allowed_types:
        v.err(entry, f"unknown collision shape type {t!r} (known: {', '.join(allowed_types)})")
    pos = v.vector(entry, "pos", d.get("pos", [0, 0, 0]), 3)
    rpy = v.vector(entry, "rpy", d.get("rpy", [0, 0, 0]), 3)
    s = CollisionShape(t, pos, rpy)
    need = {"plane": ("normal",), "shell": ("radius", "length", "thickness")}.get(t, SHAPE_KEYS.get(t, ()))
    for k in need:
        if k not in d:
            v.err(entry, f"collision shape '{t}' needs '{k}'")
    if t == "box":
        s.size = v.vector(entry, "size", d["size"], 3)
        if np.any(s.size <= 0):
            v.err(entry, f"'size' must be positive, got {s.size.tolist()}")
    if t in ("sphere", "capsule", "cylinder", "shell"):
        s.radius = v.number(entry, "radius", d["radius"], positive=True)
    if t in ("capsule", "cylinder", "shell"):
        s.length = v.number(entry, "length", d["length"], positive=True)
    if t == "mesh":
        s.file = str(v.named_file(entry, "file", d["file"], "mesh"))
        s.scale = v.vector(entry, "scale", d.get("scale", 1.0), 3, allow_scalar=True)
        if np.any(s.scale <= 0):
            v.err(entry, "'scale' must be positive")
    if t == "plane":
        n = v.vector(entry, "normal", d["normal"], 3)
        if np.linalg.norm(n) < 1e-12:
            v.err(entry, "'normal' must be non-zero")
        s.normal = n / np.linalg.norm(n)
        s.offset = v.number(entry, "offset", d.get("offset", 0.0))
    if t == "shell":
        s.thickness = v.number(entry, "thickness", d["thickness"], positive=True)
        seg = d.get("segments", 16)
        if isinstance(seg, bool) or not isinstance(seg, int) or seg < 3:
            v.err(entry, f"'segments' must be an integer >= 3, got {seg!r}")
        s.segments = seg
    return s


def parse(v, raw: dict, spec, bodies: set):
    """Validate the ``collision`` section (``v``: the scene validator, for messages naming the entry)."""
    if "collision" not in raw:
        return None
    d = raw["collision"]
    if d is None:
        return None
    if spec.friction is not None:
        v.err("collision", "self-collision is not supported together with contact or joint friction (ground, "
              "contacts, joint friction: Staggered Projections); model the ground as a collision obstacle")
    v.keys("collision", d, {"margin", "offset", "restitution", "bodies", "shapes", "exclude", "obstacles"})
    out = CollisionSpec()
    out.margin = v.number("collision.margin", "margin", d.get("margin", out.margin), positive=True)
    out.offset = v.number("collision.offset", "offset", d.get("offset", 0.0), nonneg=True)
    out.restitution = v.number("collision.restitution", "restitution", d.get("restitution", 0.0), nonneg=True)
    if out.restitution > 1.0:
        v.err("collision.restitution", f"must be in [0, 1], got {out.restitution}")
    if out.offset >= out.margin:
        v.err("collision.offset", f"must be below collision.margin ({out.margin} m), got {out.offset}")
    if "bodies" in d:
        bl = d["bodies"]
        if not isinstance(bl, list) or not all(isinstance(b, str) for b in bl):
            v.err("collision.bodies", "must be a list of body names")
        for b in bl:
            if b not in bodies or b == "world":
                v.err("collision.bodies", f"unknown body '{b}'")
        out.bodies = list(bl)
    shapes = d.get("shapes") or {}
    if not isinstance(shapes, dict):
        v.err("collision.shapes", "must be a mapping body -> shape")
    for b, sd in shapes.items():
        if b not in bodies:
            v.err(f"collision.shapes.{b}", f"unknown body '{b}'")
        out.shapes[b] = _shape(v, f"collision.shapes.{b}", sd, tuple(SHAPE_KEYS))
    ex = d.get("exclude") or []
    if not isinstance(ex, list):
        v.err("collision.exclude", "must be a list of [body, body] pairs")
    for i, pair in enumerate(ex):
        entry = f"collision.exclude[{i}]"
        if not (isinstance(pair, list) and len(pair) == 2 and all(isinstance(b, str) for b in pair)):
            v.err(entry, f"must be a pair [body, body], got {pair!r}")
        for b in pair:
            if b not in bodies and b not in {o.get("name") for o in (d.get("obstacles") or []) if isinstance(o, dict)}:
                v.err(entry, f"unknown body or obstacle '{b}'")
        out.exclude.append(tuple(pair))
    for entry, od in v.entries(d, "obstacles"):
        entry = "collision." + entry
        if od["name"] in bodies:
            v.err(entry, f"obstacle name '{od['name']}' is also a body name")
        out.obstacles.append((od["name"], _shape(v, entry, od, OBSTACLE_TYPES)))
    colliding = out.bodies if out.bodies is not None else sorted(bodies - {"world"})
    body_shapes = {b.name: b.shape for b in spec.bodies}
    if out.bodies is not None:
        for b in out.bodies:
            if b not in out.shapes and body_shape(body_shapes.get(b)) is None:
                v.err("collision.bodies", f"body '{b}' has no shape to collide with; give collision.shapes.{b}")
    if not out.obstacles and sum(1 for b in colliding if b in out.shapes or body_shape(body_shapes.get(b))) < 2:
        v.err("collision", "needs at least two colliding bodies, or an obstacle")
    return out
