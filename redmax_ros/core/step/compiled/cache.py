"""Keep numba's disk cache of the step kernels consistent with their sources.

numba keys a cached kernel on its own source file only, but the compiled step's kernels (kernel.py) contain
the code of every function they call, inlined or linked at compile time (the stages here and the kernels
of solvers/, dynamics/ and step/state.py), and so does every cached callee in those modules (kkt_solve_into
carries the Cholesky of linalg.py). After an edit of any of those files a cached kernel would silently be
the old one. :func:`drop_stale` (jit.drop_stale_caches) hashes all of those sources and, when the hash differs
from the one stored beside the cache, deletes the cached functions of every one of those modules so numba
compiles them afresh.
"""
from __future__ import annotations

from redmax_ros.core.jit import drop_stale_caches

SOURCES = ("step/compiled/kernel.py", "step/compiled/kinematics.py", "step/compiled/forces.py",
           "step/compiled/rows.py", "step/compiled/update.py", "step/compiled/limits.py", "step/compiled/energy.py", "step/compiled/model.py",
           "step/compiled/data.py", "step/compiled/packing.py", "step/compiled/manifold.py", "step/compiled/scheme.py", "step/scheme.py",
           "step/compiled/friction.py", "step/state.py",
           "solvers/recursive.py", "solvers/pcg.py", "solvers/preconditioner.py", "solvers/lockstep_kernel.py", "solvers/kkt.py",
           "linalg.py", "jit.py",
           "dynamics/tree_forces.py", "dynamics/tree_kinematics.py", "dynamics/stabilization.py",
           "dynamics/energy.py", "dynamics/springs.py",
           "friction/staggered.py", "friction/condense.py", "friction/contact.py", "friction/bisp.py",
           "friction/arena.py")


def drop_stale() -> bool:
    """jit.drop_stale_caches for the step kernels (kernel.py) and everything in SOURCES."""
    return drop_stale_caches("step/compiled/kernel.py", SOURCES)
