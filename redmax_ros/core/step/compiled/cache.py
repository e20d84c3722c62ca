"""Keep numba's disk cache of the step kernels consistent with their sources.

numba keys a cached kernel on its own source file only, but the compiled step's kernels (kernel.py) contain
the code of every function they call, inlined or linked at compile time (the stages here and the kernels
of solvers/, dynamics/ and step/state.py). After an edit of any of those files the cached kernel would
silently be the old one. :func:`drop_stale` hashes all of those sources and, when the hash differs from
the one stored beside the cache, deletes the cached kernels of kernel.py so numba compiles them afresh.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

_CORE = Path(__file__).resolve().parents[2]  # redmax_ros/core
SOURCES = ("step/compiled/kernel.py", "step/compiled/kinematics.py", "step/compiled/forces.py",
           "step/compiled/rows.py", "step/compiled/update.py", "step/compiled/limits.py", "step/compiled/energy.py", "step/compiled/model.py",
           "step/compiled/data.py", "step/compiled/packing.py", "step/compiled/manifold.py", "step/compiled/scheme.py", "step/state.py",
           "solvers/recursive.py", "solvers/pcg.py", "solvers/kkt.py", "linalg.py", "jit.py",
           "dynamics/tree_forces.py", "dynamics/tree_kinematics.py", "dynamics/stabilization.py",
           "dynamics/energy.py", "dynamics/springs.py")


def sources_digest() -> str:
    h = hashlib.sha256()
    for rel in SOURCES:
        h.update(rel.encode())
        h.update((_CORE / rel).read_bytes())
    return h.hexdigest()


def _cache_dirs() -> list:
    dirs = [_CORE / "step" / "compiled" / "__pycache__"]
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        dirs += [p for p in Path(env).rglob("compiled") if p.is_dir()]
    return [d for d in dirs if d.is_dir()]


def drop_stale() -> bool:
    """Delete the cached step kernels if any source they contain changed; True if something was deleted."""
    digest = sources_digest()
    dropped = False
    for d in _cache_dirs():
        stamp = d / "step-kernels.sha256"
        try:
            if stamp.exists() and stamp.read_text() == digest:
                continue
            for f in list(d.glob("kernel.*.nbi")) + list(d.glob("kernel.*.nbc")):
                f.unlink(missing_ok=True)
                dropped = True
            stamp.write_text(digest)
        except OSError:  # a read-only install: numba then caches elsewhere or not at all
            continue
    return dropped
