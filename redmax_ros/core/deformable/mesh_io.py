"""Tetrahedral meshes from files with meshio (Schlömer et al., https://github.com/nschloe/meshio): Gmsh
``.msh``, VTK ``.vtk`` and ``.vtu``. Only the ``tetra`` cells are used (linear tetrahedra); other cells
(surface triangles, lines of a Gmsh file) are ignored."""
from __future__ import annotations

import meshio
import numpy as np

FORMATS = (".msh", ".vtk", ".vtu")
FILE_FORMATS = {".msh": "gmsh", ".vtk": "vtk", ".vtu": "vtu"}


class MeshReadError(ValueError):
    """A mesh file that cannot be read or has no tetrahedra."""


def read_tets(path) -> tuple:
    """(vertices (n,3) float, tets (T,4) int) of a mesh file; unused vertices are dropped."""
    fmt = FILE_FORMATS.get(str(path).lower()[-4:])
    try:
        m = meshio.read(str(path), file_format=fmt)
    except (Exception, SystemExit) as e:  # meshio raises many kinds on bad files, and sys.exit(1) on some
        raise MeshReadError(f"cannot read {path}: {type(e).__name__}: {e}") from None
    tets = [c.data for c in m.cells if c.type == "tetra"]
    if not tets:
        raise MeshReadError(f"{path} has no linear tetrahedra ('tetra' cells)")
    tets = np.concatenate(tets).astype(np.int64)
    pts = np.asarray(m.points, dtype=float)
    if pts.shape[1] == 2:
        raise MeshReadError(f"{path} is a 2-D mesh")
    used = np.unique(tets)
    remap = -np.ones(len(pts), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return pts[used, :3], remap[tets]


def write_tets(path, vertices, tets) -> None:
    """Write a tetrahedral mesh (any meshio format by the file's suffix)."""
    mesh = meshio.Mesh(np.asarray(vertices, float), [("tetra", np.asarray(tets, np.int64))])
    if str(path).lower().endswith(".msh"):  # Gmsh 2.2 ASCII: the version every Gmsh and meshio reads back
        meshio.write(str(path), mesh, file_format="gmsh22", binary=False)
    else:
        meshio.write(str(path), mesh)
