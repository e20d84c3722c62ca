"""Linear algebra of a step, independent of how its terms were computed: the problem types (LinearSystem of
Eq. 2, Constraints of Eq. 5-7; problem.py), the direct solver (Cholesky, KKT Schur complement of Eq. 6/7,
ProxSuite QP of Eq. 5; direct.py, with the small-system compiled kernels in kkt.py), the O(n) recursive passes
over the kinematic tree (recursive.py), the matrix-free LHS of Eq. (2) and PCG (pcg.py), the Projected Block
Jacobi Preconditioner (Alg. 1, preconditioner.py), the lockstep PCG solves of Eq. (4) with the
joint-limit active set (lockstep_pcg.py), and the sparse LDL^T with a fixed pattern of the coupled deformable
step (sparse_ldl.py)."""
