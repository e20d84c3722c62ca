"""The JIT decorators of every compiled kernel: numba ``njit(cache=True, nogil=True)`` (kernels are cached
on disk beside their module) and ``njit_inline`` (the same, inlined into its callers), or the plain Python
function where numba is missing."""

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
