"""Configuration-space manifold operations of a Pinocchio model as numba kernels.

:func:`integrate` reproduces ``pin.integrate(model, q, v)`` and :func:`difference` reproduces
``pin.difference(model, q0, q1)`` joint by joint, for use inside a larger compiled kernel (a
compiled simulation step). Both take only plain arrays: the per-joint ``kind`` codes of
:func:`joint_kinds` and the joints' ``idx_q`` / ``idx_v`` (``model.idx_qs`` / ``model.idx_vs``).
Nothing is allocated: every joint works on scalars held in registers.

Each joint is mapped to the Lie group Pinocchio integrates it on (``LieGroupMap``):

===================================  ===========  =====  =====================================
kind                                 Lie group    nq/nv  configuration
===================================  ===========  =====  =====================================
REVOLUTE (RX/RY/RZ, unaligned)       R^1          1/1    angle [rad]
REVOLUTE_UNBOUNDED (RUBx, unaligned) SO(2)        2/1    (cos, sin)
PRISMATIC (PX/PY/PZ, unaligned)      R^1          1/1    displacement [m]
HELICAL (HX/HY/HZ, unaligned)        R^1          1/1    angle [rad]
SPHERICAL                            SO(3)        4/3    quaternion (x, y, z, w)
FREEFLYER                            SE(3)        7/6    (p [m], quaternion (x, y, z, w))
TRANSLATION                          R^3          3/3    p [m]
UNIVERSAL                            R^2          2/2    two angles [rad]
PLANAR                               SE(2)        4/3    (x [m], y [m], cos, sin)
===================================  ===========  =====  =====================================

Velocities are in the joint's local frame, linear part first: a free-flyer ``v = (v [m/s],
w [rad/s])`` (times the unit time step of ``integrate``), a planar joint ``(vx, vy, wz)``.

The formulas are those of Pinocchio 4.1 (the version this project pins), operation by operation,
so the results agree to round-off (most to the last bit; see ``test/core/compiled/test_manifold.py``):

* ``src/multibody/liegroup/vector-space.hxx``: ``q + v`` and ``q1 - q0``;
* ``src/multibody/liegroup/special-orthogonal.hxx``: SO(2) ``integrate_impl`` (rotation of the unit
  complex number then first-order renormalisation ``(3 - |z|^2) / 2``) and ``difference_impl``
  (``SO2::log``, with its ``asin`` branch for ``tr > 2 - 1e-2``); SO(3) ``integrate_impl``
  (``q * exp3(v)`` then ``quaternion::firstOrderNormalize``) and ``difference_impl``
  (``log3(conj(q0) * q1)``);
* ``src/multibody/liegroup/special-euclidean.hxx``: SE(2) ``exp`` / ``log`` (local-frame
  exponential, threshold ``|w| > 1e-14`` for the ``exp`` and ``|theta| < 1e-4`` for the Taylor
  branch of ``log``; Pinocchio does *not* renormalise the (cos, sin) pair after an SE(2) step) and
  SE(3) ``integrate_impl`` (``M * exp6(v)``, sign fix ``dot(q_new, q) < 0``, first-order
  normalisation) and ``difference_impl`` (``log6(conj(q0) * q1, conj(q0) * (p1 - p0))``);
* ``src/spatial/explog-quaternion.hxx``: ``quaternion::exp3`` (Taylor branch for
  ``|v|^2 <= eps^(1/4)``), ``quaternion::exp6`` (Taylor coefficients for ``|w| < eps^(1/4)``) and
  ``quaternion::log3`` (Taylor branch for ``|vec|^2 < eps^(1/3)``); ``src/spatial/log.hxx``:
  ``log6_impl::run(quaternion, vector)`` (Taylor ``beta`` for ``theta <= eps^(1/4)``);
* ``src/math/quaternion.hxx``: ``quaternion::firstOrderNormalize``;
* Eigen 3.4 ``Geometry/Quaternion.h`` (``_transformVector``: ``v + 2 w (u x v) + u x 2 (u x v)``)
  and ``Geometry/arch/Geometry_SIMD.h`` (the SSE2 quaternion product and its order of sums).

The exponential maps themselves (Rodrigues' formula, Murray et al. 1994) are those of Sueda's
RedMax notes §1.3, Eq. (1.10) and (1.29); Pinocchio computes them on unit quaternions.

All kernels are alias-safe per joint (every input of a joint is read before its output is
written), so ``integrate(kind, iq, iv, q, v, q)`` updates ``q`` in place. FALLBACK joints (any
Pinocchio joint not listed above, e.g. SphericalZYX, Composite, Mimic) are left untouched in
``out``; the caller handles them.
"""
from __future__ import annotations

