"""SceneSpec -> the compiled, frozen :class:`~redmax_ros.core.model.mechanism.Mechanism` (Pinocchio's Model,
MJX's Model): the Pinocchio model of the tree, sites, springs, loops, the coupling matrix J_rR of Eq. (9),
the reduced forces and limits (mechanism.py); joints Pinocchio cannot represent as carrier joints with a
configuration-dependent J_rR (Eq. 2.88-2.89, joint_maps.py); one position per velocity DOF for reports
(dof_positions.py). No cache, no pin.Data, no scratch: those live in step/workspace.py."""
