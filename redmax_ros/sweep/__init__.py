"""redmax_sweep: scenario sweeps over scene overrides, run on a local process pool or on Ray (docs/sweeps.md).

* spec.py: ``--grid`` / ``--random`` expansion into RunSpecs (one per run: scene, overrides, duration, controller);
* run.py: one run -> one metrics row (final state, energies, constraint violation, required-torque
  statistics, distance travelled by a body, failure, wall/CPU time), through redmax_ros.runner's loop;
* pool.py: ``run_tasks``, the one entry point of the local pool (worker.py processes; a killed worker's task
  retried once) and of Ray, also used by redmax_bench;
* table.py: the results table streamed to CSV row by row (Parquet at the end); chart.py: metric against parameter;
* cli.py: the ``redmax_sweep`` command.

Uses the core only through ``redmax_ros.core``; the core never imports this package.
"""