import math

import numpy as np

from redmax_ros.core.jit import njit
from redmax_ros.core.solvers import recursive
from redmax_ros.core.solvers.recursive import (  # noqa: F401  (re-exported joint kinds)
    FALLBACK, FREEFLYER, HELICAL, PRISMATIC, REVOLUTE, REVOLUTE_UNBOUNDED, SPHERICAL, TRANSLATION)

# Joint kinds beyond those of recursive.py (which evaluates these joints through Pinocchio).
UNIVERSAL = 8  # JointModelUniversal: nq = nv = 2, additive
PLANAR = 9  # JointModelPlanar: nq = 4 (x, y, cos, sin), nv = 3 (vx, vy, wz), SE(2)

# Pinocchio's thresholds (double precision). TaylorSeriesExpansion<double>::precision<n>() is
# pow(eps, 1 / (n + 1)) (math/taylor-expansion.hxx), evaluated here with the same libm pow.
_EPS = float(np.finfo(np.float64).eps)
_EPS2 = _EPS * _EPS
_TS_PREC2 = math.pow(_EPS, 1.0 / 3.0)  # precision<2>() ~ 6.06e-6
_TS_PREC3 = math.pow(_EPS, 1.0 / 4.0)  # precision<3>() = 2^-13 ~ 1.22e-4
_SO2_ASIN_TR = 2.0 - 1e-2  # SO2::log switches from acos to asin above this trace
_SE2_EXP_TOL = 1e-14  # SE2::exp: |w| > 1e-14 uses the exact formula
_SE2_LOG_TOL = 1e-4  # SE2::log: |theta| < 1e-4 uses the Taylor series of alpha


def joint_kinds(model) -> np.ndarray:
    """Kind code of every joint of ``model`` ((njoints,) int64; index 0, the universe, FALLBACK).

    Uses :func:`redmax_ros.core.solvers.recursive._kind_of`, plus :data:`UNIVERSAL` and
    :data:`PLANAR` for Pinocchio's ``JointModelUniversal`` / ``JointModelPlanar``; every other joint
    (including a mimic joint, which ``_kind_of`` rejects) is :data:`FALLBACK`.
    ``JointModelRevoluteUnboundedUnaligned`` is mapped by name (REVOLUTE_UNBOUNDED) because
    ``_kind_of`` fails on it in pin 4.1 (its binding has no ``axis``).
    """
    kinds = np.full(model.njoints, FALLBACK, dtype=np.int64)
    for j in range(1, model.njoints):
        jm = model.joints[j]
        short = jm.shortname().replace("JointModel", "")
        if short == "Universal":
            kinds[j] = UNIVERSAL
        elif short == "Planar":
            kinds[j] = PLANAR
        elif short == "RevoluteUnboundedUnaligned":
            # _kind_of reads jm.extract().axis, which pin 4.1's Python binding of this joint lacks
            # (AttributeError); only the kind is needed here.
            kinds[j] = REVOLUTE_UNBOUNDED
        else:
            try:
                kinds[j] = recursive._kind_of(jm)[0]
            except NotImplementedError:  # mimic joints: not a manifold operation of their own
                kinds[j] = FALLBACK
    return kinds


