"""The compiled step (issue 12): the whole RedMax step of Eq. (2) in one numba call, on a static Model and a
preallocated Data (MJX's split), with the Pinocchio pipeline as the reference beside it.

    model.py       Mechanism -> packed constants (MODEL_SPEC), which Mechanisms it takes (unsupported)
    data.py        the workspace per set of prescriptions (DATA_SPEC)
    packing.py     flat buffers <-> namedtuples of views (why: the cost of typing many numba arguments)
    manifold.py    pin.integrate / pin.difference per joint kind
    scheme.py      stage 0: BDF1, or where a BDF2 step is linearised and from where it advances (step/scheme.py)
    kinematics.py  stage 1;  forces.py  stage 2 (Eq. 2, Eq. 9-10);  rows.py  stage 3 (Eq. 7, limits)
    limits.py      stage 4': the joint limits of Eq. (5) by an active set
    update.py      stages 5-6 (manifold update, loop post-stabilization, required forces);  energy.py
    kernel.py      step_n_kernel / friction_step_n_kernel (a single step: n = 1): the stages in order, hand-offs
    cache.py       drops cached kernels whose inlined or linked sources changed
    backend.py     CompiledBackend (solver: compiled; default of solver: direct), step_run, step_batch
"""
