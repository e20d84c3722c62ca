"""RedMax core: scenes, the linearly implicit step of Eq. (2), constraints and solvers. No ROS here."""
from redmax_ros.core.errors import CommandError, SceneError, StepError
from redmax_ros.core.scene.loader import list_scenes, load_scene
from redmax_ros.core.simulator import SceneDescription, Simulator
from redmax_ros.core.step.pipeline import Commands, Diagnostics, State, StepResult

__all__ = ["CommandError", "SceneError", "StepError", "list_scenes", "load_scene", "SceneDescription",
           "Simulator", "Commands", "Diagnostics", "State", "StepResult"]