# --------------------------------------------------------------------------------------------
# Scalar building blocks (Eigen's evaluation order, so that round-off matches)
# --------------------------------------------------------------------------------------------
@njit
def _sq3(x, y, z):
    """Eigen ``Vector3::squaredNorm``: (x^2 + y^2) + z^2."""
    return (x * x + y * y) + z * z


@njit
def _sq4(x, y, z, w):
    """Eigen ``Vector4::squaredNorm`` with SSE2 packets (x, y), (z, w): (x^2 + z^2) + (y^2 + w^2)."""
    return (x * x + z * z) + (y * y + w * w)


@njit
def _cross(a0, a1, a2, b0, b1, b2):
    """a x b."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit
def _quat_mul(ax, ay, az, aw, bx, by, bz, bw):
    """Hamilton product a * b, as Eigen's SSE2 ``quat_product`` for double orders the sums."""
    x = (aw * bx + ay * bz) - (az * by - ax * bw)
    y = (aw * by + ay * bw) + (az * bx - ax * bz)
    z = (aw * bz - ay * bx) + (az * bw + ax * by)
    w = (aw * bw - ay * by) - (az * bz + ax * bx)
    return x, y, z, w


@njit
def _quat_rotate(qx, qy, qz, qw, v0, v1, v2):
    """Eigen ``Quaternion * Vector3`` (``_transformVector``): uv = 2 (u x v); v + w uv + u x uv."""
    u0, u1, u2 = _cross(qx, qy, qz, v0, v1, v2)
    u0, u1, u2 = u0 + u0, u1 + u1, u2 + u2
    c0, c1, c2 = _cross(qx, qy, qz, u0, u1, u2)
    return (v0 + qw * u0) + c0, (v1 + qw * u1) + c1, (v2 + qw * u2) + c2


@njit
def _first_order_normalize(x, y, z, w):
    """Pinocchio ``quaternion::firstOrderNormalize``: q * (3 - |q|^2) / 2."""
    alpha = (3.0 - _sq4(x, y, z, w)) / 2.0
    return x * alpha, y * alpha, z * alpha, w * alpha


@njit
def _exp3(v0, v1, v2):
    """Pinocchio ``quaternion::exp3``: unit quaternion (x, y, z, w) of the rotation vector v [rad].

    Angle-axis (cos(t/2), sin(t/2) v/t) with t = sqrt(|v|^2 + eps^2) when |v|^2 > eps^(1/4), else
    the order-4 Taylor expansion in t/2.
    """
    t2 = _sq3(v0, v1, v2)
    if t2 > _TS_PREC3:
        t = math.sqrt(t2 + _EPS2)
        ha = 0.5 * t
        s = math.sin(ha)
        return s * (v0 / t), s * (v1 / t), s * (v2 / t), math.cos(ha)
    t2_2 = t2 / 4.0  # (theta / 2)^2
    a = 0.5 * ((1.0 - t2_2 / 6.0) + t2_2 * t2_2 / 120.0)
    return a * v0, a * v1, a * v2, (1.0 - t2_2 / 2.0) + t2_2 * t2_2 / 24.0


@njit
def _log3(x, y, z, w):
    """Pinocchio ``quaternion::log3(quat, theta)``: rotation vector [rad] (|.| <= pi) and angle.

    Returns (r0, r1, r2, theta). Taylor branch for |vec|^2 < eps^(1/3).
    """
    norm_squared = _sq3(x, y, z)
    norm = math.sqrt(norm_squared + _EPS2)
    pos_neg = 1.0 if w >= 0.0 else -1.0
    wp = pos_neg * w
    xp, yp, zp = pos_neg * x, pos_neg * y, pos_neg * z
    if norm_squared < _TS_PREC2:
        y_x = norm / wp
        y_x_sq = norm_squared / (wp * wp)
        theta = 2.0 * (1.0 - y_x_sq / 3.0) * y_x
        th2_2 = theta * theta / 4.0
        inv_sinc = 2.0 * ((1.0 + th2_2 / 6.0) + 7.0 / 360.0 * th2_2 * th2_2)
    else:
        theta_2 = math.atan2(norm, wp)  # in [0, pi/2]
        theta = 2.0 * theta_2
        inv_sinc = theta / math.sin(theta_2)
    return inv_sinc * xp, inv_sinc * yp, inv_sinc * zp, theta


