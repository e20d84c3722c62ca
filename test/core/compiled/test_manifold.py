"""redmax_ros/core/step/compiled/manifold.py against pin.integrate / pin.difference.

The kernels replay Pinocchio 4.1's liegroup formulas operation by operation, so they must agree
with Pinocchio to round-off: max abs error <= 1e-14 per entry (configurations are O(1): unit
quaternions / (cos, sin) pairs, positions within +-2 m; velocities up to 3 rad, 3 m). Inputs:
a chain holding every joint kind of the module (and a SphericalZYX FALLBACK joint, whose entries
must stay untouched), random configurations, velocities at scales from 1e-9 to 3 (rad, m) per
joint plus exactly zero and scales straddling every Taylor-branch threshold of Pinocchio, and
rotations near pi (angle pi - 1e-3 ... pi - 1e-9, antipodal quaternions).

Round trip: difference(q, integrate(q, v)) == v to 1e-12 for |rotation| < pi. That holds for
Pinocchio's formulas at the scales 0, 1e-9, 1e-3, 1, 3 used there (each joint's linear and
angular parts of the same magnitude), except Pinocchio's SO(2) log clamp for |angle| < ~1.5e-8
(see test_round_trip); near the branch thresholds (e.g. SE(2) log just above
|theta| = 1e-4, where (1 - cos theta) loses ~8 digits) Pinocchio's own round trip is only good to
a relative ~1e-8, so those scales are checked against Pinocchio only.
"""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core.step.compiled import manifold as mf

KIND_NAMES = {
    mf.REVOLUTE: "REVOLUTE", mf.REVOLUTE_UNBOUNDED: "REVOLUTE_UNBOUNDED", mf.PRISMATIC: "PRISMATIC",
    mf.HELICAL: "HELICAL", mf.SPHERICAL: "SPHERICAL", mf.FREEFLYER: "FREEFLYER",
    mf.TRANSLATION: "TRANSLATION", mf.UNIVERSAL: "UNIVERSAL", mf.PLANAR: "PLANAR",
}
TOL = 1e-14  # kernel vs Pinocchio, absolute
TOL_ROUND_TRIP = 1e-12  # difference(q, integrate(q, v)) vs v, absolute
ROUND_TRIP_SCALES = (0.0, 1e-9, 1e-3, 1.0, 3.0)
# every Pinocchio threshold: exp3 |v|^2 > 2^-13 (|v| ~ 1.105e-2), exp6 / log6 |w| ~ 1.22e-4,
# log3 |vec|^2 < 6.06e-6 (angle ~ 4.92e-3), SE2 log 1e-4, SE2 exp 1e-14, SO2 log tr > 1.99
THRESHOLD_SCALES = (1e-15, 1e-14 * 0.9, 1e-14 * 1.1, 9e-5, 1.1e-4, 1.2e-4, 1.25e-4, 4.9e-3, 4.95e-3,
                    0.011, 0.0111, 0.0999, 0.1001, 0.3)
NEAR_PI = (1e-3, 1e-6, 1e-9)  # pi - angle


def _chain(rng):
    """A chain with every joint kind of manifold.py (several variants each) and one FALLBACK."""
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    a2 = np.cross(axis, rng.standard_normal(3))
    a2 /= np.linalg.norm(a2)
    joints = [
        pin.JointModelRX(), pin.JointModelRY(), pin.JointModelRZ(),
        pin.JointModelRevoluteUnaligned(axis), pin.JointModelRUBX(), pin.JointModelRUBZ(),
        pin.JointModelRevoluteUnboundedUnaligned(), pin.JointModelPX(),
        pin.JointModelPrismaticUnaligned(axis), pin.JointModelHZ(0.05),
        pin.JointModelHelicalUnaligned(axis, -0.1), pin.JointModelSpherical(),
        pin.JointModelFreeFlyer(), pin.JointModelTranslation(), pin.JointModelUniversal(axis, a2),
        pin.JointModelPlanar(), pin.JointModelSphericalZYX(), pin.JointModelSpherical(),
        pin.JointModelFreeFlyer(), pin.JointModelPlanar(), pin.JointModelRUBY(),
    ]
    model = pin.Model()
    parent = 0
    for i, jm in enumerate(joints):
        parent = model.addJoint(parent, jm, pin.SE3.Random(), f"j{i}")
        model.appendBodyToJoint(parent, pin.Inertia.Random(), pin.SE3.Identity())
    # finite bounds for the free / planar / translation joints (randomConfiguration needs them)
    model.lowerPositionLimit = np.where(np.isfinite(model.lowerPositionLimit),
                                        np.maximum(model.lowerPositionLimit, -2.0), -2.0)
    model.upperPositionLimit = np.where(np.isfinite(model.upperPositionLimit),
                                        np.minimum(model.upperPositionLimit, 2.0), 2.0)
    return model


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(20240611)
    model = _chain(rng)
    kind = mf.joint_kinds(model)
    iq = np.array(model.idx_qs, dtype=np.int64)
    iv = np.array(model.idx_vs, dtype=np.int64)
    return model, kind, iq, iv, rng


