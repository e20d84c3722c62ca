"""Scene files: YAML -> validated :class:`SceneSpec` (pure data, SI units).

Schema: docs/scenes.md. Every problem raises :class:`SceneError` naming the file, the entry and
what is wrong. Parametric scenes name a builder (``builder: chain``) whose output is a scene dict
of the same schema; YAML lists beside the builder are appended to the builder's.
"""
from __future__ import annotations

import copy
import math
import os
from pathlib import Path

import numpy as np
import pinocchio as pin

from redmax_ros.core.errors import SceneError, SceneNotFound
from redmax_ros.core.geometry.inertia import shape_inertia, shape_volume
from redmax_ros.core.scene import (bodies, body_twist, catalogue_schema, collision_schema, contact_schema,
                                   deformable_schema, files,
                                   timefunctions)
from redmax_ros.core.scene import builders, builders_friction, builders_hagfish, builders_large, builders_starfish  # noqa: F401  (register the shipped builders)
from redmax_ros.core.scene.registry import BUILDERS
from redmax_ros.core.scene.spec import (CORE_JOINT_TYPES, SCHEMES, SOLVERS, SPRING_STIFFNESS, WORLD, BodySpec, CouplingSpec, JointSpec, LoopSpec, SceneSpec, SiteSpec,
                                        SpringSpec, WrenchSpec, numeric, numeric_deep)

JOINT_TYPES = {**CORE_JOINT_TYPES, **catalogue_schema.TYPES}  # notes §2.5 catalogue (joints.py, joint_maps.py; composite: per joint)
SHAPES = {"box": ("size",), "sphere": ("radius",), "cylinder": ("radius", "length"), "capsule": ("radius", "length")}
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def _scenes_dir() -> Path:
    """Where shipped scenes live: $REDMAX_SCENES_DIR, the source tree (scenes/ beside the package),
    or an install prefix's share/redmax_ros/scenes (colcon/pip install: <prefix>/lib/python3.X/
    site-packages/redmax_ros/core/scene/loader.py)."""
    env = os.environ.get("REDMAX_SCENES_DIR")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    source = here.parents[3] / "scenes"
    if source.is_dir():
        return source
    for parent in here.parents:
        cand = parent / "share" / "redmax_ros" / "scenes"
        if cand.is_dir():
            return cand
    return source


SCENES_DIR = _scenes_dir()


# ----------------------------------------------------------------------------------------------
# entry points


def resolve_scene_path(name_or_path: str, *, allowed_dirs=None) -> Path:
    """The real path (symlinks resolved) of a scene given by name (``hand``, ``catalogue/gear``: a
    ``.yaml`` file in a scene directory) or by path to a YAML file.

    ``allowed_dirs=None`` (offline use: redmax_run, tests, ``Simulator.load``): any path the process
    can read; relative paths first against the working directory, names in SCENES_DIR. With
    ``allowed_dirs`` (a list of directories; SCENES_DIR is always allowed, and searched first): names
    and relative paths resolve inside those directories only (never against the working directory),
    ``..`` may not climb above the directory, and the file's real path (every symlink resolved) must
    lie inside one of them and end in ``.yaml`` / ``.yml``; otherwise :class:`SceneNotFound`
    "outside the allowed scene directories", decided before the file is looked at, so the answer is
    the same whether or not such a file exists."""
    if allowed_dirs is not None:
        return _resolve_confined(str(name_or_path), scene_roots(allowed_dirs))
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") and p.exists():
        return files.real(p)
    for cand in (SCENES_DIR / f"{name_or_path}.yaml", SCENES_DIR / name_or_path):
        if cand.is_file():
            return files.real(cand)
    known = ", ".join(list_scenes())
    raise SceneNotFound(str(name_or_path), "", f"no such scene file or scene name (known scenes: {known})")


def scene_roots(allowed_dirs) -> list:
    """SCENES_DIR and ``allowed_dirs`` as real paths, without repeats; SceneError naming an entry that
    is not an existing directory."""
    roots = []
    for d in [SCENES_DIR, *allowed_dirs]:
        if not isinstance(d, (str, os.PathLike)) or not os.fspath(d):
            raise SceneError(repr(d), "", "an allowed scene directory must be a non-empty path")
        r = files.real(d)
        if not r.is_dir():
            raise SceneError(str(d), "", "allowed scene directory does not exist or is not a directory")
        if r not in roots:
            roots.append(r)
    return roots


def _resolve_confined(name: str, roots: list) -> Path:
    shown = name if name.isprintable() and len(name) <= 200 else repr(name)[:200]  # the request, as text
    outside = f"outside the allowed scene directories ({', '.join(map(str, roots))})"
    try:
        p = Path(name)
        if p.is_absolute():
            cands = [Path(f"{name}.yaml"), p]
        else:
            if files.climbs(name):
                raise SceneNotFound(shown, "", outside)
            cands = [c for r in roots for c in (r / f"{name}.yaml", r / name)]
        for cand in cands:
            rc = files.real(cand)
            if not any(files.inside(rc, r) for r in roots):
                raise SceneNotFound(shown, "", outside)
            if rc.is_file():
                if rc.suffix not in (".yaml", ".yml"):
                    raise SceneNotFound(shown, "", "not a scene file (a scene file's name ends in .yaml or .yml)")
                return rc
    except (OSError, ValueError) as e:  # a NUL byte, a name too long, ...
        if isinstance(e, SceneError):
            raise
        raise SceneNotFound(shown, "", f"not a usable scene name or path ({type(e).__name__})") from None
    names = list_scenes(roots[1:])
    known = ", ".join(names[:100]) + (f", ... ({len(names) - 100} more)" if len(names) > 100 else "")
    raise SceneNotFound(shown, "", f"no such scene file or scene name (known scenes: {known})")


