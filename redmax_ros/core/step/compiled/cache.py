"""Keep numba's disk cache of the step kernels consistent with their sources.

numba keys a cached kernel on its own source file only, but the compiled step's kernels (kernel.py) contain
the code of every function they call, inlined or linked at compile time (the stages here and the kernels
of solvers/, dynamics/ and step/state.py), and so does every cached callee in those modules (kkt_solve_into
carries the Cholesky of linalg.py). After an edit of any of those files a cached kernel would silently be
the old one. :func:`drop_stale` hashes all of those sources and, when the hash differs from the one stored
beside the cache, deletes the cached functions of every one of those modules so numba compiles them afresh.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

_CORE = Path(__file__).resolve().parents[2]  # redmax_ros/core
SOURCES = ("step/compiled/kernel.py", "step/compiled/kinematics.py", "step/compiled/forces.py",
           "step/compiled/rows.py", "step/compiled/update.py", "step/compiled/limits.py", "step/compiled/energy.py", "step/compiled/model.py",
           "step/compiled/data.py", "step/compiled/packing.py", "step/compiled/manifold.py", "step/compiled/scheme.py", "step/scheme.py",
           "step/compiled/friction.py", "step/state.py",
           "solvers/recursive.py", "solvers/pcg.py", "solvers/preconditioner.py", "solvers/lockstep_kernel.py", "solvers/kkt.py",
           "linalg.py", "jit.py",
           "dynamics/tree_forces.py", "dynamics/tree_kinematics.py", "dynamics/stabilization.py",
           "dynamics/energy.py", "dynamics/springs.py",
           "friction/staggered.py", "friction/condense.py", "friction/contact.py", "friction/bisp.py")


def sources_digest() -> str:
    h = hashlib.sha256()
    for rel in SOURCES:
        h.update(rel.encode())
        h.update((_CORE / rel).read_bytes())
    return h.hexdigest()


def _cache_dir(source: Path, env) -> Path:
    """Where numba caches the functions of ``source``: its __pycache__, or NUMBA_CACHE_DIR + its directory."""
    if env:
        return Path(env).joinpath(*source.parent.parts[1:])
    return source.parent / "__pycache__"


def drop_stale() -> bool:
    """Delete the cached functions of every module in SOURCES if any of those sources changed (the stamp in
    kernel.py's cache directory); True if something was deleted."""
    digest = sources_digest()
    env = os.environ.get("NUMBA_CACHE_DIR")
    stamp_dir = _cache_dir(_CORE / "step" / "compiled" / "kernel.py", env)
    stamp = stamp_dir / "step-kernels.sha256"
    try:
        if not stamp_dir.is_dir():  # nothing of the step cached yet
            stamp_dir.mkdir(parents=True, exist_ok=True)
            stamp.write_text(digest)
            return False
        if stamp.exists() and stamp.read_text() == digest:
            return False
        dropped = False
        for rel in SOURCES:
            src = _CORE / rel
            d = _cache_dir(src, env)
            if not d.is_dir():
                continue
            for f in list(d.glob(src.stem + ".*.nbi")) + list(d.glob(src.stem + ".*.nbc")):
                f.unlink(missing_ok=True)
                dropped = True
        stamp.write_text(digest)
        return dropped
    except OSError:  # a read-only install: numba then caches elsewhere or not at all
        return False