@njit
def _so2_log(c, s_lower, s_upper):
    """Pinocchio ``SO2::log`` of R = [[c, s_upper], [s_lower, c]] (angle [rad] in [-pi, pi])."""
    tr = c + c
    if tr > 2.0:
        return 0.0
    if tr < -2.0:
        return math.pi if s_lower >= 0.0 else -math.pi
    if tr > _SO2_ASIN_TR:
        return math.asin((s_lower - s_upper) / 2.0)
    return math.acos(tr / 2.0) if s_lower >= 0.0 else -math.acos(tr / 2.0)


# --------------------------------------------------------------------------------------------
# Kernels
# --------------------------------------------------------------------------------------------
@njit
def integrate(kind, idx_q, idx_v, q, v, out):
    """``out = pin.integrate(model, q, v)`` for every non-FALLBACK joint (q (nq,), v (nv,)).

    ``kind``, ``idx_q``, ``idx_v`` are (njoints,) arrays (:func:`joint_kinds`, ``model.idx_qs``,
    ``model.idx_vs``); joint 0 (the universe) is skipped and FALLBACK joints' entries of ``out`` are
    left untouched. Per joint (Pinocchio 4.1 liegroup ``integrate_impl``, see the module docstring):
    vector spaces ``q + v``; SO(2) rotation of (cos, sin) by ``v`` then first-order renormalisation;
    SO(3) ``q * exp3(v)`` then ``firstOrderNormalize``; SE(3) ``M(q) * exp6(v)`` with ``v = (linear,
    angular)`` in the local frame, sign fix and ``firstOrderNormalize``; SE(2) ``M(q) * exp(v)`` with
    ``v = (vx, vy, wz)`` in the local frame. ``out`` may be ``q`` (in-place update).
    """
    for j in range(1, kind.shape[0]):
        k = kind[j]
        iq = idx_q[j]
        iv = idx_v[j]
        if k == REVOLUTE or k == PRISMATIC or k == HELICAL:
            out[iq] = q[iq] + v[iv]
        elif k == TRANSLATION:
            for i in range(3):
                out[iq + i] = q[iq + i] + v[iv + i]
        elif k == UNIVERSAL:
            for i in range(2):
                out[iq + i] = q[iq + i] + v[iv + i]
        elif k == REVOLUTE_UNBOUNDED:
            ca = q[iq]
            sa = q[iq + 1]
            om = v[iv]
            cw = math.cos(om)
            sw = math.sin(om)
            c = cw * ca - sw * sa
            s = sw * ca + cw * sa
            alpha = (3.0 - (c * c + s * s)) / 2.0
            out[iq] = c * alpha
            out[iq + 1] = s * alpha
        elif k == SPHERICAL:
            ex, ey, ez, ew = _exp3(v[iv], v[iv + 1], v[iv + 2])
            x, y, z, w = _quat_mul(q[iq], q[iq + 1], q[iq + 2], q[iq + 3], ex, ey, ez, ew)
            x, y, z, w = _first_order_normalize(x, y, z, w)
            out[iq] = x
            out[iq + 1] = y
            out[iq + 2] = z
            out[iq + 3] = w
        elif k == FREEFLYER:
            px, py, pz = q[iq], q[iq + 1], q[iq + 2]
            qx, qy, qz, qw = q[iq + 3], q[iq + 4], q[iq + 5], q[iq + 6]
            l0, l1, l2 = v[iv], v[iv + 1], v[iv + 2]
            w0, w1, w2 = v[iv + 3], v[iv + 4], v[iv + 5]
            # quaternion::exp6: translation part of exp of the twist (l, w)
            t2 = _sq3(w0, w1, w2) + _EPS2
            t = math.sqrt(t2)
            if t < _TS_PREC3:
                a_wxv = 0.5 - t2 / 24.0
                a_w2 = 1.0 / 6.0 - t2 / 120.0
            else:
                inv_t2 = 1.0 / t2
                a_wxv = (1.0 - math.cos(t)) * inv_t2
                a_w2 = (t - math.sin(t)) * inv_t2 / t
            c0, c1, c2 = _cross(w0, w1, w2, l0, l1, l2)
            d0, d1, d2 = _cross(w0, w1, w2, c0, c1, c2)
            e0 = (l0 + a_wxv * c0) + a_w2 * d0
            e1 = (l1 + a_wxv * c1) + a_w2 * d1
            e2 = (l2 + a_wxv * c2) + a_w2 * d2
            ex, ey, ez, ew = _exp3(w0, w1, w2)
            # M * exp6(v): p + R e, quat * exp3(w)
            r0, r1, r2 = _quat_rotate(qx, qy, qz, qw, e0, e1, e2)
            x, y, z, w = _quat_mul(qx, qy, qz, qw, ex, ey, ez, ew)
            if (x * qx + z * qz) + (y * qy + w * qw) < 0.0:
                x, y, z, w = -x, -y, -z, -w
            x, y, z, w = _first_order_normalize(x, y, z, w)
            out[iq] = r0 + px
            out[iq + 1] = r1 + py
            out[iq + 2] = r2 + pz
            out[iq + 3] = x
            out[iq + 4] = y
            out[iq + 5] = z
            out[iq + 6] = w
        elif k == PLANAR:
            tx, ty, c0, s0 = q[iq], q[iq + 1], q[iq + 2], q[iq + 3]
            vx, vy, om = v[iv], v[iv + 1], v[iv + 2]
            cv = math.cos(om)
            sv = math.sin(om)
            # SE2::exp: R = [[cv, -sv], [sv, cv]], t = ((-vy, vx) - (-vy R.col(0) + vx R.col(1))) / w
            if math.fabs(om) > _SE2_EXP_TOL:
                ex = (-vy - (-vy * cv + vx * -sv)) / om
                ey = (vx - (-vy * sv + vx * cv)) / om
            else:
                ex = vx
                ey = vy
            # integrate_impl: head = R0 t + t0, tail = R0 R.col(0); no renormalisation
            out[iq] = (c0 * ex + -s0 * ey) + tx
            out[iq + 1] = (s0 * ex + c0 * ey) + ty
            out[iq + 2] = c0 * cv + -s0 * sv
            out[iq + 3] = s0 * cv + c0 * sv


