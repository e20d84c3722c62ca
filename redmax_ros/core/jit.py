"""The JIT decorator of every compiled kernel: numba ``njit(cache=True, nogil=True)`` (kernels are cached
on disk beside their module), or the plain Python function where numba is missing."""

try:  # numba is a hard performance dependency but keep the module importable without it
    from numba import njit as _numba_njit

    def njit(fn):
        return _numba_njit(cache=True, nogil=True)(fn)

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    def njit(fn):
        return fn

    HAVE_NUMBA = False
