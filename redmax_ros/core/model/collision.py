"""The collision model of a scene: a Pinocchio GeometryModel of every collision shape and its candidate
pairs (docs/collisions.md).

Built once at compile time (step/compile.py) from the scene's ``collision`` section: each colliding body's
shapes (geometry/collision_shapes.coal_parts) are GeometryObjects on the body's Pinocchio joint (body frame
placement of the Mechanism), obstacles on the world (joint 0). Candidate pairs: every pair of objects on
different joints, except objects of the same body, of a parent-child body pair of the scene tree (which
touch at their joint by construction), of a user-excluded pair, and pairs that are both fixed (world).
Every candidate is a pin.CollisionPair of the GeometryModel, so a step asks coal (through
pin.computeDistance) only about the pairs the bounding-sphere pre-filter keeps (dynamics/self_collision.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin

from redmax_ros.core.geometry.collision_shapes import coal_parts
from redmax_ros.core.scene.collision_schema import body_shape


@dataclass(frozen=True)
class CollisionModel:
    geom: pin.GeometryModel  # the collision objects (pin.GeometryObject with coal geometries) and pairs
    owner: list  # object -> body or obstacle name
    jid: np.ndarray  # (O,) Pinocchio joint of each object (0: world)
    radius: np.ndarray  # (O,) bounding radius about the object's frame origin [m] (inf: half-space)
    pair_a: np.ndarray  # (P,) object index of each candidate pair (pair k of geom.collisionPairs)
    pair_b: np.ndarray  # (P,)
    pair_bound: np.ndarray  # (P,) radius[a] + radius[b] + margin [m]
    margin: float  # m: detection distance (rows for d < margin)
    offset: float  # m: gap the rows keep
    restitution: float  # Newton's coefficient on the normal velocity of pairs that hit within a step (0: inelastic)
    pair_labels: list  # "a/b" per candidate pair (row labels, messages)

    @property
    def n_pairs(self) -> int:
        return len(self.pair_a)


def build_collision(mech, cspec) -> CollisionModel:
    """The CollisionModel of a Mechanism and its scene's CollisionSpec (scene/collision_schema.py)."""
    spec = mech.spec
    shapes_of = {b.name: b.shape for b in spec.bodies}
    names = cspec.bodies if cspec.bodies is not None else list(mech.bodies)
    bidx = {n: i for i, n in enumerate(mech.bodies)}
    geom = pin.GeometryModel()
    owner, jid, radius = [], [], []
    for name in names:
        shape = cspec.shapes.get(name) or body_shape(shapes_of.get(name))
        if shape is None:
            continue  # bodies without a shape do not collide (collision.bodies names them explicitly)
        i = bidx[name]
        j = int(mech.body_jid[i])
        M_body = mech.body_placement[i]
        for k, (g, M, r) in enumerate(coal_parts(shape)):
            geom.addGeometryObject(pin.GeometryObject(f"{name}#{k}", j, M_body * M, g))
            owner.append(name)
            jid.append(j)
            radius.append(r)  # about the object's frame origin (its oMg translation)
    for oname, shape in cspec.obstacles:
        for k, (g, M, r) in enumerate(coal_parts(shape)):
            geom.addGeometryObject(pin.GeometryObject(f"{oname}#{k}", 0, M, g))
            owner.append(oname)
            jid.append(0)
            radius.append(r)
    jid = np.array(jid, dtype=int)
    radius = np.array(radius, float)
    excluded = {frozenset(p) for p in cspec.exclude}
    adjacent = {frozenset((j.parent, j.child)) for j in spec.joints}  # parent-child bodies (scene tree)
    pa, pb, labels = [], [], []
    for a in range(len(owner)):
        for b in range(a + 1, len(owner)):
            ja, jb = int(jid[a]), int(jid[b])
            pair = frozenset((owner[a], owner[b]))
            if owner[a] == owner[b] or ja == jb or pair in adjacent or pair in excluded:
                continue  # same body, same joint (both fixed, or merged by fixed joints), adjacent, excluded
            geom.addCollisionPair(pin.CollisionPair(a, b))
            pa.append(a)
            pb.append(b)
            labels.append(f"{owner[a]}/{owner[b]}")
    pa, pb = np.array(pa, dtype=int), np.array(pb, dtype=int)
    return CollisionModel(geom, owner, jid, radius, pa, pb, radius[pa] + radius[pb] + cspec.margin if len(pa) else
                          np.zeros(0), cspec.margin, cspec.offset, cspec.restitution, labels)


@dataclass(frozen=True)
class ShapePose:
    """One collision object in the world at a configuration (for display: the node's markers)."""
    owner: str  # body or obstacle name
    kind: str  # 'sphere' | 'box' | 'cylinder' | 'capsule' (others, meshes and planes, are not listed)
    size: tuple  # m: sphere (d, d, d); box full extents; cylinder and capsule (d, d, length between the end centres)
    position: np.ndarray  # (3,) world frame [m]
    quaternion: np.ndarray  # (4,) xyzw, world frame (axis of cylinders and capsules: local z)


def shape_poses(mech, data, q) -> list:
    """ShapePose of every primitive collision object at configuration ``q`` (``data``: a pin.Data of
    mech.model, used for the forward kinematics)."""
    cm = mech.collision
    if cm is None:
        return []
    pin.forwardKinematics(mech.model, data, q)
    out = []
    for k, obj in enumerate(cm.geom.geometryObjects):
        g = obj.geometry
        if isinstance(g, coal.Sphere):
            kind, size = "sphere", (2 * g.radius,) * 3
        elif isinstance(g, coal.Box):
            kind, size = "box", tuple(2 * np.asarray(g.halfSide, float))
        elif isinstance(g, coal.Capsule):
            kind, size = "capsule", (2 * g.radius, 2 * g.radius, 2 * g.halfLength)
        elif isinstance(g, coal.Cylinder):
            kind, size = "cylinder", (2 * g.radius, 2 * g.radius, 2 * g.halfLength)
        else:
            continue
        M = data.oMi[int(cm.jid[k])] * obj.placement
        quat = pin.Quaternion(M.rotation).coeffs()  # x, y, z, w
        out.append(ShapePose(cm.owner[k], kind, tuple(float(s) for s in size), M.translation.copy(),
                             np.asarray(quat, float).copy()))
    return out
