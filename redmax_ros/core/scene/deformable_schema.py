"""Scene-file keys of deformable bodies (docs/deformables.md, docs/scenes.md "Deformables").

    deformables:
      - name: rope
        type: string
        n: 20                     # point masses (>= 2), laid out straight from start to end
        start: [0, 0, 0]          # world [m], at the initial configuration
        end: [1, 0, 0]
        mass: 0.2                 # kg, total
        stiffness: 500            # N: EA, force per unit strain (l - L)/L; rest length = initial spacing
        rayleigh: {alpha: 0, beta: 0}   # D = alpha M + beta K
        attachments:
          - {body: world, vertices: [0]}      # listed vertices (negative: from the end)
          - {body: link, vertices: [-1]}      # held at the body point they occupy at q0
      - name: pad
        type: fem
        mesh: {file: meshes/pad.msh}  # meshio: .msh, .vtk, .vtu; or {box: {lo, size, cells}};
                                      # or {vertices: [[x,y,z]...], tets: [[i,j,k,l]...]} (builders)
        pos: [0, 0, 0]            # translation of the mesh's vertices [m]
        young: 1.0e5              # Pa
        poisson: 0.3
        density: 1000             # kg/m^3
        rayleigh: {alpha: 0, beta: 0.01}
        attachments:
          - {body: foot, inside: true}        # every vertex inside the body's shape (box, sphere, cylinder, capsule)
        floor: 0.0                # optional: its free vertices stay above z = floor (contact rows)
        floor_mu: 0.5             # optional Coulomb friction of the floor (default 0, frictionless)

Parsed into :class:`DeformableSpec` (SceneSpec.deformables, [] when absent); a bad entry is a SceneError
naming it (``deformables.pad.young``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from redmax_ros.core.deformable import meshes
from redmax_ros.core.deformable.mesh_io import FORMATS, MeshReadError, read_tets

TOP_KEYS = {"deformables"}
TYPES = ("string", "fem")
MAX_VERTICES = 200_000


@dataclass
class AttachmentSpec:
    body: str  # body name or "world"
    vertices: list | None = None  # vertex indices (negative from the end), or None with inside
    inside: bool = False


@dataclass
class DeformableSpec:
    name: str
    kind: str  # string | fem
    vertices: np.ndarray  # (n,3) world, at the initial configuration [m]
    tets: np.ndarray | None = None  # (T,4) for fem
    mass: float = 0.0  # string: total [kg]
    stiffness: float = 0.0  # string: EA [N]
    young: float = 0.0  # fem [Pa]
    poisson: float = 0.0
    density: float = 0.0  # fem [kg/m^3]
    alpha: float = 0.0  # Rayleigh [1/s]
    beta: float = 0.0  # Rayleigh [s]
    attachments: list = field(default_factory=list)
    floor: float | None = None
    floor_mu: float = 0.0  # Coulomb friction coefficient of the floor contacts
    source: str = ""  # mesh file or builder


def parse(v, raw, spec, body_names) -> list:
    """The ``deformables`` section with the loader's validator ``v`` (loader._Validator)."""
    out = []
    names = set()
    for entry, d in v.entries(raw, "deformables"):
        entry = f"deformables.{d.get('name', entry)}" if isinstance(d, dict) else entry
        v.keys(entry, d, {"name", "type", "n", "start", "end", "mass", "stiffness", "rayleigh", "attachments",
                          "mesh", "pos", "young", "poisson", "density", "floor",
                          "floor_mu"}, required=("name", "type"))
        name = str(d["name"])
        if name in names:
            v.err(entry, f"duplicate deformable name '{name}'")
        names.add(name)
        kind = d["type"]
        if kind not in TYPES:
            v.err(f"{entry}.type", f"unknown deformable type {kind!r} ({', '.join(TYPES)})")
        ray = d.get("rayleigh") or {}
        v.keys(f"{entry}.rayleigh", ray, {"alpha", "beta"})
        alpha = v.number(f"{entry}.rayleigh", "alpha", ray.get("alpha", 0.0), nonneg=True)
        beta = v.number(f"{entry}.rayleigh", "beta", ray.get("beta", 0.0), nonneg=True)
        if kind == "string":
            for k in ("mesh", "young", "poisson", "density", "pos"):
                if k in d:
                    v.err(entry, f"'{k}' is a key of type fem, not string")
            for k in ("n", "start", "end", "mass", "stiffness"):
                if k not in d:
                    v.err(entry, f"missing '{k}'")
            n = d["n"]
            if isinstance(n, bool) or not isinstance(n, int) or not 2 <= n <= MAX_VERTICES:
                v.err(f"{entry}.n", f"'n' must be an integer from 2 to {MAX_VERTICES}, got {n!r}")
            a = v.vector(entry, "start", d["start"], 3)
            b = v.vector(entry, "end", d["end"], 3)
            if np.linalg.norm(b - a) <= 0:
                v.err(entry, "'start' and 'end' must differ")
            x = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
            ds = DeformableSpec(name, kind, x, mass=v.number(entry, "mass", d["mass"], positive=True),
                                stiffness=v.number(entry, "stiffness", d["stiffness"], positive=True),
                                alpha=alpha, beta=beta, source="string")
        else:
            for k in ("n", "start", "end", "mass", "stiffness"):
                if k in d:
                    v.err(entry, f"'{k}' is a key of type string, not fem")
            for k in ("mesh", "young", "poisson", "density"):
                if k not in d:
                    v.err(entry, f"missing '{k}'")
            x, tets, src = _mesh(v, f"{entry}.mesh", d["mesh"])
            if "pos" in d:
                x = x + v.vector(entry, "pos", d["pos"], 3)
            nu = v.number(entry, "poisson", d["poisson"])
            if not -1.0 < nu < 0.5:
                v.err(f"{entry}.poisson", f"'poisson' must lie in (-1, 0.5), got {nu}")
            ds = DeformableSpec(name, kind, x, tets, young=v.number(entry, "young", d["young"], positive=True),
                                poisson=nu, density=v.number(entry, "density", d["density"], positive=True),
                                alpha=alpha, beta=beta, source=src)
        ds.attachments = _attachments(v, f"{entry}.attachments", d.get("attachments") or [], body_names, len(ds.vertices))
        if d.get("floor") is not None:
            ds.floor = v.number(entry, "floor", d["floor"])
        if d.get("floor_mu") is not None:
            if ds.floor is None:
                v.err(f"{entry}.floor_mu", "'floor_mu' needs a 'floor'")
            # Coulomb coefficient of the floor contacts (solvers/coupled.py, four-sided pyramid on world x, y)
            ds.floor_mu = v.number(f"{entry}.floor_mu", "floor_mu", d["floor_mu"], nonneg=True)
        out.append(ds)
    return out


