"""redmax_bench: the benchmarks of redmax_ros (``redmax_bench <subcommand> --out DIR``, see cli.py).

Not part of the runtime: it uses the public API of redmax_ros.core (and the node for
``redmax_bench node``) and writes its results only into the ``--out`` directory.
"""

# redmax_ros pins BLAS to one thread (redmax_ros/__init__.py), which only works before numpy is first
# imported: import it before any benchmark module imports numpy. Without it `redmax_bench step` ran
# chain-100 + 50 springs at 113 instead of ~2000 steps/s (two OpenBLAS threads on two busy cores).
import redmax_ros  # noqa: E402,F401