@njit
def difference(kind, idx_q, idx_v, q0, q1, out):
    """``out = pin.difference(model, q0, q1)`` for every non-FALLBACK joint (out (nv,)).

    Same arguments as :func:`integrate`; FALLBACK joints' entries of ``out`` are left untouched.
    Per joint (Pinocchio 4.1 liegroup ``difference_impl``): vector spaces ``q1 - q0``; SO(2)
    ``SO2::log(R0^T R1)`` [rad]; SO(3) ``log3(conj(q0) * q1)`` [rad]; SE(3) ``log6`` of
    ``M(q0)^-1 M(q1)`` (linear part first, local frame of q0); SE(2) ``SE2::log`` of
    ``M(q0)^-1 M(q1)`` as (vx, vy, wz).
    """
    for j in range(1, kind.shape[0]):
        k = kind[j]
        iq = idx_q[j]
        iv = idx_v[j]
        if k == REVOLUTE or k == PRISMATIC or k == HELICAL:
            out[iv] = q1[iq] - q0[iq]
        elif k == TRANSLATION:
            for i in range(3):
                out[iv + i] = q1[iq + i] - q0[iq + i]
        elif k == UNIVERSAL:
            for i in range(2):
                out[iv + i] = q1[iq + i] - q0[iq + i]
        elif k == REVOLUTE_UNBOUNDED:
            a0, b0 = q0[iq], q0[iq + 1]
            a1, b1 = q1[iq], q1[iq + 1]
            c = a0 * a1 + b0 * b1
            s = a0 * b1 - b0 * a1
            out[iv] = _so2_log(c, s, -s)
        elif k == SPHERICAL:
            x, y, z, w = _quat_mul(-q0[iq], -q0[iq + 1], -q0[iq + 2], q0[iq + 3],
                                   q1[iq], q1[iq + 1], q1[iq + 2], q1[iq + 3])
            r0, r1, r2, _ = _log3(x, y, z, w)
            out[iv] = r0
            out[iv + 1] = r1
            out[iv + 2] = r2
        elif k == FREEFLYER:
            cx, cy, cz, cw = -q0[iq + 3], -q0[iq + 4], -q0[iq + 5], q0[iq + 6]  # conj(q0)
            p0, p1, p2 = _quat_rotate(cx, cy, cz, cw, q1[iq] - q0[iq], q1[iq + 1] - q0[iq + 1],
                                      q1[iq + 2] - q0[iq + 2])
            x, y, z, w = _quat_mul(cx, cy, cz, cw, q1[iq + 3], q1[iq + 4], q1[iq + 5], q1[iq + 6])
            # log6_impl::run(quat, vec)
            w0, w1, w2, theta = _log3(x, y, z, w)
            t2 = _sq3(w0, w1, w2)
            if theta <= _TS_PREC3:
                beta = (1.0 / 3.0 - (t2 / 4.0) / 45.0) / 4.0
            else:
                ct_2 = w if w >= 0.0 else -w
                st_2 = math.sqrt(_sq3(x, y, z) + _EPS2)
                beta = 1.0 / t2 - ct_2 / st_2 * 0.5 / theta
            c0, c1, c2 = _cross(w0, w1, w2, p0, p1, p2)
            d0, d1, d2 = _cross(w0, w1, w2, c0, c1, c2)
            out[iv] = (p0 - 0.5 * c0) + beta * d0
            out[iv + 1] = (p1 - 0.5 * c1) + beta * d1
            out[iv + 2] = (p2 - 0.5 * c2) + beta * d2
            out[iv + 3] = w0
            out[iv + 4] = w1
            out[iv + 5] = w2
        elif k == PLANAR:
            c0, s0 = q0[iq + 2], q0[iq + 3]
            c1, s1 = q1[iq + 2], q1[iq + 3]
            dx = q1[iq] - q0[iq]
            dy = q1[iq + 1] - q0[iq + 1]
            # R = R0^T R1, p = R0^T (t1 - t0)
            r00 = c0 * c1 + s0 * s1
            r10 = -s0 * c1 + c0 * s1
            r01 = c0 * -s1 + s0 * c1
            px = c0 * dx + s0 * dy
            py = -s0 * dx + c0 * dy
            # SE2::log
            t = _so2_log(r00, r10, r01)
            tabs = math.fabs(t)
            t2 = t * t
            if tabs < _SE2_LOG_TOL:
                alpha = (1.0 - t2 / 12.0) - t2 * t2 / 720.0
            else:
                alpha = tabs * math.sin(tabs) / (2.0 * (1.0 - math.cos(tabs)))
            out[iv] = alpha * px + t / 2.0 * py
            out[iv + 1] = alpha * py + -t / 2.0 * px
            out[iv + 2] = t