def list_scenes(allowed_dirs=()) -> list:
    """Names of the scenes shipped in ``scenes/`` and (``allowed_dirs``) in other scene directories
    (their ``.yaml`` files, relative to the directory, without the suffix; sorted, without repeats)."""
    names = set()
    for d in [SCENES_DIR, *allowed_dirs]:
        root = files.real(d)
        names.update(str(p.relative_to(d).with_suffix("")) for p in Path(d).rglob("*.yaml")
                     if files.inside(files.real(p), root))
    return sorted(names)


def load_scene(name_or_path: str, overrides=(), *, allowed_dirs=None) -> SceneSpec:
    """Read, expand (builder), override (``key=value``) and validate a scene.

    ``allowed_dirs``: None (any path; offline use) or the directories a scene may come from besides
    SCENES_DIR (see :func:`resolve_scene_path`); with it, the meshes and URDF the scene names must lie
    inside the scene file's own directory. Always: the YAML file at most files.MAX_SCENE_BYTES, a
    named file at most files.MAX_MESH_BYTES, the YAML document within files.MAX_YAML_NODES /
    MAX_YAML_DEPTH (alias bombs). No error message quotes the file."""
    path = resolve_scene_path(name_or_path, allowed_dirs=allowed_dirs)
    src = str(path)
    try:
        raw = files.parse_yaml(files.read_capped(path, files.MAX_SCENE_BYTES))
    except files.FileProblem as e:
        raise SceneError(src, "", str(e)) from None
    if not isinstance(raw, dict):
        raise SceneError(src, "", "top level must be a mapping")
    raw.setdefault("name", path.stem)
    return scene_from_dict(raw, src, overrides, base_dir=path.parent, confine_files=allowed_dirs is not None)


def parse_joint_trajectory(entry: str, d, nv: int, source: str = "command"):
    """A joint trajectory ``{position: <time function or list of nv>, b: 5}`` in the scene grammar
    (``prescribed.joints.<name>``, timefunctions.parse_trajectory), for commands; SceneError naming ``entry``."""
    return timefunctions.parse_trajectory(_Validator(source, None), entry, d, nv)


def parse_time_function(entry: str, key: str, d, source: str = "command"):
    """One time function (a number or ``{type: ..., ...}``, timefunctions.parse) for commands, e.g. a timed
    component of a body twist; SceneError naming ``entry`` and ``key``."""
    return timefunctions.parse(_Validator(source, None), entry, key, d)


def scene_from_dict(raw: dict, source: str = "<dict>", overrides=(), base_dir: Path | None = None, *,
                    confine_files: bool = False) -> SceneSpec:
    """Validate a scene given as a dict (the parsed YAML). Files it names (meshes, URDF) are relative
    to ``base_dir``; ``confine_files``: they must lie inside it (real paths; no absolute paths)."""
    raw = copy.deepcopy(raw)
    ov = [_parse_override(source, o) for o in overrides]
    # Builder parameters first (they shape the model), everything else after expansion.
    for keys, val in ov:
        if keys[0] in ("params", "builder"):
            _apply_override(source, raw, keys, val, create=True)
    if "builder" in raw:
        raw = _expand_builder(raw, source)
    for keys, val in ov:
        if keys[0] not in ("params", "builder"):
            _apply_override(source, raw, keys, val, create=len(keys) == 1)
    return _Validator(source, base_dir, confine_files).scene(raw)


# ----------------------------------------------------------------------------------------------
# overrides: "dt=0.002", "params.n=20", "joints.elbow.q0=0.3", "springs.0.stiffness=10"


def _parse_override(source, text):
    if not isinstance(text, str) or "=" not in text:
        raise SceneError(source, f"override {text!r}", "expected key=value")
    key, _, val = text.partition("=")
    keys = [k for k in key.strip().split(".") if k]
    if not keys:
        raise SceneError(source, f"override {text!r}", "empty key")
    try:
        value = files.parse_yaml(val)
    except files.FileProblem as e:
        raise SceneError(source, f"override {text!r}", f"value is {e}") from None
    return keys, value


# optional top-level mappings an override may create (``--set integrator.scheme=bdf2`` on a scene without one)
OPTIONAL_SECTIONS = ("params", "integrator", "stabilization")


