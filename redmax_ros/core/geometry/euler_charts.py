"""Chart switching of the notes' three-angle spherical joint (Sueda's notes §2.5.5, Eq. 2.38-2.40, Table 3).

A chart ``abc`` (a, b, c in X, Y, Z) writes the joint rotation as R = exp(a q1) exp(b q2) exp(c q3)
(joints.ref_euler). Every chart is singular somewhere: a Tait-Bryan chart (a != c) where cos q2 = 0,
a proper Euler chart (a == c) where sin q2 = 0; there S loses rank and the mass matrix becomes singular.

**Which charts.** A joint with ``switch_charts: true`` uses its ``chart`` (the *home* chart, in which q0
is given) and one *partner* chart with the same first two axes: ``abc`` <-> ``aba`` (e.g. XYZ <-> XYX,
ZYZ <-> ZYX). Both singular sets are read off row a of R: the Tait-Bryan chart has |R[a,c]| = |sin q2|,
the proper Euler chart |R[a,a]| = |cos q2|, and since R[a,a]^2 + R[a,c]^2 <= 1 the two singular sets
are disjoint (where one chart is singular the other has |sin q2| or |cos q2| = 1, i.e. is best
conditioned).

**When.** The chart is a function of the rotation only (no hysteresis, so it never has to be stored
besides the configuration): the home chart while its q2 is at least ``MARGIN`` (30 deg) away from its
singularity, the partner chart inside that band, where the partner's q2 is at least 60 deg away from the
partner's own singularity. So the chart in use always has |cos q2| (Tait-Bryan) or |sin q2| (Euler)
>= sin 30 deg = 0.5 (S stays well conditioned). This is the notes' rule ("watch q2, switch before
det S gets too close to 0") with a fixed switching band.

**How** (Eq. 2.38-2.40): at a switch the new angles are read from R (Table 3, written here for every
chart with the permutation parity eps of (a, b, c)), and the rates are mapped so that the angular
velocity is unchanged, qdot_new = S_new^-1 S_old qdot_old (Eq. 2.40, top: the rotational rows of S, body
frame). The rotation and the angular velocity are continuous to round-off; the coordinates jump (as
Grassia's reparameterisation of spherical_exp does), so limits, joint springs and constant joint torques
on the angles are not allowed with switching.
"""
from __future__ import annotations

import math

import numpy as np
from redmax_ros.core.geometry.joints import ref_euler

MARGIN = math.radians(30.0)  # switch when q2 of the home chart is within this of its singularity [rad]
_THRESH = math.cos(MARGIN)  # |sin q2| (Tait-Bryan) or |cos q2| (Euler) above which the partner is used
_IDX = {"X": 0, "Y": 1, "Z": 2}


def _abc(chart):
    a, b, c = (_IDX[ch] for ch in chart.upper())
    return a, b, c


def _parity(a, b, c) -> float:
    """+1 for cyclic (X, Y, Z) orders, -1 otherwise; c may equal a (proper Euler): uses the third axis."""
    if c == a:
        c = 3 - a - b
    return 1.0 if (b - a) % 3 == 1 else -1.0


def is_tait_bryan(chart: str) -> bool:
    return chart[0].upper() != chart[2].upper()


def partner(chart: str) -> str:
    """The chart with the same first two axes and the other kind (abc <-> aba)."""
    a, b = chart[0].upper(), chart[1].upper()
    if is_tait_bryan(chart):
        return a + b + a
    return a + b + ({"X", "Y", "Z"} - {a, b}).pop()


def singularity_measure(chart: str, R) -> float:
    """|sin q2| (Tait-Bryan) or |cos q2| (proper Euler) of rotation R in ``chart``: 1 at the singularity."""
    a, _, c = _abc(chart)
    return abs(float(R[a, c]))


def select(home: str, R) -> str:
    """The chart to use at rotation R: ``home`` unless its q2 is within MARGIN of its singularity."""
    return home.upper() if singularity_measure(home, R) <= _THRESH else partner(home)


def angles(chart: str, R) -> np.ndarray:
    """(q1, q2, q3) with R = exp(a q1) exp(b q2) exp(c q3) (Table 3 / Eq. 2.38-2.39, any chart; q1, q3 in
    (-pi, pi], q2 in [-pi/2, pi/2] (Tait-Bryan) or [0, pi] (Euler)); R must not be at the singularity."""
    a, b, c = _abc(chart)
    eps = _parity(a, b, c)
    R = np.asarray(R, float)
    if c != a:  # Tait-Bryan: R[a,c] = eps s2, R[b,c] = -eps s1 c2, R[c,c] = c1 c2, R[a,b] = -eps c2 s3, R[a,a] = c2 c3
        q2 = math.atan2(eps * R[a, c], math.hypot(R[a, a], R[a, b]))
        q1 = math.atan2(-eps * R[b, c], R[c, c])
        q3 = math.atan2(-eps * R[a, b], R[a, a])
    else:  # proper Euler, k the third axis: R[a,a] = c2, R[b,a] = s1 s2, R[k,a] = -eps c1 s2, R[a,b] = s2 s3,
        k = 3 - a - b  # R[a,k] = eps s2 c3
        q2 = math.atan2(math.hypot(R[b, a], R[k, a]), R[a, a])
        q1 = math.atan2(R[b, a], -eps * R[k, a])
        q3 = math.atan2(R[a, b], eps * R[a, k])
    return np.array([q1, q2, q3])


def rotation_jacobian(chart: str, q) -> tuple:
    """(R, S_w): the rotation and the rotational rows of S (body angular velocity = S_w qdot)."""
    Q, S, _ = ref_euler(chart, q, np.zeros(3))
    return Q.rotation, S[3:]


def convert(old: str, new: str, q, qd) -> tuple:
    """Eq. 2.40: the same rotation and angular velocity in chart ``new``: (q_new, qdot_new)."""
    R, S_old = rotation_jacobian(old, q)
    q_new = angles(new, R)
    _, S_new = rotation_jacobian(new, q_new)
    return q_new, np.linalg.solve(S_new, S_old @ np.asarray(qd, float))
