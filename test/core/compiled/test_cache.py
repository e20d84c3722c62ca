"""jit.drop_stale_caches: a kernel's disk cache is dropped when any source compiled into it changes (numba itself
keys a cached kernel on its own file only, so a stale callee would silently stay in it)."""
from __future__ import annotations

from redmax_ros.core import jit

OWNER = "solvers/coupled_kernel.py"
SOURCES = ("solvers/coupled_kernel.py", "solvers/sparse_ldl.py", "jit.py")


def _cache_files(rel: str, stem: str):
    d = jit.cache_dir(rel)
    d.mkdir(parents=True, exist_ok=True)
    files = [d / f"{stem}.kernel-12.py311.nbi", d / f"{stem}.kernel-12.py311.1.nbc"]
    for f in files:
        f.write_bytes(b"x")
    return d, files


def test_cache_kept_while_sources_unchanged_dropped_after_a_callee_changes(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert jit.cache_dir(OWNER).parent == tmp_path  # numba's own layout under NUMBA_CACHE_DIR
    assert jit.drop_stale_caches(OWNER, SOURCES) is False  # first use: stamps the digest
    owner_dir, owner_files = _cache_files(OWNER, "coupled_kernel")
    _, callee_files = _cache_files("solvers/sparse_ldl.py", "sparse_ldl")
    _, other_files = _cache_files("solvers/coupled.py", "coupled")  # not among the sources
    assert jit.drop_stale_caches(OWNER, SOURCES) is False
    assert all(f.exists() for f in owner_files + callee_files)
    stamp = owner_dir / "coupled_kernel.sources.sha256"
    assert stamp.read_text() == jit.sources_digest(SOURCES)
    stamp.write_text("digest of an older sparse_ldl.py")  # as after an edit of a callee's file
    assert jit.drop_stale_caches(OWNER, SOURCES) is True
    assert not any(f.exists() for f in owner_files + callee_files)
    assert all(f.exists() for f in other_files)
    assert stamp.read_text() == jit.sources_digest(SOURCES)