def _apply_override(source, raw, keys, value, create):
    node = raw
    path = []
    for i, k in enumerate(keys):
        last = i == len(keys) - 1
        path.append(k)
        where = f"override '{'.'.join(keys)}'"
        if isinstance(node, list):
            idx = None
            if k.isdigit() and int(k) < len(node):
                idx = int(k)
            else:
                names = [e.get("name") if isinstance(e, dict) else None for e in node]
                if k in names:
                    idx = names.index(k)
            if idx is None:
                raise SceneError(source, where, f"no entry named '{k}' in '{'.'.join(path[:-1])}'")
            if last:
                node[idx] = value
            else:
                node = node[idx]
        elif isinstance(node, dict):
            if last:
                if k not in node and not (create or i > 0):
                    raise SceneError(source, where, f"unknown key '{k}'")
                node[k] = value
            else:
                if k not in node:
                    if create or (i == 0 and k in OPTIONAL_SECTIONS):
                        node[k] = {}
                    else:
                        raise SceneError(source, where, f"unknown key '{'.'.join(path)}'")
                node = node[k]
        else:
            raise SceneError(source, where, f"'{'.'.join(path[:-1])}' is not a mapping or list")


def _expand_builder(raw, source):
    name = raw.pop("builder")
    if not isinstance(name, str) or name not in BUILDERS:
        raise SceneError(source, "builder", f"unknown builder '{name}' (known: {', '.join(sorted(BUILDERS))})")
    params = raw.pop("params", {}) or {}
    if not isinstance(params, dict):
        raise SceneError(source, "params", "must be a mapping")
    params = {k: numeric_deep(v) for k, v in params.items()}  # '1e3' (YAML 1.1 string) -> 1000.0
    try:
        built = BUILDERS[name](dict(params))
    except SceneError:
        raise
    except (TypeError, ValueError, KeyError) as e:
        raise SceneError(source, f"params of builder '{name}'", str(e)) from None
    for key, val in raw.items():
        if isinstance(val, list) and isinstance(built.get(key), list):
            built[key] = built[key] + val
        elif isinstance(val, dict) and isinstance(built.get(key), dict):
            built[key] = {**built[key], **val}
        else:
            built[key] = val
    n = len(built.get("bodies") or [])
    if n > files.MAX_BODIES:
        raise SceneError(source, f"params of builder '{name}'", f"the scene would have {n} bodies, above the limit "
                                                                f"of {files.MAX_BODIES}")
    built["params"] = params
    return built


# ----------------------------------------------------------------------------------------------
# validation


