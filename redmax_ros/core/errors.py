"""Errors raised by the core. Each names the problem; none leaves state half-changed."""


class SceneError(ValueError):
    """A scene file (or builder parameters) is malformed.

    The message names the file, the entry (e.g. ``joints[3] 'pip'``) and what is wrong.
    """

    def __init__(self, source: str, entry: str, problem: str):
        self.source, self.entry, self.problem = source, entry, problem
        where = f"{source}: {entry}" if entry else source
        super().__init__(f"{where}: {problem}")


class SceneNotFound(SceneError):
    """No scene of that name or path may be loaded: there is no such file, or (``load_scene`` with
    ``allowed_dirs``) it lies outside the allowed scene directories. The node answers NOT_FOUND."""


class StepError(RuntimeError):
    """A step failed (non-finite numbers, singular/infeasible system, QP failure, divergence).

    The simulator state is exactly as it was before the failing step. ``steps_done`` counts the
    steps of a multi-step request that completed before the failure.
    """

    def __init__(self, reason: str, steps_done: int = 0):
        self.reason, self.steps_done = reason, steps_done
        super().__init__(reason)


class CommandError(ValueError):
    """A command (prescription, torque) names an unknown joint/site, has the wrong length or a
    non-finite value. Nothing is changed when it is raised."""
