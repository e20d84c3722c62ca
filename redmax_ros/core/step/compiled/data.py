"""The compiled step's Data (MJX's ``Data``, Pinocchio's ``model.createData()``): the preallocated workspace
of one Mechanism for one set of prescriptions, plus that set's constant row layout, as flat arrays
(:func:`build_data`), unpacked inside numba by :func:`data_views` into the namedtuple :data:`Data`.
Nothing is allocated per step. A Data is rebuilt (and cached by the backend) only when the set of
prescribed joints and sites changes, because the number of bilateral rows does.

Row layout (as dynamics/constraints.row_layout): loop rows first, then the prescribed joints' rows (constant
rows of J_rR, Eq. 7), then the prescribed sites' rows (P J_site J_rR, P the site's axes).
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np

from redmax_ros.core.jit import njit_inline
from redmax_ros.core.step.compiled.packing import f1, f2, f3, i1, i2, pack

DATA_SPEC = (
    # kinematics (world frame at the world origin, linear first: recursive.py's convention)
    ("jR", "f", 3), ("jp", "f", 2), ("Sl", "f", 2), ("c_local", "f", 2), ("R", "f", 3), ("p", "f", 2),
    ("St", "f", 2), ("I", "f", 3), ("ov", "f", 2), ("acc", "f", 2), ("W", "f", 2), ("ext", "f", 2),
    ("F", "f", 2), ("X", "f", 2),
    # forces and the LHS/RHS of Eq. (2)
    ("spring_f", "f", 2), ("spring_C", "f", 3), ("blocks", "f", 3), ("A", "f", 2), ("b", "f", 1),
    ("AR", "f", 2), ("bR", "f", 1), ("dq", "f", 1), ("v_r", "f", 1),
    # rows: G qdot_R = g (m rows), their multipliers; limits lo <= C qdot_R <= hi
    ("G", "f", 2), ("g", "f", 1), ("lam", "f", 1), ("lo", "f", 1), ("hi", "f", 1), ("mu", "f", 1),
    ("G_joints", "f", 2), ("joint_dofs", "i", 1), ("free_mask", "f", 1),
    ("site_ids", "i", 1), ("site_k", "i", 1), ("site_P", "f", 3), ("Jpt", "f", 3), ("held", "i", 1),
    # outputs of the step
    ("v_hyper", "f", 1), ("q_new", "f", 1), ("v_new", "f", 1), ("effort", "f", 1), ("site_force", "f", 2),
    # scalars: see OUT_* below
    ("out", "f", 1),
    # scratch: spring end positions, reduced loop rows, a configuration, a velocity
    ("pa", "f", 2), ("pb", "f", 2), ("Gr_loop", "f", 2), ("q_tmp", "f", 1), ("step_v", "f", 1),
    # the KKT solve's factors (solvers/kkt.kkt_solve_into)
    ("kkt_L", "f", 2), ("kkt_Y", "f", 2), ("kkt_S", "f", 2), ("kkt_LS", "f", 2), ("kkt_y", "f", 1),
    # the rows of a prescribed site, reduced coordinates (3, nv)
    ("site_rows", "f", 2),
    # loop residuals phi (nl,) and the loop sites' differences (3L,)
    ("phi", "f", 1), ("dx", "f", 1),
    # the chord projection's factors and steps (dynamics/stabilization.chord_factor_into, chord_step_into)
    ("chord_KK", "f", 2), ("chord_L", "f", 2), ("chord_y", "f", 1), ("chord_dq", "f", 1), ("chord_out", "f", 1),
    # small scratch of the force stage
    ("x3", "f", 1), ("C33", "f", 2),
    # the springs' 3x3 stiffness and damping, lengths (dynamics/springs.spring_kernel), site velocities
    ("spring_K", "f", 3), ("spring_D", "f", 3), ("spring_l", "f", 1), ("V", "f", 2),
    # the joint-limit active set (limits.py): rows [G; C_W], right-hand side, multipliers, KKT factors, and the
    # working set per limit row (0 free, -1 at its lower bound, +1 at its upper bound)
    ("Gx", "f", 2), ("gx", "f", 1), ("lamx", "f", 1), ("kkt_Yx", "f", 2), ("kkt_Sx", "f", 2), ("kkt_LSx", "f", 2),
    ("wset", "f", 1),
    # BDF2 (step/scheme.py, compiled/scheme.py): q^ and q* (nq,), v* and v^ hyper-reduced (ndof,), v^ reduced,
    # q* (-) q^ and q_k (-) q_k-1 (nv,), twists of v^ and of q* (-) q^ (njoints, 6), site displacements x* - x^ (S, 3)
    ("q_base", "f", 1), ("q_lin", "f", 1), ("v_lin", "f", 1), ("v_mom_h", "f", 1), ("v_mom", "f", 1),
    ("back", "f", 1), ("bdf_d", "f", 1), ("ovm", "f", 2), ("ovb", "f", 2), ("Xf", "f", 2),
    # A's elimination tree (ndof + 1: the last entry 1 = the L^T D L path) and chains, solvers/kkt.tree_structure;
    # kkt_par[0] = -2 until first made
    ("kkt_par", "i", 1), ("kkt_allowed", "i", 2),
    # the span of rows each row of the Schur solve's Y can be nonzero on (2, ndof), solvers/kkt.kkt_solve_tree_into
    ("kkt_span", "i", 2),
    # St transposed (6, nv) for the composite-rigid-body rows (tree_forces.crba_runs_kernel); the KKT residual (ndof,)
    ("StT", "f", 2), ("kkt_r", "f", 1),
    # the columns of a loop row's nonzeros (ndof,), dynamics/stabilization.chord_factor_into
    ("chord_nz", "i", 1),
)

Data = namedtuple("Data", [n for n, _, _ in DATA_SPEC])

# indices of Data.out
# OUT_ORDER: the order of the step taken, 1 (BDF1, Eq. 2) or 2 (BDF2 kept by the order control, step/scheme.py)
OUT_E_KIN, OUT_E_POT, OUT_E_SPRING, OUT_VIOL_POS, OUT_VIOL_VEL, OUT_RESIDUAL, OUT_STAGE, OUT_ITERS, OUT_ORDER = range(9)
N_OUT = 9


@njit_inline
def data_views(f, i, t):
    """The Data namedtuple of views into the packed buffers (DATA_SPEC order)."""
    return Data(f3(f, t, 0), f2(f, t, 1), f2(f, t, 2), f2(f, t, 3), f3(f, t, 4), f2(f, t, 5),
                f2(f, t, 6), f3(f, t, 7), f2(f, t, 8), f2(f, t, 9), f2(f, t, 10), f2(f, t, 11),
                f2(f, t, 12), f2(f, t, 13),
                f2(f, t, 14), f3(f, t, 15), f3(f, t, 16), f2(f, t, 17), f1(f, t, 18),
                f2(f, t, 19), f1(f, t, 20), f1(f, t, 21), f1(f, t, 22),
                f2(f, t, 23), f1(f, t, 24), f1(f, t, 25), f1(f, t, 26), f1(f, t, 27), f1(f, t, 28),
                f2(f, t, 29), i1(i, t, 30), f1(f, t, 31),
                i1(i, t, 32), i1(i, t, 33), f3(f, t, 34), f3(f, t, 35), i1(i, t, 36),
                f1(f, t, 37), f1(f, t, 38), f1(f, t, 39), f1(f, t, 40), f2(f, t, 41),
                f1(f, t, 42),
                f2(f, t, 43), f2(f, t, 44), f2(f, t, 45), f1(f, t, 46), f1(f, t, 47),
                f2(f, t, 48), f2(f, t, 49), f2(f, t, 50), f2(f, t, 51), f1(f, t, 52),
                f2(f, t, 53),
                f1(f, t, 54), f1(f, t, 55),
                f2(f, t, 56), f2(f, t, 57), f1(f, t, 58), f1(f, t, 59), f1(f, t, 60),
                f1(f, t, 61), f2(f, t, 62),
                f3(f, t, 63), f3(f, t, 64), f1(f, t, 65), f2(f, t, 66),
                f2(f, t, 67), f1(f, t, 68), f1(f, t, 69), f2(f, t, 70), f2(f, t, 71), f2(f, t, 72),
                f1(f, t, 73),
                f1(f, t, 74), f1(f, t, 75), f1(f, t, 76), f1(f, t, 77), f1(f, t, 78),
                f1(f, t, 79), f1(f, t, 80), f2(f, t, 81), f2(f, t, 82), f2(f, t, 83),
                i1(i, t, 84), i2(i, t, 85), i2(i, t, 86),
                f2(f, t, 87), f1(f, t, 88), i1(i, t, 89))


def build_data(mech, model, joints: tuple, sites: tuple, site_axes: dict, T) -> "Packed":
    """The workspace for ``mech`` (its packed Model ``model``) with prescribed ``joints`` and ``sites`` (names,
    in command order) and ``site_axes`` {site: (k,3)} (default: x, y, z). ``T``: the live J_rR or None."""
    nv, nq, ndof = mech.nv, mech.nq, mech.ndof
    nj = mech.model.njoints
    S = len(mech.site_names)
    P = len(mech.spring_ab)
    nl = sum(len(ax) for ax in mech.loop_axes) if len(mech.loop_ab) else 0
    # prescribed joints: identity rows on their reduced DOFs, projected by J_rR (constraints.prescribed_joint_rows)
    dofs = [d for name in joints for d in range(mech.joint_index[name].idx_v,
                                                    mech.joint_index[name].idx_v + mech.joint_index[name].nv)]
    Gr = np.zeros((len(dofs), nv))
    Gr[np.arange(len(dofs)), dofs] = 1.0
    Gj = Gr if T is None else Gr @ T
    mask = np.ones(nv)
    mask[dofs] = 0.0
    held = set()  # hyper-reduced DOFs moved by the prescribed joints (constraints.held_dofs)
    for d in dofs:
        held.update([d] if T is None else np.flatnonzero(T[d]).tolist())
    site_ids = [mech.site_index[n] for n in sites]
    site_P = np.zeros((len(sites), 3, 3))
    site_k = []
    for k, n in enumerate(sites):
        ax = None if not site_axes else site_axes.get(n)
        ax = np.eye(3) if ax is None else np.asarray(ax, float).reshape(-1, 3)
        site_P[k, :len(ax)] = ax
        site_k.append(len(ax))
    m = nl + len(dofs) + sum(site_k)
    nlim = len(mech.limited)
    values = dict(
        jR=np.tile(np.eye(3), (nj, 1, 1)), jp=np.zeros((nj, 3)), Sl=model["Sl0"].copy(), c_local=np.zeros((nj, 6)),
        R=np.tile(np.eye(3), (nj, 1, 1)), p=np.zeros((nj, 3)), St=np.zeros((nv, 6)), I=np.zeros((nj, 6, 6)),
        ov=np.zeros((nj, 6)), acc=np.zeros((nj, 6)), W=np.zeros((nj, 6)), ext=np.zeros((nj, 6)),
        F=np.zeros((nj, 6)), X=np.zeros((S, 3)),
        spring_f=np.zeros((P, 3)), spring_C=np.zeros((P, 3, 3)), blocks=np.zeros((nj, 6, 6)),
        A=np.zeros((nv, nv)), b=np.zeros(nv), AR=np.zeros((ndof, ndof)), bR=np.zeros(ndof), dq=np.zeros(nv),
        v_r=np.zeros(nv),
        G=np.zeros((m, ndof)), g=np.zeros(m), lam=np.zeros(m), lo=np.zeros(nlim), hi=np.zeros(nlim),
        mu=np.zeros(nlim),
        G_joints=Gj.reshape(len(dofs), ndof), joint_dofs=np.array(dofs, np.int64), free_mask=mask,
        site_ids=np.array(site_ids, np.int64), site_k=np.array(site_k, np.int64), site_P=site_P,
        Jpt=np.zeros((max(2 * len(mech.loop_ab), len(sites)), 3, nv)), held=np.array(sorted(held), np.int64),
        v_hyper=np.zeros(ndof), q_new=np.zeros(nq), v_new=np.zeros(nv), effort=np.zeros(nv),
        site_force=np.zeros((len(sites), 3)), out=np.zeros(N_OUT),
        kkt_L=np.zeros((ndof, ndof)), kkt_Y=np.zeros((ndof, m)), kkt_S=np.zeros((m, m)), kkt_LS=np.zeros((m, m)),
        kkt_y=np.zeros(ndof), kkt_par=np.full(ndof + 1, -2, np.int64), kkt_allowed=np.zeros((ndof, ndof), np.int64),
        kkt_span=np.zeros((2, ndof), np.int64),
        site_rows=np.zeros((3, nv)),
        phi=np.zeros(nl), dx=np.zeros(3 * len(mech.loop_ab)),
        chord_KK=np.zeros((nl + len(held), nl + len(held))), chord_L=np.zeros((nl + len(held), nl + len(held))),
        chord_y=np.zeros(nl + len(held)), chord_dq=np.zeros(ndof), chord_out=np.zeros(nv),
        x3=np.zeros(3), C33=np.zeros((3, 3)),
        Gx=np.zeros((m + nlim, ndof)), gx=np.zeros(m + nlim), lamx=np.zeros(m + nlim),
        kkt_Yx=np.zeros((ndof, m + nlim)), kkt_Sx=np.zeros((m + nlim, m + nlim)),
        kkt_LSx=np.zeros((m + nlim, m + nlim)), wset=np.zeros(nlim),
        spring_K=np.zeros((P, 3, 3)), spring_D=np.zeros((P, 3, 3)), spring_l=np.zeros(P), V=np.zeros((S, 3)),
        pa=np.zeros((P, 3)), pb=np.zeros((P, 3)), Gr_loop=np.zeros((nl, nv)), q_tmp=np.zeros(nq), step_v=np.zeros(nv),
        q_base=np.zeros(nq), q_lin=np.zeros(nq), v_lin=np.zeros(ndof), v_mom_h=np.zeros(ndof), v_mom=np.zeros(nv),
        back=np.zeros(nv), bdf_d=np.zeros(nv), ovm=np.zeros((nj, 6)), ovb=np.zeros((nj, 6)), Xf=np.zeros((S, 3)),
        StT=np.zeros((6, nv)), kkt_r=np.zeros(ndof), chord_nz=np.zeros(ndof, np.int64),
    )
    return pack(DATA_SPEC, values)
