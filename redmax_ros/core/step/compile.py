"""SceneSpec -> the frozen Mechanism: the structure (model.mechanism.build_mechanism), then the compile
steps that need the dynamics.

1. the Pinocchio model of the tree, sites, springs, loops, couplings J_rR (Eq. 9), reduced forces;
2. catalogue features (dynamics/catalogue_hooks.attach): validated, linear joint constraints satisfied
   at q0 (and J_rR of joint maps at q0);
3. couplings consistent at q0; qdot_R(0) from the scene's reduced velocities;
4. loops closed at q0 (stabilization.assemble_loops, Newton to 1e-12 m) and their rows checked for
   redundancy; default spring rest lengths = the spring lengths at that q0;
5. the friction model (friction/contact.compile_friction: contact primitives, BISP joint friction);
6. the collision model (model/collision.build_collision: Pinocchio GeometryModel, candidate pairs).

Each step returns a new frozen Mechanism (dataclasses.replace); nothing is changed afterwards.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from redmax_ros.core.dynamics.catalogue_hooks import attach
from redmax_ros.core.dynamics.stabilization import assemble_loops
from redmax_ros.core.dynamics.tree_kinematics import Context, spring_lengths
from redmax_ros.core.friction.contact import compile_friction
from redmax_ros.core.model.collision import build_collision
from redmax_ros.core.model.mechanism import Mechanism, build_mechanism, check_couplings_q0, hyper_reduced_v0
from redmax_ros.core.scene.spec import SceneSpec


def compile_scene(spec: SceneSpec) -> Mechanism:
    """The Mechanism of a validated scene (SceneError on what cannot be compiled)."""
    mech = build_mechanism(spec)  # 1
    extras = attach(mech, mech.maps)  # 2
    if extras is not None:
        mech = dataclasses.replace(mech, extras=extras, q0=extras.q0)
    check_couplings_q0(mech)  # 3
    mech = dataclasses.replace(mech, v0=hyper_reduced_v0(mech, mech.v0))
    ctx = Context(mech)  # 4: no pin.Data (its memory grows as nv^3 for large models)
    q0 = assemble_loops(ctx, mech.q0)
    lengths = spring_lengths(ctx, q0)
    rest = np.array([lengths[i] if s.rest_length is None else s.rest_length for i, s in enumerate(spec.springs)])
    mech = dataclasses.replace(mech, q0=q0, spring_rest=rest.reshape(len(spec.springs)))
    if spec.friction is not None:  # 5
        mech = dataclasses.replace(mech, friction=compile_friction(mech, spec.friction))
    if spec.collision is not None:  # 6: self-collision GeometryModel and candidate pairs (docs/collisions.md)
        mech = dataclasses.replace(mech, collision=build_collision(mech, spec.collision))
    return mech
