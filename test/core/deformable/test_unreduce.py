"""deformable/unreduce.py: the full-space results of the reduced coupled solve in one compiled call equal, bit for
bit, the numpy expressions of the coupled step (lam[rest] = the solve's multipliers, lam[held rows] = -(A z - b)
on the held DOFs / coef via reduction.reactions, the held rows' violation max |coef z[dofs] - g|, v_d scattered
from the free vertices' z and the attached ones' E qdot_r + t)."""
import numpy as np
import scipy.sparse as sp

from redmax_ros.core.deformable import reduction
from redmax_ros.core.deformable.unreduce import unreduce


def test_unreduce_equals_the_numpy_expressions_bit_for_bit():
    rng = np.random.default_rng(3)
    n_free, n_r, m = 9, 5, 6  # free vertex DOFs, skeleton DOFs, skeleton rows
    n = n_free + n_r
    A = (sp.random(n, n, density=0.4, random_state=rng) + sp.eye(n)).tocsr()
    A.sort_indices()
    dofs = np.array([n_free + 1, n_free + 3], dtype=np.int64)  # held skeleton DOFs
    saved = np.concatenate([A.data[A.indptr[j]:A.indptr[j + 1]] for j in dofs])
    b_saved = rng.normal(size=len(dofs))
    rows = np.array([4, 1], dtype=np.int64)  # the held rows among the m
    rest = np.array([0, 2, 3, 5], dtype=np.int64)
    coef, g = np.array([2.0, -0.5]), rng.normal(size=2)
    z, lam_rest = rng.normal(size=n), rng.normal(size=len(rest))
    free_dof = rng.permutation(15)[:n_free].astype(np.int64)
    att_dof = np.setdiff1d(np.arange(15), free_dof).astype(np.int64)
    Ev, t = rng.normal(size=len(att_dof)), rng.normal(size=len(att_dof))

    lam, v_d, violation = unreduce(z, n_free, free_dof, att_dof, Ev, t, m, rest, lam_rest, A.indptr.astype(np.int64),
                                   A.indices.astype(np.int64), dofs, saved, b_saved, coef, g, rows)

    want_lam = np.empty(m)
    want_lam[rest] = lam_rest
    want_lam[rows] = -reduction.reactions(A.indptr, A.indices, dofs, saved, b_saved, z) / coef
    want_v = np.empty(15)
    want_v[free_dof] = z[:n_free]
    want_v[att_dof] = Ev + t
    assert lam.tobytes() == want_lam.tobytes()
    assert v_d.tobytes() == want_v.tobytes()
    assert violation == float(np.abs(coef * z[dofs] - g).max())
    # the reactions are A z - b on the held rows
    assert np.allclose(-lam[rows] * coef, A[dofs] @ z - b_saved, rtol=1e-14, atol=1e-14)
