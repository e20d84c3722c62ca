"""A local worker process of the sweep pool: ``python -m redmax_ros.sweep.worker [MODULE ...]``.

Imports the MODULEs (the work's own modules, so that the import is paid once per worker), then reads tasks
from stdin and writes results to stdout, each a frame: 8-byte little-endian length + pickle. A task is
(fn, arg); the result is fn(arg), or a pool.TaskFailure with the traceback. Anything the work prints goes to
stderr (fd 1 is pointed at fd 2; the frames use a private copy of the original stdout). Ends at EOF on stdin.
"""
from __future__ import annotations

import importlib
import os
import pickle
import sys

from redmax_ros.sweep.pool import call_task, read_frame, write_frame


def main(argv=None) -> int:
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)
    inp = sys.stdin.buffer
    for name in (sys.argv[1:] if argv is None else argv):
        importlib.import_module(name)
    while True:
        msg = read_frame(inp)
        if msg is None:
            return 0
        fn, arg = pickle.loads(msg)
        res = call_task(fn, arg)
        try:
            data = pickle.dumps(res, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as e:  # noqa: BLE001 - an unpicklable result is the task's failure
            data = pickle.dumps(call_task(_raise, e))
        write_frame(out, data)


def _raise(e):
    raise RuntimeError(f"the task's result cannot be pickled: {e}")


if __name__ == "__main__":
    sys.exit(main())
