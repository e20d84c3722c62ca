"""The validated scene: dataclasses of a scene file's entries (pure data, SI units; docs/scenes.md)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# solver: direct (the compiled one-call step where the scene allows it, else the reference), reference (the
# Pinocchio pipeline), compiled (the compiled step or an error naming why not), pcg, auto; docs/solvers.md
SOLVERS = ("direct", "reference", "compiled", "pcg", "auto")
SCHEMES = ("euler", "bdf2")  # integrator.scheme (docs/scenes.md, "Integrator"; step/scheme.py)
SPRING_STIFFNESS = ("full", "gauss_newton")  # integrator.spring_stiffness (dynamics/springs.geometric_blocks_kernel)

WORLD = "world"
CORE_JOINT_TYPES = {  # catalogue joints (catalogue_schema.TYPES) carry their nv in JointSpec.extra
    # type: (nv, length of q0 in the scene file)
    "revolute": (1, 1),
    "prismatic": (1, 1),
    "universal": (2, 2),
    "spherical": (3, 3),  # q0 as roll, pitch, yaw [rad]
    "planar": (3, 3),  # q0 as x, y [m], theta [rad] in the joint frame's xy plane
    "fixed": (0, 0),
    "free": (6, 6),  # q0 as x, y, z [m], roll, pitch, yaw [rad]
}


@dataclass
class BodySpec:
    name: str
    mass: float  # kg
    com: np.ndarray  # (3,) m, body frame
    inertia: np.ndarray  # (3,3) kg m^2 about the COM, body frame
    shape: dict | None = None  # for markers
    damping: float = 0.0  # body damping coefficient c: D_m = c diag(m I3, I_com) [c in 1/s] or c I6 (damping_form)
    rgba: tuple = (0.7, 0.7, 0.75, 1.0)
    damping_form: str = "mass"  # "mass": c diag(m I3, I_com); "twist": c I6 on the body twist at the COM


@dataclass
class JointSpec:
    name: str
    type: str
    parent: str
    child: str
    placement: tuple  # (pos, rpy) of the joint frame in the parent body frame
    body_placement: tuple  # (pos, rpy) of the child body frame in the joint frame
    axes: np.ndarray  # (k,3) unit axes (revolute/prismatic: 1, universal: 2); empty otherwise
    q0: np.ndarray  # scene-file convention (see JOINT_TYPES)
    v0: np.ndarray  # (nv,)
    lower: np.ndarray  # (nv,) or -inf
    upper: np.ndarray  # (nv,) or +inf
    stiffness: np.ndarray  # (nv,) K_r [N m/rad or N/m]
    rest: np.ndarray  # like q0
    damping: np.ndarray  # (nv,) D_r [N m s/rad or N s/m]
    armature: np.ndarray  # (nv,) [kg m^2 or kg]
    torque: np.ndarray  # (nv,) constant explicit joint torque/force
    extra: dict = field(default_factory=dict)  # type-specific data (catalogue_schema): nv, chart, parts, geometry

    @property
    def nv(self) -> int:
        return self.extra["nv"] if "nv" in self.extra else CORE_JOINT_TYPES[self.type][0]


@dataclass
class SiteSpec:
    name: str
    body: str  # body name or 'world'
    pos: np.ndarray  # (3,) m, in the body frame (world frame for 'world')


@dataclass
class SpringSpec:
    name: str
    a: str
    b: str
    stiffness: float  # N/m
    damping: float  # N s/m
    rest_length: float | None  # m; None = distance at the initial configuration
    implicit: bool = True  # False: explicit force only, no K/D in the LHS of Eq. (2) (springs.spring_forces)


@dataclass
class WrenchSpec:
    name: str
    body: str
    force: np.ndarray  # (3,) N, world frame, at the body COM
    torque: np.ndarray  # (3,) N m, world frame


@dataclass
class LoopSpec:
    name: str
    a: str
    b: str
    axes: np.ndarray  # (k,3) world directions along which site a and b coincide


@dataclass
class CouplingSpec:
    name: str
    joints: list
    ratios: np.ndarray  # qdot_joint = ratio * qdot_coupling (Eq. 8)


@dataclass
class SceneSpec:
    name: str
    source: str
    gravity: np.ndarray
    dt: float
    duration: float
    bodies: list = field(default_factory=list)
    joints: list = field(default_factory=list)
    sites: list = field(default_factory=list)
    springs: list = field(default_factory=list)
    wrenches: list = field(default_factory=list)
    loops: list = field(default_factory=list)
    couplings: list = field(default_factory=list)
    prescribable_joints: list | None = None  # None = every moving joint
    prescribable_sites: list | None = None  # None = every site
    prescribed_joints: dict = field(default_factory=dict)  # name -> velocity (nv,)
    prescribed_trajectories: dict = field(default_factory=dict)  # name -> timefunctions.JointTrajectory
    prescribed_sites: dict = field(default_factory=dict)  # name -> velocity (3,) world frame
    prescribed_site_axes: dict = field(default_factory=dict)  # name -> (k,3) directions, when not x, y, z
    prescribed_bodies: dict = field(default_factory=dict)  # name -> step.body_twist.BodyTwist
    urdf: str | None = None  # path of a URDF giving the tree (bodies/joints then come from it)
    urdf_fixed_base: bool = True
    solver: str = "direct"  # one of SOLVERS
    scheme: str = "euler"  # integrator.scheme: euler (BDF1, Eq. 2 as in the paper) | bdf2 (step/scheme.py)
    coriolis: str = "explicit"  # integrator.coriolis: explicit (Eq. 2 as in the paper) | implicit (linearised)
    spring_stiffness: str = "full"  # integrator.spring_stiffness: full (K_m with the lever-arm terms) | gauss_newton
    stabilization: str = "post"  # loops: post (projection after the step) | baumgarte (velocity-level feedback)
    baumgarte_b: float = 5.0  # [1/s] stabilization.b: G qdot+ = -b phi(q_k) for the loop rows (method baumgarte)
    description: str = ""
    raw: dict = field(default_factory=dict, repr=False)
    friction: object = None  # contact_schema.FrictionSpec: ground, contacts, joint/loop friction (or None)
    catalogue: object = None  # catalogue_schema.CatalogueSpec: linear joint constraints, force elements (or None)
    collision: object = None  # collision_schema.CollisionSpec: self-collision shapes, margin, obstacles (or None)
    deformables: list = field(default_factory=list)  # deformable_schema.DeformableSpec: strings, FEM meshes (docs/deformables.md)


def numeric_deep(x):
    """_numeric on a value, or on every item of a list."""
    return [numeric_deep(v) for v in x] if isinstance(x, list) else numeric(x)


def numeric(x):
    """YAML 1.1 reads '1e6' (no dot) as a string: accept numeric strings as numbers."""
    if isinstance(x, str):
        try:
            return float(x)
        except ValueError:
            return x
    return x
