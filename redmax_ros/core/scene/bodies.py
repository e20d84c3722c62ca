"""Composite bodies (parts with transforms) and triangle-mesh bodies for scene files.

* **Composite body** (``parts:``): each part is a primitive shape, a mesh, or explicit mass properties,
  placed in the body's *design frame* by ``pos``/``rpy``. The combined mass, COM and inertia about the
  COM are m = sum m_i, c = sum m_i c_i / m, I = sum [R_i I_i R_i^T + m_i (|d_i|^2 I - d_i d_i^T)],
  d_i = c_i - c (parallel-axis theorem), with c_i = p_i + R_i com_i the part COMs in the design frame.
* **Mesh body** (``shape: {type: mesh, file, scale}``): mass properties of the closed OBJ surface by
  Mirtich's polyhedral volume integrals (mesh.py).
* **Principal body frame** (``frame: principal``, notes §2.1: "body frames are located at the center
  of mass with their axes oriented according to the rotational inertia"): the body frame becomes the
  COM with the principal axes (eigenvalues ascending, right-handed); the inertia is then diagonal.
  Everything the scene file says about the body (its parent joint's ``body_placement``, its child
  joints' ``placement``, its sites) stays written in the design frame and is converted here, so
  switching the option does not move anything physically; it changes the frame reported by
  ``Simulator.body_poses`` (and used for markers). Contact geometry of the friction/contact schema
  is not converted: give it in the principal frame for such bodies.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.geometry.mesh import MeshError, mass_properties, read_obj
from redmax_ros.core.spatial import placement
from redmax_ros.core.scene import files
from redmax_ros.core.scene.spec import BodySpec

BODY_KEYS = {"name", "parts", "shape", "density", "mass", "damping", "rgba", "frame"}
PART_KEYS = {"name", "shape", "density", "mass", "com", "inertia", "pos", "rpy"}


DAMPING_FORMS = ("mass", "twist")


def body_damping(v, entry, value):
    """The body-damping entry of a body: ``damping: c`` (mass-proportional) or
    ``damping: {c: c, form: mass | twist}``. Returns (c, form). Both forms are maximal damping
    matrices D_m of Eq. (2) (notes §1.9.1, damping force f = -D phi, D = -df/dphi), implicit:
      * ``mass`` (default): D_m = c diag(m I3, I_com) at the COM, c in 1/s (every body's velocity
        decays at the rate c, independent of its size);
      * ``twist``: the reference's wrench -c phi on all six components of the body twist
        phi = (omega, nu) in the body frame at the COM, D_m = c I6 (c in N m s for the angular and
        N s/m for the linear part; c I6 is invariant under a rotation of the frame, so the design and
        principal frames give the same D_m)."""
    if isinstance(value, dict):
        v.keys(f"{entry} damping", value, {"c", "form"}, required=("c",))
        form = value.get("form", "mass")
        if form not in DAMPING_FORMS:
            v.err(entry, f"'damping.form' must be one of {list(DAMPING_FORMS)}, got {form!r}")
        return v.number(entry, "damping.c", value["c"], nonneg=True), form
    return v.number(entry, "damping", value, nonneg=True), "mass"


def handles(d) -> bool:
    """True for body entries this module validates (composite or mesh bodies)."""
    if not isinstance(d, dict):
        return False
    shape = d.get("shape")
    return "parts" in d or (isinstance(shape, dict) and shape.get("type") == "mesh")


def combine(parts):
    """(mass, com (3,), inertia about com (3,3)) of parts given as (mass, com_in_design_frame, R, I_com)."""
    m = sum(p[0] for p in parts)
    c = sum(p[0] * np.asarray(p[1], float) for p in parts) / m
    I = np.zeros((3, 3))
    for mi, ci, Ri, Ii in parts:
        d = np.asarray(ci, float) - c
        I += Ri @ Ii @ Ri.T + mi * (float(d @ d) * np.eye(3) - np.outer(d, d))
    return m, c, 0.5 * (I + I.T)


def principal_frame(com, inertia) -> tuple:
    """(R, eigenvalues): principal axes (columns of R, right-handed) and moments, ascending."""
    w, R = np.linalg.eigh(inertia)
    if np.linalg.det(R) < 0:
        R[:, 2] = -R[:, 2]
    return R, w


def _mesh(v, entry, shape, base_dir, density=None, mass=None):
    v.keys(f"{entry} shape", shape, {"type", "file", "scale"}, required=("type", "file"))
    p = v.named_file(entry, "shape.file", shape["file"], "mesh")  # relative to base_dir; confined, capped
    scale = shape.get("scale", 1.0)
    scale = v.vector(entry, "shape.scale", scale, 3, allow_scalar=True)
    if np.any(scale <= 0):
        v.err(entry, f"shape.scale must be positive, got {scale.tolist()}")
    try:
        text = files.read_capped(p, files.MAX_MESH_BYTES).decode("utf-8", errors="replace")
    except files.FileProblem as e:
        v.err(entry, f"mesh file {p.name}: {e}")
    try:
        mesh = read_obj(p, scale, text=text)
        m, c, I, vol = mass_properties(mesh, density=density, mass=mass)
    except MeshError as e:
        v.err(entry, f"mesh {p.name}: {e}")
    except OverflowError:
        v.err(entry, f"mesh {p.name}: its coordinates overflow with shape.scale {scale.tolist()} (too large)")
    return m, c, I, {"type": "mesh", "file": str(p), "scale": scale.tolist(), "volume": vol}


def _part(v, entry, d, base_dir):
    """(mass, com in design frame, R, I_com) of one part."""
    v.keys(entry, d, PART_KEYS)
    M = placement(v.vector(entry, "pos", d.get("pos", [0, 0, 0]), 3), v.vector(entry, "rpy", d.get("rpy", [0, 0, 0]), 3))
    shape = d.get("shape")
    if isinstance(shape, dict) and shape.get("type") == "mesh":
        if ("mass" in d) == ("density" in d):
            v.err(entry, "give either 'mass' or 'density' for a mesh part")
        if "com" in d or "inertia" in d:
            v.err(entry, "a mesh part takes its COM and inertia from the mesh")
        dens = v.number(entry, "density", d["density"], positive=True) if "density" in d else None
        mass = v.number(entry, "mass", d["mass"], positive=True) if "mass" in d else None
        m, c, I, _ = _mesh(v, entry, shape, base_dir, dens, mass)
    else:
        sub = {k: d[k] for k in ("shape", "density", "mass", "com", "inertia") if k in d}
        b = v.body(entry, {"name": "part", **sub})
        m, c, I = b.mass, b.com, b.inertia
    return m, M.act(np.asarray(c, float)), M.rotation, np.asarray(I, float)


def validate_body(v, entry, d, base_dir):
    """A BodySpec for a composite or mesh body (``v``: the scene _Validator)."""
    v.keys(entry, d, BODY_KEYS)
    frame = d.get("frame", "design")
    if frame not in ("design", "principal"):
        v.err(entry, f"'frame' must be 'design' or 'principal', got {frame!r}")
    if "parts" in d:
        if "shape" in d or "mass" in d or "density" in d:
            v.err(entry, "a composite body takes 'parts' only (mass/density/shape go on the parts)")
        parts = d["parts"]
        if not isinstance(parts, list) or not parts:
            v.err(entry, "'parts' must be a non-empty list")
        props = [_part(v, f"{entry} parts[{i}]", p, base_dir) for i, p in enumerate(parts)]
        m, c, I = combine(props)
        shape = {"type": "composite", "parts": [dict(p) for p in parts]}
    else:
        if ("mass" in d) == ("density" in d):
            v.err(entry, "needs either 'mass' or 'density' (not both)")
        dens = v.number(entry, "density", d["density"], positive=True) if "density" in d else None
        mass = v.number(entry, "mass", d["mass"], positive=True) if "mass" in d else None
        m, c, I, shape = _mesh(v, entry, d["shape"], base_dir, dens, mass)
    v.finite_mass_properties(entry, m, c, I)
    ev = np.linalg.eigvalsh(I)
    if ev[0] <= 0:
        v.err(entry, f"inertia is not positive definite (eigenvalues {ev.tolist()}); a flat or degenerate body?")
    damping, dform = body_damping(v, entry, d.get("damping", 0.0))
    rgba = tuple(v.vector(entry, "rgba", d.get("rgba", [0.7, 0.7, 0.75, 1.0]), 4))
    shape["frame"] = frame
    if frame == "principal":
        R, w = principal_frame(c, I)
        shape["principal"] = (R, np.asarray(c, float))  # principal frame in the design frame
    return BodySpec(d["name"], float(m), np.asarray(c, float), I, shape, damping, rgba, dform)


def _pose(M: pin.SE3):
    return (M.translation.copy(), pin.rpy.matrixToRpy(M.rotation))


def apply_principal_frames(spec) -> None:
    """Re-express bodies with ``frame: principal`` in their principal frame (see module doc)."""
    for b in spec.bodies:
        shape = b.shape if isinstance(b.shape, dict) else {}
        if shape.get("frame") != "principal" or "principal_applied" in shape:
            continue
        R, c = shape["principal"]
        X = pin.SE3(R, c)  # principal frame in the design frame
        Xi = X.inverse()
        w = np.linalg.eigvalsh(b.inertia)
        b.inertia = np.diag(np.diag(R.T @ b.inertia @ R))
        b.com = np.zeros(3)
        for j in spec.joints:
            if j.child == b.name:
                j.body_placement = _pose(placement(*j.body_placement) * X)
            if j.parent == b.name:
                j.placement = _pose(Xi * placement(*j.placement))
        for s in spec.sites:
            if s.body == b.name:
                s.pos = Xi.act(np.asarray(s.pos, float))
        shape["principal_applied"] = True
        shape["moments"] = w.tolist()