class _Validator:
    """Turns the raw dict into a SceneSpec, naming the entry of every problem."""

    def __init__(self, source: str, base_dir: Path | None, confine_files: bool = False):
        self.src = source
        self.base_dir = base_dir
        self.confine_files = confine_files

    def err(self, entry, problem):
        raise SceneError(self.src, entry, problem)

    def named_file(self, entry, key, value, what) -> Path:
        """The path of a file the scene names (``what``: "mesh", "URDF"), relative to the scene
        file's directory; with confine_files it must lie inside that directory (real path, no
        absolute path, no ``..`` above it). Must exist; at most files.MAX_MESH_BYTES."""
        if not isinstance(value, str) or not value:
            self.err(entry, f"'{key}' must be a file path (a non-empty string)")
        p = Path(value)
        if self.confine_files:
            if self.base_dir is None:
                self.err(entry, f"'{key}': this scene has no directory its {what} file could be in")
            if p.is_absolute():
                self.err(entry, f"'{key}': an absolute path is not allowed here; give the {what} file's path "
                                "relative to the scene file's directory")
            base = files.real(self.base_dir)
            try:
                rp = files.real(base / p)
            except (OSError, ValueError) as e:
                self.err(entry, f"'{key}': not a usable path ({type(e).__name__})")
            if files.climbs(value) or not files.inside(rp, base):
                self.err(entry, f"'{key}': the {what} file must lie inside the scene file's directory {base}")
            p = rp
        else:
            if not p.is_absolute() and self.base_dir is not None:
                p = Path(self.base_dir) / p
            p = files.real(p)  # read what was checked, even if a symlink changes meanwhile
        if not p.is_file():
            self.err(entry, f"{what} file not found: {p}")
        try:
            files.check_size(p, files.MAX_MESH_BYTES)
        except files.FileProblem as e:
            self.err(entry, f"{what} file {p.name}: {e}")
        return p

    # -- scalars and vectors
    def number(self, entry, key, value, *, positive=False, nonneg=False):
        value = numeric(value)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.err(entry, f"'{key}' must be a number, got {value!r}")
        v = float(value)
        if not math.isfinite(v):
            self.err(entry, f"'{key}' must be finite, got {value!r}")
        if positive and v <= 0:
            self.err(entry, f"'{key}' must be positive, got {v}")
        if nonneg and v < 0:
            self.err(entry, f"'{key}' must be non-negative, got {v}")
        return v

    def vector(self, entry, key, value, n, *, allow_scalar=False, allow_inf=False):
        if allow_scalar and isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value] * n
        if isinstance(value, (int, float)) and n == 1 and not isinstance(value, bool):
            value = [value]
        if not isinstance(value, (list, tuple)):
            self.err(entry, f"'{key}' must be a list of {n} numbers, got {value!r}")
        if len(value) != n:
            self.err(entry, f"'{key}' must have {n} values, got {len(value)}")
        out = []
        for x in value:
            x = numeric(x)
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                self.err(entry, f"'{key}' must contain numbers, got {x!r}")
            if not allow_inf and not math.isfinite(float(x)):
                self.err(entry, f"'{key}' must be finite, got {x!r}")
            if math.isnan(float(x)):
                self.err(entry, f"'{key}' must not be NaN")
            out.append(float(x))
        return np.array(out)

    def finite_mass_properties(self, entry, mass, com, inertia):
        """SceneError unless mass, COM and inertia are finite (huge sizes, positions or densities overflow)."""
        if not (math.isfinite(mass) and np.all(np.isfinite(com)) and np.all(np.isfinite(inertia))):
            self.err(entry, f"mass properties are not finite (mass {mass:.3g}, largest inertia "
                            f"{np.max(np.abs(inertia)):.3g}): a size, position or density is too large")

    def keys(self, entry, d, allowed, required=()):
        if not isinstance(d, dict):
            self.err(entry, f"must be a mapping, got {d!r}")
        for k in required:
            if k not in d:
                self.err(entry, f"missing '{k}'")
        unknown = sorted(set(d) - set(allowed))
        if unknown:
            self.err(entry, f"unknown key(s) {unknown} (allowed: {sorted(allowed)})")

    def entries(self, raw, key):
        val = raw.get(key, []) or []
        if not isinstance(val, list):
            self.err(key, "must be a list")
        limit = files.MAX_BODIES if key in ("bodies", "joints") else files.MAX_ENTRIES
        if len(val) > limit:
            self.err(key, f"has {len(val)} entries, above the limit of {limit}")
        seen = {}
        out = []
        for i, e in enumerate(val):
            entry = f"{key}[{i}]"
            if not isinstance(e, dict):
                self.err(entry, "must be a mapping")
            name = e.get("name")
            if not isinstance(name, str) or not name:
                self.err(entry, "missing 'name' (a non-empty string)")
            entry = f"{key}[{i}] '{name}'"
            if name in seen:
                self.err(entry, f"duplicate name '{name}' (also {key}[{seen[name]}])")
            seen[name] = i
            out.append((entry, e))
        return out

    # -- sections
    def scene(self, raw) -> SceneSpec:
        top = {"name", "description", "units", "gravity", "dt", "duration", "bodies", "joints", "sites", "springs",
               "wrenches", "loops", "couplings", "prescribable", "prescribed", "urdf", "params", "solver",
               "integrator", "stabilization"}
        top |= contact_schema.TOP_KEYS | catalogue_schema.TOP_KEYS | collision_schema.TOP_KEYS | deformable_schema.TOP_KEYS
        self.keys("scene", raw, top)
        if raw.get("units", "SI") != "SI":
            self.err("units", f"only SI units are supported, got {raw.get('units')!r}")
        spec = SceneSpec(
            name=str(raw.get("name", "scene")),
            source=self.src,
            gravity=self.vector("gravity", "gravity", raw.get("gravity", [0.0, 0.0, -9.81]), 3),
            dt=self.number("dt", "dt", raw.get("dt", 1e-3), positive=True),
            duration=self.number("duration", "duration", raw.get("duration", 5.0), positive=True),
            description=str(raw.get("description", "")),
            solver=str(raw.get("solver", "direct")),
            raw=raw,
        )
        if spec.solver not in SOLVERS:
            self.err("solver", f"unknown solver '{spec.solver}' ({', '.join(SOLVERS)})")
        if "urdf" in raw:
            self.urdf(spec, raw["urdf"])
        spec.bodies = [self.body(e, d) for e, d in self.entries(raw, "bodies")]
        spec.joints = [self.joint(e, d) for e, d in self.entries(raw, "joints")]
        if spec.urdf and (spec.bodies or spec.joints):
            self.err("urdf", "a URDF scene takes its bodies and joints from the URDF; remove 'bodies'/'joints'")
        if not spec.urdf:
            self.tree(spec)
        body_names = self.body_names(spec)
        spec.sites = [self.site(e, d, body_names) for e, d in self.entries(raw, "sites")]
        site_names = {s.name for s in spec.sites}
        spec.springs = [self.spring(e, d, site_names) for e, d in self.entries(raw, "springs")]
        spec.wrenches = [self.wrench(e, d, body_names) for e, d in self.entries(raw, "wrenches")]
        spec.loops = [self.loop(e, d, site_names) for e, d in self.entries(raw, "loops")]
        spec.couplings = [self.coupling(e, d, spec) for e, d in self.entries(raw, "couplings")]
        self.prescriptions(spec, raw, site_names)
        spec.friction = contact_schema.parse(self, raw, spec, body_names)
        spec.catalogue = catalogue_schema.parse(self, raw, spec, body_names)
        spec.collision = collision_schema.parse(self, raw, spec, body_names)  # self-collision (docs/collisions.md)
        spec.deformables = deformable_schema.parse(self, raw, spec, body_names)  # docs/deformables.md
        self.integrator(spec, raw.get("integrator"))
        self.stabilization(spec, raw.get("stabilization"))
        return spec

    def stabilization(self, spec, d):
        """``stabilization: {method: post | baumgarte, b: 5.0}`` (docs/scenes.md, "Loop stabilization")."""
        if d is None:
            return
        if not isinstance(d, dict):
            self.err("stabilization", f"must be a mapping such as {{method: baumgarte, b: 5.0}}, got {d!r}")
        self.keys("stabilization", d, {"method", "b"})
        method = d.get("method", "post")
        if method not in ("post", "baumgarte"):
            self.err("stabilization.method", f"unknown value {method!r} (post, baumgarte)")
        if "b" in d and method != "baumgarte":
            self.err("stabilization.b", "is the Baumgarte gain; it needs method: baumgarte")
        spec.stabilization = method
        spec.baumgarte_b = self.number("stabilization.b", "b", d.get("b", 5.0), positive=True)

    def integrator(self, spec, d):
        """``integrator: {scheme: euler | bdf2, coriolis: explicit | implicit, spring_stiffness: full | gauss_newton}``
        (docs/scenes.md, "Integrator")."""
        if d is None:
            return
        if not isinstance(d, dict):
            self.err("integrator", f"must be a mapping such as {{scheme: bdf2}}, got {d!r}")
        self.keys("integrator", d, {"coriolis", "scheme", "spring_stiffness"})
        scheme = d.get("scheme", "euler")
        if scheme not in SCHEMES:
            self.err("integrator.scheme", f"unknown value {scheme!r} ({', '.join(SCHEMES)})")
        if scheme == "bdf2":
            if spec.friction is not None:
                self.err("integrator.scheme", "'bdf2' is not supported with contact or joint friction (Staggered "
                         "Projections / BISP are derived for the BDF1 step); use scheme: euler")
            if spec.collision is not None:
                self.err("integrator.scheme", "'bdf2' is not supported with self-collision (the contact rows are "
                         "linearised about the BDF1 step, Eq. 5); use scheme: euler")
        spec.scheme = scheme
        c = d.get("coriolis", "explicit")
        if c not in ("explicit", "implicit"):
            self.err("integrator.coriolis", f"unknown value {c!r} (explicit, implicit)")
        if c == "implicit":
            if spec.solver != "direct":
                self.err("integrator.coriolis", f"'implicit' needs solver: direct (the Pinocchio pipeline); "
                         f"solver '{spec.solver}' does not support it")
            if spec.friction is not None:
                self.err("integrator.coriolis", "'implicit' is not supported with contact or joint friction "
                         "(the staggered solve needs a symmetric LHS); use coriolis: explicit")
        spec.coriolis = c
        ks = d.get("spring_stiffness", "full")
        if ks not in SPRING_STIFFNESS:
            self.err("integrator.spring_stiffness", f"unknown value {ks!r} ({', '.join(SPRING_STIFFNESS)})")
        spec.spring_stiffness = ks

    def urdf(self, spec, d):
        if isinstance(d, str):
            d = {"file": d}
        self.keys("urdf", d, {"file", "fixed_base"}, required=("file",))
        p = self.named_file("urdf", "file", d["file"], "URDF")
        spec.urdf = str(p)
        spec.urdf_fixed_base = bool(d.get("fixed_base", True))

    def body(self, entry, d) -> BodySpec:
        if bodies.handles(d):  # composite (parts) and mesh bodies
            return bodies.validate_body(self, entry, d, self.base_dir)
        self.keys(entry, d, {"name", "shape", "density", "mass", "com", "inertia", "damping", "rgba"})
        shape = d.get("shape")
        if shape is not None:
            self.keys(f"{entry} shape", shape, {"type", "size", "radius", "length"}, required=("type",))
            if not isinstance(shape["type"], str) or shape["type"] not in SHAPES:
                self.err(entry, f"unknown shape type '{shape['type']}' (known: {', '.join(SHAPES)})")
            shape = dict(shape)
            for k in SHAPES[shape["type"]]:
                if k not in shape:
                    self.err(entry, f"shape '{shape['type']}' needs '{k}'")
                if k == "size":
                    shape[k] = self.vector(entry, "shape.size", shape[k], 3)
                    if np.any(shape[k] <= 0):
                        self.err(entry, f"shape.size must be positive, got {shape[k].tolist()}")
                    shape[k] = shape[k].tolist()
                else:
                    shape[k] = self.number(entry, f"shape.{k}", shape[k], positive=True)
        if "mass" in d and "density" in d:
            self.err(entry, "give either 'mass' or 'density', not both")
        if "mass" in d:
            mass = self.number(entry, "mass", d["mass"])
            if mass <= 0:
                self.err(entry, f"mass must be positive, got {mass}")
        elif "density" in d:
            rho = self.number(entry, "density", d["density"])
            if rho <= 0:
                self.err(entry, f"density must be positive, got {rho}")
            if shape is None:
                self.err(entry, "'density' needs a 'shape'")
            mass = rho * shape_volume(shape)
        else:
            self.err(entry, "needs 'mass' or 'density'")
        com = self.vector(entry, "com", d.get("com", [0, 0, 0]), 3)
        if "inertia" in d:
            I = d["inertia"]
            if isinstance(I, list) and len(I) == 3 and all(isinstance(r, list) for r in I):
                I = np.array([self.vector(entry, "inertia", r, 3) for r in I])
            else:
                v = self.vector(entry, "inertia ([ixx, iyy, izz, ixy, ixz, iyz])", I, 6)
                I = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
            if not np.allclose(I, I.T):
                self.err(entry, "inertia must be symmetric")
        elif shape is not None:
            I = shape_inertia(shape, mass)
        else:
            self.err(entry, "needs 'inertia' or a 'shape' to compute it from")
        self.finite_mass_properties(entry, mass, com, I)
        ev = np.linalg.eigvalsh(I)
        if ev[0] <= 0:
            self.err(entry, f"inertia is not positive definite (eigenvalues {np.round(ev, 12).tolist()})")
        if ev[2] > ev[0] + ev[1] + 1e-12 * ev[2]:
            self.err(entry, f"inertia violates the triangle inequality (eigenvalues {ev.tolist()})")
        damping, dform = bodies.body_damping(self, entry, d.get("damping", 0.0))
        rgba = tuple(self.vector(entry, "rgba", d.get("rgba", [0.7, 0.7, 0.75, 1.0]), 4))
        return BodySpec(d["name"], mass, com, I, shape, damping, rgba, dform)

    def joint(self, entry, d) -> JointSpec:
        if isinstance(d.get("type"), str) and d["type"] in catalogue_schema.TYPES:  # notes §2.5 catalogue joints
            return catalogue_schema.validate_joint(self, entry, d, self.base_dir)
        allowed = {"name", "type", "parent", "child", "placement", "body_placement", "axis", "axes", "q0", "v0",
                   "limits", "stiffness", "rest", "damping", "armature", "torque", "friction", "conserve_momentum"}
        self.keys(entry, d, allowed, required=("type", "parent", "child"))
        jt = d["type"]
        extra = {}
        if "conserve_momentum" in d:  # dynamics/momentum.py (with deformables), catalogue_hooks.py (without)
            if jt != "free":
                self.err(entry, f"'conserve_momentum' is an option of free and free3d root joints, not {jt}")
            if not isinstance(d["conserve_momentum"], bool):
                self.err(entry, "'conserve_momentum' must be true or false")
            if d["conserve_momentum"] and d["parent"] != "world":
                self.err(entry, "'conserve_momentum' needs a root joint (parent: world)")
            if d["conserve_momentum"]:
                extra["conserve_momentum"] = True
        if not isinstance(jt, str) or jt not in JOINT_TYPES:
            self.err(entry, f"unknown joint type '{jt}' (known: {', '.join(JOINT_TYPES)})")
        nv, nq0 = JOINT_TYPES[jt]
        for k in ("parent", "child"):
            if not isinstance(d[k], str):
                self.err(entry, f"'{k}' must be a body name")
        axes = np.zeros((0, 3))
        if jt in ("revolute", "prismatic"):
            axes = self.axis(entry, "axis", d.get("axis", "z"))[None, :]
        elif jt == "universal":
            ax = d.get("axes", ["x", "y"])
            if not isinstance(ax, list) or len(ax) != 2:
                self.err(entry, "'axes' of a universal joint must be a list of 2 axes")
            axes = np.array([self.axis(entry, "axes", a) for a in ax])
            if abs(axes[0] @ axes[1]) > 1e-9:
                self.err(entry, "the two axes of a universal joint must be orthogonal")
        elif "axis" in d or "axes" in d:
            self.err(entry, f"a {jt} joint takes no axis")
        placement = self.pose(entry, "placement", d.get("placement", {}))
        body_placement = self.pose(entry, "body_placement", d.get("body_placement", {}))
        q0 = self.vector(entry, "q0", d.get("q0", [0.0] * nq0), nq0, allow_scalar=nq0 == 1)
        v0 = self.vector(entry, "v0", d.get("v0", [0.0] * nv), nv, allow_scalar=nv == 1)
        lower = np.full(nv, -np.inf)
        upper = np.full(nv, np.inf)
        if "limits" in d:
            lim = d["limits"]
            self.keys(f"{entry} limits", lim, {"lower", "upper"})
            if jt not in ("revolute", "prismatic", "universal"):
                self.err(entry, f"limits are supported on revolute, prismatic and universal joints, not {jt}")
            lower = self.vector(entry, "limits.lower", lim.get("lower", -np.inf), nv, allow_scalar=True, allow_inf=True)
            upper = self.vector(entry, "limits.upper", lim.get("upper", np.inf), nv, allow_scalar=True, allow_inf=True)
            if np.any(lower >= upper):
                self.err(entry, f"limits.lower must be below limits.upper ({lower.tolist()} vs {upper.tolist()})")
        def per_dof(key, default=0.0, nonneg=True):
            v = self.vector(entry, key, d.get(key, default), nv, allow_scalar=True)
            if nonneg and np.any(v < 0):
                self.err(entry, f"'{key}' must be non-negative, got {v.tolist()}")
            return v
        rest = self.vector(entry, "rest", d.get("rest", [0.0] * nq0), nq0, allow_scalar=nq0 == 1)
        return JointSpec(d["name"], jt, d["parent"], d["child"], placement, body_placement, axes, q0, v0, lower, upper,
                         per_dof("stiffness"), rest, per_dof("damping"), per_dof("armature"),
                         per_dof("torque", nonneg=False), extra)

    def axis(self, entry, key, a):
        if isinstance(a, str):
            sign = -1.0 if a.startswith("-") else 1.0
            if a.lstrip("+-") not in AXES:
                self.err(entry, f"'{key}' must be x, y, z or a 3-vector, got {a!r}")
            return sign * np.array(AXES[a.lstrip("+-")])
        v = self.vector(entry, key, a, 3)
        n = np.linalg.norm(v)
        if n < 1e-12:
            self.err(entry, f"'{key}' must not be the zero vector")
        return v / n

    def pose(self, entry, key, d):
        self.keys(f"{entry} {key}", d, {"pos", "rpy"})
        return (self.vector(entry, f"{key}.pos", d.get("pos", [0, 0, 0]), 3),
                self.vector(entry, f"{key}.rpy", d.get("rpy", [0, 0, 0]), 3))

    def tree(self, spec):
        bodies = {b.name for b in spec.bodies}
        if not bodies:
            self.err("bodies", "the scene has no bodies (give at least one body and the joint that attaches it)")
        if WORLD in bodies:
            self.err("bodies", "'world' is reserved")
        parent_of = {}
        for i, j in enumerate(spec.joints):
            entry = f"joints[{i}] '{j.name}'"
            if j.parent != WORLD and j.parent not in bodies:
                self.err(entry, f"unknown parent body '{j.parent}'")
            if j.child not in bodies:
                self.err(entry, f"unknown child body '{j.child}'")
            if j.child in parent_of:
                self.err(entry, f"body '{j.child}' already has parent joint '{parent_of[j.child].name}'; "
                                "close kinematic loops with a 'loops' constraint")
            parent_of[j.child] = j
        for b in spec.bodies:
            if b.name not in parent_of:
                self.err(f"bodies '{b.name}'", "no joint attaches this body (add a joint with it as child)")
        # cycles: walk up from every body; must reach the world (bodies known to reach it are
        # remembered, so a long chain costs O(n), not O(n^2) walks with O(n) membership tests)
        reaches = {WORLD}
        for b in spec.bodies:
            seen, cur = {}, b.name  # dict: ordered, O(1) membership
            while cur not in reaches:
                if cur in seen:
                    path = list(seen)
                    cyc = " -> ".join(path[path.index(cur):] + [cur])
                    self.err(f"joints '{parent_of[cur].name}'", f"the joints form a cycle ({cyc}); use a loop constraint")
                seen[cur] = None
                cur = parent_of[cur].parent
            reaches.update(seen)
        # Depth-first order, children in file order: Pinocchio needs each joint after its parent AND
        # every subtree's DOFs contiguous (CRBA's sparsity pattern relies on it).
        children = {}
        for j in spec.joints:
            children.setdefault(j.parent, []).append(j)
        ordered, stack = [], list(reversed(children.get(WORLD, [])))
        while stack:
            j = stack.pop()
            ordered.append(j)
            stack.extend(reversed(children.get(j.child, [])))
        spec.joints[:] = ordered

    def body_names(self, spec):
        if spec.urdf:
            try:
                model = pin.buildModelFromUrdf(spec.urdf)
            except (ValueError, RuntimeError):  # its message names the file only; urdfdom prints the details
                self.err("urdf", f"{Path(spec.urdf).name} is not a valid URDF model")
            return {f.name for f in model.frames if f.type == pin.FrameType.BODY} | {WORLD}
        return {b.name for b in spec.bodies} | {WORLD}

    def site(self, entry, d, bodies) -> SiteSpec:
        self.keys(entry, d, {"name", "body", "pos"}, required=("body",))
        if not isinstance(d["body"], str) or d["body"] not in bodies:
            self.err(entry, f"unknown body '{d['body']}'")
        return SiteSpec(d["name"], d["body"], self.vector(entry, "pos", d.get("pos", [0, 0, 0]), 3))

    def site_ref(self, entry, key, d, sites):
        if key not in d:
            self.err(entry, f"missing '{key}' (a site name)")
        if not isinstance(d[key], str) or d[key] not in sites:
            self.err(entry, f"unknown site '{d[key]}' in '{key}'")
        return d[key]

    def spring(self, entry, d, sites) -> SpringSpec:
        self.keys(entry, d, {"name", "a", "b", "stiffness", "damping", "rest_length", "implicit"})
        a, b = self.site_ref(entry, "a", d, sites), self.site_ref(entry, "b", d, sites)
        if a == b:
            self.err(entry, "a spring needs two different sites")
        rl = d.get("rest_length")
        implicit = d.get("implicit", True)
        if not isinstance(implicit, bool):
            self.err(entry, f"'implicit' must be true or false, got {implicit!r}")
        return SpringSpec(d["name"], a, b, self.number(entry, "stiffness", d.get("stiffness", 0.0), nonneg=True),
                          self.number(entry, "damping", d.get("damping", 0.0), nonneg=True),
                          None if rl is None else self.number(entry, "rest_length", rl, nonneg=True), implicit)

    def wrench(self, entry, d, bodies) -> WrenchSpec:
        self.keys(entry, d, {"name", "body", "force", "torque"}, required=("body",))
        if not isinstance(d["body"], str) or d["body"] not in bodies or d["body"] == WORLD:
            self.err(entry, f"unknown body '{d['body']}'")
        return WrenchSpec(d["name"], d["body"], self.vector(entry, "force", d.get("force", [0, 0, 0]), 3),
                          self.vector(entry, "torque", d.get("torque", [0, 0, 0]), 3))

    def loop(self, entry, d, sites) -> LoopSpec:
        self.keys(entry, d, {"name", "a", "b", "rows", "axis", "friction"})
        a, b = self.site_ref(entry, "a", d, sites), self.site_ref(entry, "b", d, sites)
        rows = d.get("rows", ["x", "y", "z"])
        if not isinstance(rows, list) or not rows or len(rows) > 3:
            self.err(entry, "'rows' must list 1-3 world directions (x, y, z or unit vectors)")
        axes = np.array([self.axis(entry, "rows", r) for r in rows])
        if np.linalg.matrix_rank(axes) < len(rows):
            self.err(entry, "'rows' must be linearly independent directions")
        return LoopSpec(d["name"], a, b, axes)

    def coupling(self, entry, d, spec) -> CouplingSpec:
        self.keys(entry, d, {"name", "joints", "ratios"}, required=("joints", "ratios"))
        joints = d["joints"]
        known = {j.name: j for j in spec.joints}
        if not isinstance(joints, list) or len(joints) < 2:
            self.err(entry, "'joints' must list at least two joints")
        for j in joints:
            if not isinstance(j, str):
                self.err(entry, f"'joints' must list joint names, got {j!r}")
            if not spec.urdf and j not in known:
                self.err(entry, f"unknown joint '{j}'")
            if not spec.urdf and known[j].nv != 1:
                self.err(entry, f"joint '{j}' must have one DOF to be coupled (it has {known[j].nv})")
        if len(set(joints)) != len(joints):
            self.err(entry, "a joint appears twice")
        ratios = self.vector(entry, "ratios", d["ratios"], len(joints))
        if np.any(ratios == 0):
            self.err(entry, "ratios must be non-zero")
        return CouplingSpec(d["name"], list(joints), ratios)

    def prescriptions(self, spec, raw, sites):
        joint_names = [j.name for j in spec.joints if j.type != "fixed"]
        p = raw.get("prescribable")
        if p is not None:
            self.keys("prescribable", p, {"joints", "sites"})
            for k in ("joints", "sites"):
                if k in p and (not isinstance(p[k], list) or not all(isinstance(x, str) for x in p[k])):
                    self.err(f"prescribable.{k}", f"must be a list of {k[:-1]} names, got {p[k]!r}")
            if "joints" in p:
                for j in p["joints"]:
                    if not spec.urdf and j not in joint_names:
                        self.err("prescribable.joints", f"unknown joint '{j}'")
                spec.prescribable_joints = list(p["joints"])
            if "sites" in p:
                for s in p["sites"]:
                    if s not in sites:
                        self.err("prescribable.sites", f"unknown site '{s}'")
                spec.prescribable_sites = list(p["sites"])
        pr = raw.get("prescribed") or {}
        self.keys("prescribed", pr, {"joints", "sites", "bodies"})
        for k in ("joints", "sites", "bodies"):
            if not isinstance(pr.get(k) or {}, dict):
                self.err(f"prescribed.{k}", f"must be a mapping {k[:-1]} name -> prescription, got {pr[k]!r}")
        nv_of = {j.name: j.nv for j in spec.joints}
        for name, val in (pr.get("joints") or {}).items():
            if not spec.urdf and name not in joint_names:
                self.err("prescribed.joints", f"unknown joint '{name}'")
            n = nv_of.get(name, 1)
            if isinstance(val, dict):  # {position: <time function(s)>, b: 5}: a trajectory q_p(t) (timefunctions.py)
                spec.prescribed_trajectories[name] = timefunctions.parse_trajectory(self, f"prescribed.joints.{name}",
                                                                                   val, n)
                continue
            spec.prescribed_joints[name] = self.vector(f"prescribed.joints.{name}", "velocity", val, n, allow_scalar=n == 1)
        for name, val in (pr.get("sites") or {}).items():
            entry = f"prescribed.sites.{name}"
            if name not in sites:
                self.err("prescribed.sites", f"unknown site '{name}'")
            if isinstance(val, dict):  # {velocity: [vx, vy, vz], axes: [x, z]}
                self.keys(entry, val, {"velocity", "axes"}, required=("velocity",))
                if "axes" in val:
                    ax = val["axes"]
                    if not isinstance(ax, list) or not 1 <= len(ax) <= 3:
                        self.err(entry, "'axes' must list 1-3 world directions")
                    P = np.array([self.axis(entry, "axes", a) for a in ax])
                    if np.linalg.matrix_rank(P) < len(P):
                        self.err(entry, "'axes' must be linearly independent")
                    spec.prescribed_site_axes[name] = P
                val = val["velocity"]
            spec.prescribed_sites[name] = self.vector(entry, "velocity", val, 3)
        body_names = [b.name for b in spec.bodies]
        for name, val in (pr.get("bodies") or {}).items():  # {angular: [3], linear: [3], frame: body|world}
            entry = f"prescribed.bodies.{name}"
            try:  # components: numbers, null, or time functions evaluated at t_k+1 (scene/body_twist.py)
                spec.prescribed_bodies[name] = body_twist.parse(
                    name, val, body_names, lambda key, x, entry=entry: timefunctions.parse(self, entry, key, x))
            except ValueError as e:
                self.err(entry, str(e))