def _mesh(v, entry, m):
    if not isinstance(m, dict):
        v.err(entry, f"must be a mapping (file, box, or vertices and tets), got {m!r}")
    if "file" in m:
        v.keys(entry, m, {"file"})
        p = v.named_file(entry, "file", m["file"], "mesh")
        if p.suffix.lower() not in FORMATS:
            v.err(entry, f"mesh file {p.name}: unsupported format (meshio formats {', '.join(FORMATS)})")
        try:
            x, t = read_tets(p)
        except MeshReadError as e:
            v.err(entry, str(e))
        return x, t, str(p)
    if "box" in m:
        v.keys(entry, m, {"box"})
        b = m["box"]
        v.keys(f"{entry}.box", b, {"lo", "size", "cells"}, required=("size", "cells"))
        size = v.vector(f"{entry}.box", "size", b["size"], 3)
        if np.any(size <= 0):
            v.err(f"{entry}.box", "'size' must be positive")
        cells = b["cells"]
        if (not isinstance(cells, list) or len(cells) != 3
                or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 1 for c in cells)
                or np.prod(cells) > MAX_VERTICES // 6):
            v.err(f"{entry}.box", f"'cells' must be 3 positive integers (at most {MAX_VERTICES // 6} cells), got {cells!r}")
        lo = v.vector(f"{entry}.box", "lo", b.get("lo", list(-0.5 * size)), 3)
        x, t = meshes.box_tets(lo, size, cells)
        return x, t, "box"
    v.keys(entry, m, {"vertices", "tets"}, required=("vertices", "tets"))
    try:
        x = np.asarray(m["vertices"], dtype=float)
        t = np.asarray(m["tets"], dtype=np.int64)
    except (TypeError, ValueError):
        v.err(entry, "'vertices' must be (n,3) numbers and 'tets' (T,4) integers")
    if x.ndim != 2 or x.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 4 or not np.isfinite(x).all():
        v.err(entry, f"'vertices' must be (n,3) finite numbers and 'tets' (T,4), got {x.shape} and {t.shape}")
    if len(t) and (t.min() < 0 or t.max() >= len(x)):
        v.err(entry, "a tetrahedron names a vertex out of range")
    return x, t, "inline"


def _attachments(v, entry, lst, body_names, n):
    if not isinstance(lst, list):
        v.err(entry, "must be a list")
    out = []
    for i, a in enumerate(lst):
        e = f"{entry}[{i}]"
        v.keys(e, a, {"body", "vertices", "inside"}, required=("body",))
        body = str(a["body"])
        if body != "world" and body not in body_names:
            v.err(e, f"unknown body '{body}'")
        inside = bool(a.get("inside", False))
        verts = a.get("vertices")
        if inside == (verts is not None):
            v.err(e, "give either 'vertices' or 'inside: true'")
        if inside and body == "world":
            v.err(e, "'inside' needs a body with a shape, not world")
        if verts is not None:
            if (not isinstance(verts, list) or not verts
                    or not all(isinstance(k, int) and not isinstance(k, bool) and -n <= k < n for k in verts)):
                v.err(e, f"'vertices' must be a non-empty list of vertex indices in [-{n}, {n}), got {verts!r}")
        out.append(AttachmentSpec(body, verts, inside))
    return out
