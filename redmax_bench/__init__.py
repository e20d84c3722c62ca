"""redmax_bench: the benchmarks of redmax_ros (``redmax_bench <subcommand> --out DIR``, see cli.py).

Not part of the runtime: it uses the public API of redmax_ros.core (and the node for
``redmax_bench node``) and writes its results only into the ``--out`` directory.
"""
