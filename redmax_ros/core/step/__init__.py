"""The step and what runs it: State/Commands/Diagnostics/StepResult and the input checks (state.py), the one
step skeleton with the Pinocchio velocity stages (pipeline.py) and the data-free ones (data_free_stages.py),
the step Workspace (workspace.py), the backends and the solver selection (backends.py), compile_scene
(compile.py), and the explicit ABA baselines (baselines.py)."""
