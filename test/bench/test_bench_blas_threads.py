"""Importing the benchmarks pins BLAS to one thread before numpy loads, as importing redmax_ros does
(two OpenBLAS threads on the shared two cores made chain-100 + 50 springs step 18x slower)."""
import os
import subprocess
import sys


def test_importing_redmax_bench_pins_blas_threads():
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    code = ("import redmax_bench, os, sys; import numpy; "
            "print(os.environ['OPENBLAS_NUM_THREADS'], os.environ['OMP_NUM_THREADS'])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "1"]
