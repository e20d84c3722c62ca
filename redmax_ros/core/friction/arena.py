"""Arenas: preallocated scratch buffers that the compiled friction step carves its arrays from (numba).

An arena is a float buffer and an int buffer with their offsets ``off`` (2,): off[0] the floats taken, off[1]
the ints. Each take returns a view of the next free part of its buffer and advances the offset; a take that
would run past the end returns a new array instead (so a buffer sized too short costs allocations, never
wrong numbers). The friction pack holds its arenas across steps (step/compiled/friction.build_friction, sized
from the model for the most rows a step can have); the reference pipeline's calls pass empty ones (every take
allocates). The views live until the arena's offsets are reset: callers reset them once per step.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def take(buf, off, r, c):
    """An (r, c) view of the float arena ``buf`` from offset off[0] (advanced), or a new array if it is full."""
    o = off[0]
    k = r * c
    if o + k <= buf.shape[0]:
        off[0] = o + k
        return buf[o:o + k].reshape((r, c))
    return np.empty((r, c))


@njit(cache=True, nogil=True)
def take1(buf, off, slot, k):
    """A (k,) view of the arena ``buf`` (floats: slot 0, ints: slot 1) from off[slot] (advanced), or a new
    array of its type if it is full."""
    o = off[slot]
    if o + k <= buf.shape[0]:
        off[slot] = o + k
        return buf[o:o + k]
    return np.empty(k, dtype=buf.dtype)


@njit(cache=True, nogil=True)
def take3(buf, off, a, b, c):
    """An (a, b, c) view of the float arena ``buf`` from offset off[0] (advanced), or a new array if it is
    full."""
    o = off[0]
    k = a * b * c
    if o + k <= buf.shape[0]:
        off[0] = o + k
        return buf[o:o + k].reshape((a, b, c))
    return np.empty((a, b, c))


@njit(cache=True, nogil=True)
def empty_arena():
    """(floats, ints, offsets): an arena with no room, on which every take allocates (the reference calls)."""
    return np.empty(0), np.empty(0, dtype=np.int64), np.zeros(2, dtype=np.int64)
