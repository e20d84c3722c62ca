"""Collision shapes as coal geometries (the collision library shipped with Pinocchio; docs/collisions.md).

One shape of a scene's ``collision`` section (scene/collision_schema.CollisionShape: read by attribute, this
layer imports nothing above it) becomes one or more (coal geometry, placement in the body frame, bounding
radius about that placement) triples:

* box, sphere, capsule (axis local z, ``length`` between the hemisphere centres), cylinder (axis local z):
  coal's primitives, for which coal's GJK/EPA gives signed distances (negative in penetration);
* mesh: a coal.BVHModelOBBRSS of the OBJ's triangles (geometry/mesh.read_obj); distances to a mesh are
  unsigned in penetration (coal), so meshes suit obstacles and bodies that must never pass the margin;
* plane: a coal.Halfspace n . x <= offset is solid (signed distance), world obstacles only;
* shell (a jar): ``segments`` box staves of the given wall ``thickness`` around a cylinder of inner
  ``radius`` and ``length`` (axis local z, open at both ends; signed distances as for boxes).

SI units (m, rad).
"""
from __future__ import annotations

import math

import coal
import numpy as np
import pinocchio as pin

from redmax_ros.core.geometry.mesh import read_obj

INF_RADIUS = math.inf  # bounding radius of a half-space


def placement(pos, rpy) -> pin.SE3:
    """SE3 of a shape frame from position [m] and roll-pitch-yaw [rad]."""
    return pin.SE3(pin.rpy.rpyToMatrix(np.asarray(rpy, float)), np.asarray(pos, float))


def coal_parts(shape) -> list:
    """[(coal.CollisionGeometry, pin.SE3 placement in the owner's frame, bounding radius [m])] of a shape."""
    M = placement(shape.pos, shape.rpy)
    t = shape.type
    if t == "sphere":
        return [(coal.Sphere(shape.radius), M, shape.radius)]
    if t == "capsule":
        return [(coal.Capsule(shape.radius, shape.length), M, shape.radius + 0.5 * shape.length)]
    if t == "cylinder":
        return [(coal.Cylinder(shape.radius, shape.length), M, math.hypot(shape.radius, 0.5 * shape.length))]
    if t == "box":
        size = np.asarray(shape.size, float)
        return [(coal.Box(*size), M, 0.5 * float(np.linalg.norm(size)))]
    if t == "plane":
        n = np.asarray(shape.normal, float)
        # coal.Halfspace(n, d) is the solid n . x <= d, its outside (free space) n . x > d
        return [(coal.Halfspace(M.rotation @ n, shape.offset + float(n @ (M.rotation.T @ M.translation))),
                 pin.SE3.Identity(), INF_RADIUS)]
    if t == "shell":
        return shell_staves(shape.radius, shape.length, shape.thickness, shape.segments, M)
    if t == "mesh":
        mesh = read_obj(shape.file, shape.scale)
        bvh = coal.BVHModelOBBRSS()
        bvh.beginModel(len(mesh.faces), len(mesh.vertices))
        bvh.addVertices(np.ascontiguousarray(mesh.vertices, float))
        bvh.addTriangles(np.ascontiguousarray(mesh.faces, np.int64))
        bvh.endModel()
        return [(bvh, M, float(np.linalg.norm(mesh.vertices, axis=1).max()))]
    raise ValueError(f"unknown collision shape type {t!r}")


def shell_staves(radius: float, length: float, thickness: float, segments: int, M: pin.SE3) -> list:
    """A cylindrical shell (inner ``radius``, wall ``thickness``, ``length`` along local z) as ``segments``
    boxes whose inner faces are tangent to the inner cylinder; chord width chosen so neighbours overlap."""
    rc = radius + 0.5 * thickness
    width = 2.0 * (radius + thickness) * math.tan(math.pi / segments) * 1.05
    out = []
    for k in range(segments):
        a = 2.0 * math.pi * k / segments
        R = pin.rpy.rpyToMatrix(0.0, 0.0, a)
        local = pin.SE3(R, np.array([rc * math.cos(a), rc * math.sin(a), 0.0]))
        size = (thickness, width, length)
        out.append((coal.Box(*size), M * local, 0.5 * math.sqrt(sum(s * s for s in size))))
    return out
