"""The stages of Eq. (2): kinematics on pin.Data (kinematics.py) and on the recursive passes without it
(tree_kinematics.py), the LHS/RHS of Eq. (2) (forces.py; tree_forces.py for the data-free pipeline), springs
(springs.py), the constraint rows of Eq. (5)-(7) (constraints.py), loop post-stabilization (stabilization.py),
energies (energy.py) and the runtime hooks of the catalogue features (catalogue_hooks.py)."""
