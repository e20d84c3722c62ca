"""The full-space results of the reduced coupled solve (reduction.py), in one compiled call after it: the vertex
velocities v_d (the free vertices' from z = (v_f, qdot_r), the attached ones' v_a = E qdot_r + t) and the
multipliers of the skeleton's held rows (prescribed joint velocities held as DOFs, reduction.hold) from their
reactions, with those rows' violation. The same operations as the numpy expressions it replaces
(lam[rows] = -reactions / coef, max |coef z_held - g|, the scatters into v_d and lam), without their ~10 calls
of 1-5 us each."""
from __future__ import annotations

import numpy as np

from redmax_ros.core.deformable.reduction import reactions_kernel
from redmax_ros.core.jit import njit


@njit
def unreduce(z, n_free, free_dof, att_dof, Ev, t, n_rows, rest, lam_rest, indptr, indices, dofs, saved, b_saved,
             coef, g_held, rows):
    """(lam (n_rows,), v_d (3N,), max |coef z[dofs] - g_held| (0 without held rows)): lam[rest] = lam_rest and,
    per held row rows[i] (reduced DOF dofs[i], coefficient coef[i], right-hand side g_held[i]), its multiplier
    -(A z - b)_i / coef[i] from the row's original values ``saved``, ``b_saved`` (reduction.hold); v_d[free_dof]
    = z[:n_free], v_d[att_dof] = Ev + t (Ev = E z[n_free:], by the caller's BLAS product)."""
    lam = np.empty(n_rows)
    for i in range(len(rest)):
        lam[rest[i]] = lam_rest[i]
    react = np.empty(len(dofs))
    reactions_kernel(indptr, indices, dofs, saved, b_saved, z, react)
    violation = 0.0
    for i in range(len(dofs)):
        lam[rows[i]] = -react[i] / coef[i]
        d = abs(coef[i] * z[dofs[i]] - g_held[i])
        if d > violation or d != d:  # np.max's: a NaN propagates
            violation = d
    v_d = np.empty(len(free_dof) + len(att_dof))
    for p in range(n_free):
        v_d[free_dof[p]] = z[p]
    for r in range(len(att_dof)):
        v_d[att_dof[r]] = Ev[r] + t[r]
    return lam, v_d, violation
