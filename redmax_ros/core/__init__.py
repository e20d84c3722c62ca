"""RedMax core: scenes, the linearly implicit step of Eq. (2), constraints and solvers. No ROS here."""
from .errors import CommandError, SceneError, StepError
from .scene import list_scenes, load_scene
from .simulator import SceneDescription, Simulator
from .stepper import Commands, Diagnostics, State, StepResult

__all__ = ["CommandError", "SceneError", "StepError", "list_scenes", "load_scene", "SceneDescription",
           "Simulator", "Commands", "Diagnostics", "State", "StepResult"]
