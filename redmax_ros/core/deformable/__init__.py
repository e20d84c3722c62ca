"""Deformable bodies beside the reduced coordinates (issue 15): mass-spring strings and co-rotated linear
tetrahedral FEM with lumped mass and Rayleigh damping, their attachment rows to the articulated skeleton, and
the coupled sparse solve of RedMax's deformable coupling (Wang et al. 2019, §4, the equation after Eq. 5:
M_d qdot_d = f_d with G_m J_mr qdot_r + G_d qdot_d = 0; Sueda's notes, deformable coupling).

Layer: right above geometry (errors -> geometry -> deformable -> scene -> ...): pure numpy/scipy mathematics
that knows nothing of scenes or Pinocchio, so the scene loader can read and build meshes with it and the step
can solve with it. docs/deformables.md.
"""
