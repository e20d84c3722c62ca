"""The step workspace: everything a step writes, kept apart from the frozen Mechanism.

As Pinocchio's ``model.createData()`` and MJX's ``Data``: a backend creates one :class:`Workspace` from
the Mechanism and passes it to every stage, ``f(mech, ws, ...)``. It holds

* ``data``: Pinocchio's ``pin.Data`` (the Pinocchio pipeline only; None for the data-free one, whose
  memory must stay O(n): pin 4.1's Data grows as nv^3);
* ``tree``: the recursive kinematics Context (dynamics/tree_kinematics.py) with its scratch;
* ``T``: the live J_rR of Eq. (9) (a copy of the Mechanism's; catalogue joint maps refresh it in place
  every step, Eq. 2.88), and :meth:`to_reduced`;
* ``cache``: per-prescription-set row layouts, site sets, the coupling rows of the PCG path, the
  zero-gravity model of the implicit Coriolis term;
* ``extras``: the workspace's runtime copy of the catalogue hooks (dynamics/catalogue_hooks.py);
* ``friction``: the friction stage's scratch (friction/contact.FrictionWork);
* ``deadline``: the running step's solvers/budget.Deadline (set by step.pipeline.step for the step's
  duration; None without a budget and between steps);
* ``bdf2``: the running step's step.scheme.Bdf2Point (integrator.scheme bdf2, set by step.pipeline.step for
  the step's duration; None for a BDF1 step and between steps).

A workspace is not thread-safe; two workspaces of one Mechanism step independently.
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.dynamics.tree_kinematics import Context
from redmax_ros.core.friction.contact import make_work


class Workspace:
    def __init__(self, mech, pin_data: bool):
        self.mech = mech
        self.data = mech.model.createData() if pin_data else None
        self.T = None if mech.T is None else np.array(mech.T, dtype=float)
        self.cache: dict = {}
        self.tree = Context(mech, self.T, self.cache)
        self.extras = None if mech.extras is None else mech.extras.runtime(mech)
        self.friction = None if mech.friction is None else make_work(mech, mech.friction, self.T)
        self.deadline = None
        self.bdf2 = None
        self.spring_ends = None  # BDF2: the maximal springs' ends (pa, pb) at q*, for pipeline.spring_miss
        # the QP of Eq. (5) with self-collision rows: "active-set" (solvers/active_set.py, ProxSuite when it does
        # not settle) or "proxsuite" (always; the comparison of redmax_bench hagfish)
        self.contact_qp = "active-set"
        if self.extras is not None:
            self.extras.at_state(self, mech.q0, 0.0)

    def to_reduced(self, vR: np.ndarray) -> np.ndarray:
        """qdot_r = J_rR qdot_R (Eq. 8-9) with the workspace's J_rR."""
        return vR if self.T is None else self.T @ vR

    def at_state(self, q: np.ndarray, t: float) -> None:
        """Make the configuration-dependent parts (J_rR of catalogue joint maps) those of the state (q, t):
        called when the simulation is reset or its state is set."""
        if self.extras is not None:
            self.extras.at_state(self, q, t)