def _blocks(model, kind):
    """Per joint: (kind, q slice, v slice, [tangent sub-blocks that share one magnitude])."""
    out = []
    for j in range(1, model.njoints):
        jm = model.joints[j]
        qs, vs = slice(jm.idx_q, jm.idx_q + jm.nq), slice(jm.idx_v, jm.idx_v + jm.nv)
        if kind[j] == mf.FREEFLYER:
            sub = [(0, 3), (3, 6)]
        elif kind[j] == mf.PLANAR:
            sub = [(0, 2), (2, 3)]
        elif kind[j] == mf.UNIVERSAL:
            sub = [(0, 1), (1, 2)]
        else:
            sub = [(0, jm.nv)]
        out.append((int(kind[j]), qs, vs, sub))
    return out


def _velocity(model, kind, rng, scale):
    """Random v whose every joint sub-block (linear / angular part, one angle) has norm `scale`."""
    v = np.zeros(model.nv)
    for _, _, vs, sub in _blocks(model, kind):
        for a, b in sub:
            d = rng.standard_normal(b - a)
            v[vs.start + a: vs.start + b] = scale * d / np.linalg.norm(d)
    return v


def _max_err_by_kind(model, kind, got, ref, which, errs):
    """Accumulate max |got - ref| per kind (which = 'q' or 'v' slices) into errs."""
    for k, qs, vs, _ in _blocks(model, kind):
        if k == mf.FALLBACK:
            continue
        s = qs if which == "q" else vs
        e = float(np.max(np.abs(got[s] - ref[s])))
        errs[k] = max(errs.get(k, 0.0), e)


def _fallback_mask(model, kind, which):
    m = np.zeros(model.nq if which == "q" else model.nv, dtype=bool)
    for k, qs, vs, _ in _blocks(model, kind):
        if k == mf.FALLBACK:
            m[qs if which == "q" else vs] = True
    return m


def _integrate(kind, iq, iv, q, v, fb_q):
    out = np.full(q.shape[0], np.nan)
    mf.integrate(kind, iq, iv, q, v, out)
    assert np.all(np.isnan(out[fb_q])), "FALLBACK entries must stay untouched"
    assert not np.any(np.isnan(out[~fb_q]))
    return out


def _difference(kind, iq, iv, q0, q1, fb_v):
    out = np.full(fb_v.shape[0], np.nan)
    mf.difference(kind, iq, iv, q0, q1, out)
    assert np.all(np.isnan(out[fb_v])), "FALLBACK entries must stay untouched"
    assert not np.any(np.isnan(out[~fb_v]))
    return out


def _report(title, errs):
    print(f"\n{title}: " + ", ".join(f"{KIND_NAMES[k]} {e:.1e}" for k, e in sorted(errs.items())))


def test_joint_kinds(setup):
    model, kind, _, _, _ = setup
    names = [model.joints[j].shortname() for j in range(model.njoints)]
    assert kind[0] == mf.FALLBACK
    assert set(kind[1:]) == set(KIND_NAMES) | {mf.FALLBACK}
    for j, name in enumerate(names):
        if name == "JointModelUniversal":
            assert kind[j] == mf.UNIVERSAL
        if name == "JointModelPlanar":
            assert kind[j] == mf.PLANAR
        if name == "JointModelSphericalZYX":
            assert kind[j] == mf.FALLBACK
    assert kind.dtype == np.int64 and kind.shape == (model.njoints,)


def test_integrate_matches_pinocchio(setup):
    model, kind, iq, iv, rng = setup
    fb_q, fb_v = _fallback_mask(model, kind, "q"), _fallback_mask(model, kind, "v")
    errs = {}
    for scale in ROUND_TRIP_SCALES + THRESHOLD_SCALES:
        for _ in range(6):
            q = pin.randomConfiguration(model)
            v = _velocity(model, kind, rng, scale)
            ref = pin.integrate(model, q, v)
            got = _integrate(kind, iq, iv, q, v, fb_q)
            _max_err_by_kind(model, kind, got, ref, "q", errs)
    # large velocities (|w| up to 3 pi: several turns) and near-pi rotations
    for scale in (math.pi - 1e-6, math.pi + 1e-6, 2 * math.pi, 3 * math.pi, 7.0):
        q = pin.randomConfiguration(model)
        v = _velocity(model, kind, rng, scale)
        _max_err_by_kind(model, kind, _integrate(kind, iq, iv, q, v, fb_q),
                         pin.integrate(model, q, v), "q", errs)
    # in place (out is q): same result
    q = pin.randomConfiguration(model)
    v = _velocity(model, kind, rng, 1.0)
    ref = _integrate(kind, iq, iv, q, v, fb_q)
    q_inplace = q.copy()
    mf.integrate(kind, iq, iv, q_inplace, v, q_inplace)
    assert np.array_equal(q_inplace[~fb_q], ref[~fb_q]) and np.array_equal(q_inplace[fb_q], q[fb_q])
    _report("integrate max abs error", errs)
    assert set(errs) == set(KIND_NAMES)
    assert max(errs.values()) <= TOL, errs


