"""The JIT decorators of every compiled kernel: numba ``njit(cache=True, nogil=True)`` (kernels are cached
on disk beside their module) and ``njit_inline`` (the same, inlined into its callers), or the plain Python
function where numba is missing; and :func:`drop_stale_caches`, which keeps those disk caches consistent with
the sources compiled into them."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

try:  # numba is a hard performance dependency but keep the module importable without it
    from numba import njit as _numba_njit

    def njit(fn):
        return _numba_njit(cache=True, nogil=True)(fn)

    def njit_inline(fn):
        """njit with numba-IR inlining into every caller: for the compiled step's stages, whose (Model, Data)
        namedtuples of ~100 array views would otherwise be copied and reference-counted at each call
        (~1.5 us per stage call, measured)."""
        return _numba_njit(cache=True, nogil=True, inline="always")(fn)

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    def njit(fn):
        return fn

    njit_inline = njit

    HAVE_NUMBA = False


_CORE = Path(__file__).resolve().parent  # redmax_ros/core


def cache_dir(rel: str) -> Path:
    """Where numba caches the functions of the module ``rel`` (relative to redmax_ros/core): its __pycache__,
    or under NUMBA_CACHE_DIR the subdirectory numba's UserProvidedCacheLocator names for it."""
    source = _CORE / rel
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        from numba.core.caching import UserProvidedCacheLocator  # optional: only with numba and NUMBA_CACHE_DIR
        return Path(env) / UserProvidedCacheLocator.get_suitable_cache_subpath(str(source))
    return source.parent / "__pycache__"


def sources_digest(sources) -> str:
    """sha256 over the files ``sources`` (paths relative to redmax_ros/core), names and contents."""
    h = hashlib.sha256()
    for rel in sources:
        h.update(rel.encode())
        h.update((_CORE / rel).read_bytes())
    return h.hexdigest()


def drop_stale_caches(owner: str, sources) -> bool:
    """numba keys a cached kernel on its own source file only, but a kernel contains the code of every njit
    function it calls (inlined, or linked at compile time), so after an edit of a callee's file the cached
    kernel would silently be the old one. Call this at the import of ``owner`` (a module path relative to
    redmax_ros/core, before its kernels are first called) with every file compiled into its kernels: when
    their digest differs from the one stamped in owner's cache directory (``<stem>.sources.sha256``), the
    cached functions of all of ``sources`` are deleted, so numba compiles them afresh. True if something was
    deleted."""
    digest = sources_digest(sources)
    stamp_dir = cache_dir(owner)
    stamp = stamp_dir / f"{Path(owner).stem}.sources.sha256"
    try:
        if not stamp_dir.is_dir():  # nothing of it cached yet
            stamp_dir.mkdir(parents=True, exist_ok=True)
            stamp.write_text(digest)
            return False
        if stamp.exists() and stamp.read_text() == digest:
            return False
        dropped = False
        for rel in sources:
            d, stem = cache_dir(rel), Path(rel).stem
            if not d.is_dir():
                continue
            for f in list(d.glob(stem + ".*.nbi")) + list(d.glob(stem + ".*.nbc")):
                f.unlink(missing_ok=True)
                dropped = True
        stamp.write_text(digest)
        return dropped
    except OSError:  # a read-only install: numba then caches elsewhere or not at all
        return False
