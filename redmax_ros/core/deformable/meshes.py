"""Procedural tetrahedral meshes: a box of hexahedral cells split into 5 or 6 tetrahedra each
(Freudenthal/Kuhn 6-tet split, conforming across cells), used by tests, the scene builders and the
starfish (scene/builders_starfish.py)."""
from __future__ import annotations

import numpy as np

# the 6 tetrahedra of the Kuhn split of the unit cube (vertex k = (k&1, k>>1&1, k>>2&1)): conforming when
# every cell uses the same split
KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def grid_vertices(lo, size, cells):
    nx, ny, nz = cells
    gx = np.linspace(lo[0], lo[0] + size[0], nx + 1)
    gy = np.linspace(lo[1], lo[1] + size[1], ny + 1)
    gz = np.linspace(lo[2], lo[2] + size[2], nz + 1)
    X, Y, Z = np.meshgrid(gx, gy, gz, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)


def box_tets(lo, size, cells, keep=None):
    """(vertices (n,3), tets (T,4)) of the box [lo, lo + size] split into cells (nx, ny, nz), 6 tets per
    cell. ``keep(center) -> bool``: cells to keep (default all); unused vertices are dropped."""
    lo, size = np.asarray(lo, float), np.asarray(size, float)
    nx, ny, nz = cells
    X = grid_vertices(lo, size, cells)

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    tets = []
    h = size / np.array(cells)
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if keep is not None and not keep(lo + (np.array([i, j, k]) + 0.5) * h):
                    continue
                corner = [vid(i + (c & 1), j + (c >> 1 & 1), k + (c >> 2 & 1)) for c in range(8)]
                tets.extend([[corner[c] for c in t] for t in KUHN])
    tets = np.array(tets, dtype=np.int64).reshape(-1, 4)
    used = np.unique(tets)
    remap = -np.ones(len(X), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return X[used], remap[tets]