def test_difference_matches_pinocchio(setup):
    model, kind, iq, iv, rng = setup
    fb_q, fb_v = _fallback_mask(model, kind, "q"), _fallback_mask(model, kind, "v")
    errs = {}
    cases = []
    for _ in range(40):  # independent configurations: any relative rotation
        cases.append((pin.randomConfiguration(model), pin.randomConfiguration(model)))
    for scale in ROUND_TRIP_SCALES + THRESHOLD_SCALES:  # nearby configurations
        for _ in range(6):
            q0 = pin.randomConfiguration(model)
            cases.append((q0, pin.integrate(model, q0, _velocity(model, kind, rng, scale))))
    for d in NEAR_PI:  # relative rotations near pi, both sides
        for s in (-d, d):
            for _ in range(4):
                q0 = pin.randomConfiguration(model)
                cases.append((q0, pin.integrate(model, q0, _velocity(model, kind, rng, math.pi + s))))
    q0 = pin.randomConfiguration(model)
    cases.append((q0, q0.copy()))  # identical
    q1 = q0.copy()  # antipodal quaternions (same rotation)
    for k, qs, _, _ in _blocks(model, kind):
        if k == mf.SPHERICAL:
            q1[qs] *= -1.0
        elif k == mf.FREEFLYER:
            q1[qs.start + 3: qs.stop] *= -1.0
    cases.append((q0, q1))
    for q0, q1 in cases:
        ref = pin.difference(model, q0, q1)
        got = _difference(kind, iq, iv, q0, q1, fb_v)
        _max_err_by_kind(model, kind, got, ref, "v", errs)
    _report("difference max abs error", errs)
    assert set(errs) == set(KIND_NAMES)
    assert max(errs.values()) <= TOL, errs


def test_round_trip(setup):
    """difference(q, integrate(q, v)) == v (|rotation| < pi), both through the kernels.

    Pinocchio's SO2::log returns 0 when the rounded trace of R0^T R1 exceeds 2, which happens for
    |angle| below ~1.5e-8 (cos rounds to 1): there pin.difference(q, pin.integrate(q, v)) itself
    returns angle 0 (measured: ~2-7 % of the draws at 1e-9), so for REVOLUTE_UNBOUNDED / PLANAR
    the expected angle is 0 in exactly that case; the planar linear part is still recovered.
    The kernels' round trip is also compared with Pinocchio's (<= TOL).
    """
    model, kind, iq, iv, rng = setup
    fb_q, fb_v = _fallback_mask(model, kind, "q"), _fallback_mask(model, kind, "v")
    so2_angle = [vs.start + (2 if k == mf.PLANAR else 0)
                 for k, _, vs, _ in _blocks(model, kind) if k in (mf.PLANAR, mf.REVOLUTE_UNBOUNDED)]
    errs, errs_pin, clamped = {}, {}, 0
    for scale in ROUND_TRIP_SCALES:
        for _ in range(10):
            q = pin.randomConfiguration(model)
            v = _velocity(model, kind, rng, scale)
            q1 = _integrate(kind, iq, iv, q, v, fb_q)
            q1[fb_q] = q[fb_q]
            d = _difference(kind, iq, iv, q, q1, fb_v)
            expected = v.copy()
            for i in so2_angle:
                if d[i] == 0.0 and 0.0 < abs(v[i]) < 1.5e-8:  # SO2::log trace clamp (docstring)
                    expected[i] = 0.0
                    clamped += 1
            _max_err_by_kind(model, kind, d, expected, "v", errs)
            _max_err_by_kind(model, kind, d, pin.difference(model, q, pin.integrate(model, q, v)),
                             "v", errs_pin)
    _report("round trip max abs error", errs)
    _report("round trip vs Pinocchio's round trip", errs_pin)
    print(f"SO(2) trace clamps: {clamped}")
    assert max(errs.values()) <= TOL_ROUND_TRIP, errs
    assert max(errs_pin.values()) <= TOL, errs_pin
