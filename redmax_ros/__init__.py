"""redmax_ros: RedMax articulated-body simulation (Wang et al. 2019) on Pinocchio, served over ROS 2.

Our linear systems are small and dense (tens to hundreds of DOFs); multi-threaded BLAS only adds
synchronisation overhead there (measured: a 150x100 product took 90 us on one thread and 16-21 ms
with two OpenBLAS threads on a loaded 2-core machine). BLAS therefore runs single-threaded unless
the user sets these variables; this must happen before numpy is first imported to take effect.
"""
import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
