"""Pinocchio models shared by test_recursive.py and test_pcg.py (deterministic, no pin.Data needed)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin


def random_placement(rng, scale=0.3) -> pin.SE3:
    R = pin.exp3(rng.normal(size=3))
    return pin.SE3(R, scale * rng.normal(size=3))


def random_inertia(rng) -> pin.Inertia:
    m = rng.uniform(0.5, 2.0)
    A = rng.normal(size=(3, 3))
    Ic = A @ A.T * 0.05 + 0.02 * np.eye(3)
    return pin.Inertia(m, 0.1 * rng.normal(size=3), Ic)


def _add(model, parent, jm, rng, name):
    j = model.addJoint(parent, jm, random_placement(rng), name)
    model.appendBodyToJoint(j, random_inertia(rng), pin.SE3.Identity())
    return j


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def chain(n=8, seed=0, armature=True) -> pin.Model:
    """Serial chain cycling through revolute joint flavours."""
    rng = np.random.default_rng(seed)
    m = pin.Model()
    kinds = [lambda: pin.JointModelRX(), lambda: pin.JointModelRY(), lambda: pin.JointModelRZ(),
             lambda: pin.JointModelRevoluteUnaligned(unit(rng.normal(size=3)))]
    parent = 0
    for k in range(n):
        parent = _add(m, parent, kinds[k % 4](), rng, f"j{k}")
    if armature:
        m.armature = rng.uniform(0.0, 0.1, size=m.nv)
    return m


def branching_tree(seed=1) -> pin.Model:
    """A root with three branches of mixed 1-DOF joints (prismatic, helical, unbounded revolute)."""
    rng = np.random.default_rng(seed)
    m = pin.Model()
    root = _add(m, 0, pin.JointModelRZ(), rng, "root")
    b1 = _add(m, root, pin.JointModelPX(), rng, "b1a")
    b1 = _add(m, b1, pin.JointModelRUBY(), rng, "b1b")
    _add(m, b1, pin.JointModelHZ(0.05), rng, "b1c")
    b2 = _add(m, root, pin.JointModelPrismaticUnaligned(unit(rng.normal(size=3))), rng, "b2a")
    _add(m, b2, pin.JointModelHelicalUnaligned(unit(rng.normal(size=3)), -0.1), rng, "b2b")
    _add(m, b2, pin.JointModelRUBZ(), rng, "b2c")
    b3 = _add(m, root, pin.JointModelRY(), rng, "b3a")
    _add(m, b3, pin.JointModelRX(), rng, "b3b")
    m.armature = rng.uniform(0.0, 0.1, size=m.nv)
    return m


def floating_spherical(seed=2) -> pin.Model:
    """Free flyer base, spherical (quaternion) joint, translation joint, revolute leaf."""
    rng = np.random.default_rng(seed)
    m = pin.Model()
    base = _add(m, 0, pin.JointModelFreeFlyer(), rng, "base")
    sph = _add(m, base, pin.JointModelSpherical(), rng, "ball")
    _add(m, sph, pin.JointModelRY(), rng, "leaf")
    tr = _add(m, base, pin.JointModelTranslation(), rng, "slider")
    _add(m, tr, pin.JointModelSpherical(), rng, "ball2")
    m.armature = rng.uniform(0.0, 0.1, size=m.nv)
    return m


def fallback_joints(seed=3) -> pin.Model:
    """Joints evaluated through Pinocchio's JointModel.calc (configuration-dependent S)."""
    rng = np.random.default_rng(seed)
    m = pin.Model()
    a = _add(m, 0, pin.JointModelPlanar(), rng, "planar")
    b = _add(m, a, pin.JointModelSphericalZYX(), rng, "zyx")
    c = _add(m, b, pin.JointModelUniversal(unit([1.0, 0.2, 0.0]), unit([0.0, 1.0, 0.3])), rng, "uni")
    comp = pin.JointModelComposite(pin.JointModelRX(), random_placement(rng))
    comp.addJoint(pin.JointModelRY(), random_placement(rng))
    _add(m, c, comp, rng, "composite")
    _add(m, b, pin.JointModelRZ(), rng, "leaf")
    m.armature = rng.uniform(0.0, 0.1, size=m.nv)
    return m


def humanoid() -> pin.Model:
    m = pin.buildSampleModelHumanoidRandom()
    m.armature = np.linspace(0.0, 0.05, m.nv)
    return m


def manipulator() -> pin.Model:
    m = pin.buildSampleModelManipulator()
    m.armature = np.linspace(0.01, 0.05, m.nv)
    return m


MODELS = {
    "chain": chain,
    "tree": branching_tree,
    "floating_spherical": floating_spherical,
    "fallback_joints": fallback_joints,
    "humanoid": humanoid,
    "manipulator": manipulator,
}


def random_state(model, rng):
    q = pin.integrate(model, pin.neutral(model), rng.normal(size=model.nv))
    return q, rng.normal(size=model.nv)


def dense_mass(model, data, q):
    M = pin.crba(model, data, q)
    return np.triu(M) + np.triu(M, 1).T
