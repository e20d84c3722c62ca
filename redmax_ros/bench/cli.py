"""redmax_bench: benchmarks (not tests). ``redmax_bench <sub> [args]`` runs redmax_ros.bench.<sub>.main(argv).

Each prints ratios measured side by side in one run and writes JSON (and PNG charts) under
bench/results/.
"""
from __future__ import annotations

import importlib
import sys

SUBCOMMANDS = {
    "step": "steps/s of the RedMax step vs semi-implicit Euler on pin.aba, and where the time goes",
    "passes": "per-joint cost of the O(n) passes and the Alg. 1 preconditioner",
    "scaling": "direct vs PCG time against DOF on bridge/umbrella (Table 2)",
    "node": "ROS node latency, service overhead and real-time factor",
    "friction": "frictional joints and contact (Fig. 5c), BISP vs SP",
    "accuracy": "work-precision charts and stability maps",
}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: redmax_bench <subcommand> [args]\n")
        for k, v in SUBCOMMANDS.items():
            print(f"  {k:10s} {v}")
        return 0 if argv else 2
    sub, rest = argv[0], argv[1:]
    if sub not in SUBCOMMANDS:
        print(f"redmax_bench: unknown subcommand '{sub}' (known: {', '.join(SUBCOMMANDS)})", file=sys.stderr)
        return 2
    try:
        mod = importlib.import_module(f"redmax_ros.bench.{sub}")
    except ModuleNotFoundError as e:
        print(f"redmax_bench: '{sub}' is not available yet ({e})", file=sys.stderr)
        return 2
    return int(mod.main(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
