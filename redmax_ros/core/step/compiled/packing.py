"""Flat buffers for the compiled step's arguments (one float64 and one int64 buffer per group, plus a table).

Why: numba types every argument on every call, and a tuple of arrays costs ~0.15 us per array to type
(a 40-array namedtuple: 5-7 us per call, more than the physics of a small step; measured on this
machine). So the static Model, the per-step Data and the per-prescription-set Rows are each handed to the
kernel as three arrays (floats, ints, table) and unpacked into namedtuples of views *inside* the kernel,
where building a namedtuple costs nothing. The table has one row per field, in the order of the field
list: (is_int, offset, ndim, d0, d1, d2).

:class:`Packer` builds the buffers from named arrays in Python; the ``f1 .. f3`` / ``i1 .. i2`` kernels
return a field's view inside numba code (numba.carray over the buffer's memory, see below).
"""
from __future__ import annotations

import numpy as np

from numba import carray, types
from numba.extending import intrinsic

from redmax_ros.core.jit import njit_inline


class Packed:
    """Three arrays (floats, ints, table) and, for Python, a view of every field by name."""

    def __init__(self, names, f, i, tab):
        self.names, self.f, self.i, self.tab = tuple(names), f, i, tab
        self.views = {n: self._view(k) for k, n in enumerate(self.names)}

    def _view(self, k):
        is_int, off, nd, d0, d1, d2 = (int(x) for x in self.tab[k])
        shape = (d0, d1, d2)[:nd]
        buf = self.i if is_int else self.f
        return buf[off:off + int(np.prod(shape, dtype=np.int64))].reshape(shape)

    def __getitem__(self, name):
        return self.views[name]

    @property
    def args(self) -> tuple:
        return self.f, self.i, self.tab


def pack(spec, values: dict) -> Packed:
    """Pack ``values`` {name: array} in the order and with the dtype/ndim of ``spec`` [(name, 'f'|'i', ndim)]
    (every name of spec must be in values; arrays are copied)."""
    missing = [n for n, _, _ in spec if n not in values]
    if missing:
        raise KeyError(f"packing: missing fields {missing}")
    tab = np.zeros((len(spec), 6), dtype=np.int64)
    nf = ni = 0
    arrays = []
    for k, (name, kind, nd) in enumerate(spec):
        a = np.asarray(values[name], dtype=np.int64 if kind == "i" else np.float64)
        if a.ndim != nd:
            raise ValueError(f"packing: field {name} has ndim {a.ndim}, expected {nd}")
        off = ni if kind == "i" else nf
        tab[k, :3] = (kind == "i", off, nd)
        tab[k, 3:3 + nd] = a.shape
        arrays.append((kind, off, a))
        if kind == "i":
            ni += a.size
        else:
            nf += a.size
    f = np.zeros(max(nf, 1))
    i = np.zeros(max(ni, 1), dtype=np.int64)
    for kind, off, a in arrays:
        (i if kind == "i" else f)[off:off + a.size] = a.reshape(-1)
    return Packed([n for n, _, _ in spec], f, i, tab)


@intrinsic
def _f64_ptr(typingctx, addr):
    """The float64 pointer at integer address ``addr``."""
    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.float64)))
    return types.CPointer(types.float64)(types.uintp), codegen


@intrinsic
def _i64_ptr(typingctx, addr):
    """The int64 pointer at integer address ``addr``."""
    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.int64)))
    return types.CPointer(types.int64)(types.uintp), codegen


# The views are numba.carray's over the buffers' memory: arrays without a reference count (NULL meminfo), so
# building ~100 of them costs ~0.5 us instead of ~4 us (slice + reshape, ~40 ns each), and handing the
# namedtuples to a stage costs ~3.5 ns per member instead of ~4.5 (measured). They are valid while the
# buffers live: the caller (backend.py) holds them for the duration of every kernel call.
@njit_inline
def f1(buf, tab, k):
    return carray(_f64_ptr(buf.ctypes.data + 8 * tab[k, 1]), (tab[k, 3],))


@njit_inline
def f2(buf, tab, k):
    return carray(_f64_ptr(buf.ctypes.data + 8 * tab[k, 1]), (tab[k, 3], tab[k, 4]))


@njit_inline
def f3(buf, tab, k):
    return carray(_f64_ptr(buf.ctypes.data + 8 * tab[k, 1]), (tab[k, 3], tab[k, 4], tab[k, 5]))


@njit_inline
def i1(buf, tab, k):
    return carray(_i64_ptr(buf.ctypes.data + 8 * tab[k, 1]), (tab[k, 3],))


@njit_inline
def i2(buf, tab, k):
    return carray(_i64_ptr(buf.ctypes.data + 8 * tab[k, 1]), (tab[k, 3], tab[k, 4]))
