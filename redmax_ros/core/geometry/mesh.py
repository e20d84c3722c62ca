"""Triangle-mesh bodies: Wavefront OBJ reading, closedness check and mass properties by the polyhedral
volume integrals of Mirtich [1996] ("Fast and Accurate Computation of Polyhedral Mass Properties",
J. Graphics Tools 1(2)).

Mirtich reduces the volume integrals of 1, x, y, z, x^2, y^2, z^2, xy, yz, zx over the solid to
surface integrals over the faces (divergence theorem), and each face integral to a line integral
around the face's projection onto the coordinate plane most parallel to it (Green's theorem). The
result is exact for any closed, consistently oriented polyhedron (up to round-off). Polygonal OBJ
faces are triangulated as fans (the faces of a triangle mesh are planar, which Mirtich's face
integrals require).

Closedness: every edge must be used by exactly two faces, once in each direction (a closed,
consistently oriented 2-manifold), and the enclosed volume must be positive (outward normals).
Violations raise :class:`~redmax_ros.core.errors.SceneError` through the caller, naming the problem.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np


class MeshError(ValueError):
    """A mesh that cannot be used as a rigid body (message says why)."""


@dataclass
class Mesh:
    vertices: np.ndarray  # (V,3) [m]
    faces: np.ndarray  # (F,3) vertex indices, counter-clockwise seen from outside


def read_obj(path, scale=1.0, text=None) -> Mesh:
    """Vertices and (fan-triangulated) faces of an OBJ file; ``scale``: scalar or 3-vector; ``text``:
    the file's content if already read (``path`` then only names it in messages). Messages give the
    line number, never the line's content."""
    path = Path(path)
    verts, faces = [], []
    for ln, line in enumerate((path.read_text() if text is None else text).splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "v":
            try:
                verts.append([float(x) for x in parts[1:4]])
            except ValueError:
                raise MeshError(f"{path.name}:{ln}: bad vertex line (expected 'v x y z', numbers)") from None
            if len(verts[-1]) != 3:
                raise MeshError(f"{path.name}:{ln}: a vertex needs 3 coordinates")
        elif parts[0] == "f":
            idx = []
            for tok in parts[1:]:
                try:
                    i = int(tok.split("/")[0])
                except ValueError:
                    raise MeshError(f"{path.name}:{ln}: bad face index (expected an integer)") from None
                i = i - 1 if i > 0 else len(verts) + i  # OBJ: 1-based, negative = relative
                if not 0 <= i < len(verts):
                    raise MeshError(f"{path.name}:{ln}: face index {tok} out of range (1..{len(verts)})")
                idx.append(i)
            if len(idx) < 3:
                raise MeshError(f"{path.name}:{ln}: a face needs at least 3 vertices")
            faces += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    if not faces:
        raise MeshError(f"{path.name}: no faces")
    V = np.array(verts, float) * np.asarray(scale, float)
    return Mesh(V, np.array(faces, dtype=int))


def check_closed(mesh: Mesh) -> None:
    """Raise MeshError unless the mesh is a closed, consistently oriented surface without degenerate faces."""
    V, F = mesh.vertices, mesh.faces
    area2 = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    bad = np.flatnonzero(area2 <= 1e-14 * max(1.0, float(np.abs(V).max()) ** 2))
    if len(bad):
        raise MeshError(f"face {int(bad[0]) + 1} has zero area (vertices {(F[bad[0]] + 1).tolist()})")
    directed = Counter()
    for f in F:
        for k in range(3):
            directed[(int(f[k]), int(f[(k + 1) % 3]))] += 1
    for (a, b), n in directed.items():
        if n > 1:
            raise MeshError(f"edge {a + 1}-{b + 1} is used {n} times in the same direction "
                            "(faces inconsistently oriented or the surface is not a 2-manifold)")
        if (b, a) not in directed:
            raise MeshError(f"not closed: edge {a + 1}-{b + 1} belongs to one face only (a hole in the surface)")


def volume_integrals(mesh: Mesh):
    """Mirtich's T0 = int 1, T1 = int (x, y, z), T2 = int (x^2, y^2, z^2), TP = int (xy, yz, zx) over
    the solid (compVolumeIntegrals of the paper's volInt.c, faces as triangles)."""
    V, F = mesh.vertices, mesh.faces
    T0 = 0.0
    T1, T2, TP = np.zeros(3), np.zeros(3), np.zeros(3)
    for f in F:
        p = V[f]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        n /= np.linalg.norm(n)
        w = -float(n @ p[0])
        ax = np.abs(n)
        C = 0 if (ax[0] > ax[1] and ax[0] > ax[2]) else (1 if ax[1] > ax[2] else 2)
        A, B = (C + 1) % 3, (C + 2) % 3
        Fa, Fb, Fc, Faa, Fbb, Fcc, Faaa, Fbbb, Fccc, Faab, Fbbc, Fcca = _face_integrals(p, n, w, A, B, C)
        T0 += n[0] * (Fa if A == 0 else (Fb if B == 0 else Fc))
        T1[A] += n[A] * Faa
        T1[B] += n[B] * Fbb
        T1[C] += n[C] * Fcc
        T2[A] += n[A] * Faaa
        T2[B] += n[B] * Fbbb
        T2[C] += n[C] * Fccc
        TP[A] += n[A] * Faab
        TP[B] += n[B] * Fbbc
        TP[C] += n[C] * Fcca
    return T0, T1 / 2.0, T2 / 3.0, TP / 2.0


def _projection_integrals(p, A, B):
    """compProjectionIntegrals: line integrals around the face projected on the (A, B) plane."""
    P1 = Pa = Pb = Paa = Pab = Pbb = Paaa = Paab = Pabb = Pbbb = 0.0
    for i in range(len(p)):
        a0, b0 = p[i][A], p[i][B]
        a1, b1 = p[(i + 1) % len(p)][A], p[(i + 1) % len(p)][B]
        da, db = a1 - a0, b1 - b0
        a0_2, b0_2, a1_2, b1_2 = a0 * a0, b0 * b0, a1 * a1, b1 * b1
        a0_3, b0_3, a1_3, b1_3 = a0_2 * a0, b0_2 * b0, a1_2 * a1, b1_2 * b1
        a0_4, b0_4 = a0_3 * a0, b0_3 * b0
        C1 = a1 + a0
        Ca = a1 * C1 + a0_2
        Caa = a1 * Ca + a0_3
        Caaa = a1 * Caa + a0_4
        Cb = b1 * (b1 + b0) + b0_2
        Cbb = b1 * Cb + b0_3
        Cbbb = b1 * Cbb + b0_4
        Cab = 3 * a1_2 + 2 * a1 * a0 + a0_2
        Kab = a1_2 + 2 * a1 * a0 + 3 * a0_2
        Caab = a0 * Cab + 4 * a1_3
        Kaab = a1 * Kab + 4 * a0_3
        Cabb = 4 * b1_3 + 3 * b1_2 * b0 + 2 * b1 * b0_2 + b0_3
        Kabb = b1_3 + 2 * b1_2 * b0 + 3 * b1 * b0_2 + 4 * b0_3
        P1 += db * C1
        Pa += db * Ca
        Paa += db * Caa
        Paaa += db * Caaa
        Pb += da * Cb
        Pbb += da * Cbb
        Pbbb += da * Cbbb
        Pab += db * (b1 * Cab + b0 * Kab)
        Paab += db * (b1 * Caab + b0 * Kaab)
        Pabb += da * (a1 * Cabb + a0 * Kabb)
    return (P1 / 2.0, Pa / 6.0, Paa / 12.0, Paaa / 20.0, Pb / -6.0, Pbb / -12.0, Pbbb / -20.0,
            Pab / 24.0, Paab / 60.0, Pabb / -60.0)


def _face_integrals(p, n, w, A, B, C):
    """compFaceIntegrals: surface integrals over the face from its projection integrals."""
    P1, Pa, Paa, Paaa, Pb, Pbb, Pbbb, Pab, Paab, Pabb = _projection_integrals(p, A, B)
    k1 = 1.0 / n[C]
    k2, k3, k4 = k1 * k1, k1 ** 3, k1 ** 4
    na, nb = n[A], n[B]
    Fa = k1 * Pa
    Fb = k1 * Pb
    Fc = -k2 * (na * Pa + nb * Pb + w * P1)
    Faa = k1 * Paa
    Fbb = k1 * Pbb
    Fcc = k3 * (na * na * Paa + 2 * na * nb * Pab + nb * nb * Pbb + w * (2 * (na * Pa + nb * Pb) + w * P1))
    Faaa = k1 * Paaa
    Fbbb = k1 * Pbbb
    Fccc = -k4 * (na ** 3 * Paaa + 3 * na * na * nb * Paab + 3 * na * nb * nb * Pabb + nb ** 3 * Pbbb
                  + 3 * w * (na * na * Paa + 2 * na * nb * Pab + nb * nb * Pbb)
                  + w * w * (3 * (na * Pa + nb * Pb) + w * P1))
    Faab = k1 * Paab
    Fbbc = -k2 * (na * Pabb + nb * Pbbb + w * Pbb)
    Fcca = k3 * (na * na * Paaa + 2 * na * nb * Paab + nb * nb * Pabb + w * (2 * (na * Paa + nb * Pab) + w * Pa))
    return Fa, Fb, Fc, Faa, Fbb, Fcc, Faaa, Fbbb, Fccc, Faab, Fbbc, Fcca


def mass_properties(mesh: Mesh, density: float | None = None, mass: float | None = None):
    """(mass [kg], COM (3,) [m], inertia about the COM (3,3) [kg m^2], volume [m^3]) of a uniform solid
    bounded by the mesh, in the mesh frame. Give ``density`` [kg/m^3] or ``mass`` [kg]."""
    check_closed(mesh)
    T0, T1, T2, TP = volume_integrals(mesh)
    if not T0 > 0:
        raise MeshError(f"enclosed volume is {T0:.3g} m^3: the faces must be oriented counter-clockwise "
                        "seen from outside (outward normals)")
    rho = density if density is not None else mass / T0
    m = rho * T0
    r = T1 / T0
    J = rho * np.array([[T2[1] + T2[2], -TP[0], -TP[2]],
                        [-TP[0], T2[2] + T2[0], -TP[1]],
                        [-TP[2], -TP[1], T2[0] + T2[1]]])
    J -= m * (float(r @ r) * np.eye(3) - np.outer(r, r))  # parallel axis theorem, to the COM
    return m, r, 0.5 * (J + J.T), T0
