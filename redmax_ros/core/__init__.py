"""RedMax core: scenes, the linearly implicit step of Eq. (2), constraints and solvers. No ROS here.

The public API (everything the node, the runner and the benchmarks use) is imported here; the
sub-packages follow the layers of a step: scene/ (YAML -> SceneSpec) -> model/ (Mechanism) ->
solvers/, dynamics/, friction/ (the stages) -> step/ (the step, backends, workspace) -> Simulator.
"""
from redmax_ros.core.errors import CommandError, SceneError, SceneNotFound, StepError
from redmax_ros.core.model.dof_positions import DofPositions
from redmax_ros.core.model.mechanism import JointInfo, Mechanism
from redmax_ros.core.scene.loader import list_scenes, load_scene, scene_from_dict
from redmax_ros.core.scene.spec import SOLVERS, SceneSpec
from redmax_ros.core.simulator import SceneDescription, Simulator
from redmax_ros.core.solvers.budget import StepBudget
from redmax_ros.core.step.compile import compile_scene
from redmax_ros.core.step.compiled.poses import BodyFrames, body_frames
from redmax_ros.core.step.state import BatchResult, Commands, Diagnostics, Rollout, State, StepResult
from redmax_ros.core.step.workspace import Workspace

__all__ = ["SOLVERS", "BatchResult", "CommandError", "SceneError", "SceneNotFound", "StepError", "DofPositions", "JointInfo", "Mechanism",
           "list_scenes", "load_scene", "scene_from_dict", "SceneSpec", "SceneDescription", "Simulator", "StepBudget",
           "compile_scene", "BodyFrames", "body_frames", "Commands", "Diagnostics", "Rollout", "State", "StepResult", "Workspace"]
