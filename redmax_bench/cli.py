"""redmax_bench: benchmarks (not tests). ``redmax_bench <sub> [args]`` runs redmax_bench.<sub>.main(argv).

Each prints ratios measured side by side in one run and writes JSON (and PNG charts) into the
directory given by ``--out DIR`` (every subcommand), by default bench/results under the current
directory. The benchmarks use the public API of redmax_ros.core (and, for ``node``, the ROS node).
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
    "budget": "step budget: time to failure and overshoot on abusive inputs, cost of its checks",
    "sweep": "redmax_sweep: speed-up of 2 local workers over 1 (40 klann runs), Ray per-task overhead",
    "hagfish": "HAGFISH self-collision (Eq. 5 QP): cost split detection / QP / rest, contacts, knot measures",
    "starfish": "STARFISH deformable coupling: cost split skeleton / mesh assembly / coupled solve, CPU vs vertices, RTF",
}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: redmax_bench <subcommand> [--out DIR] [args]\n")
        for k, v in SUBCOMMANDS.items():
            print(f"  {k:10s} {v}")
        print("\nEvery subcommand writes its JSON/PNG into --out DIR (created if missing; default:\n"
              "bench/results under the current directory). `redmax_bench <subcommand> --help` for its options.")
        return 0 if argv else 2
    sub, rest = argv[0], argv[1:]
    if sub not in SUBCOMMANDS:
        print(f"redmax_bench: unknown subcommand '{sub}' (known: {', '.join(SUBCOMMANDS)})", file=sys.stderr)
        return 2
    try:
        mod = importlib.import_module(f"redmax_bench.{sub}")
    except ModuleNotFoundError as e:
        print(f"redmax_bench: '{sub}' is not available yet ({e})", file=sys.stderr)
        return 2
    return int(mod.main(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
