"""Model apart from workspace: the compiled Mechanism is frozen and never written by a step; everything a
step writes lives in the backend's Workspace, so two workspaces of one Mechanism step independently."""
import copy
import dataclasses

import numpy as np
import pytest

from redmax_ros.core import Mechanism, Simulator, compile_scene, load_scene
from redmax_ros.core.step.backends import DataFreeBackend, DirectBackend

SCENES = [("hand", [], "direct"), ("klann", ["friction.joint_mu=0.4"], "direct"),
          ("catalogue/spline_curve", [], "direct"), ("catalogue/spherical_euler_switch", [], "direct"),
          ("catalogue/gear_loop", [], "direct"), ("catalogue/free3d", [], "direct"),
          ("bridge", ["params.n_deck=12"], "pcg"), ("umbrella", ["params.ribs=2"], "direct")]


def _arrays(obj, seen=None, path="mech"):
    """Every ndarray reachable from the Mechanism's fields (and their dataclass/list/dict members), by path."""
    seen = set() if seen is None else seen
    out = {}
    if id(obj) in seen:
        return out
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        out[path] = obj
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            out.update(_arrays(getattr(obj, f.name), seen, f"{path}.{f.name}"))
    elif isinstance(obj, (list, tuple)):
        for i, x in enumerate(obj):
            out.update(_arrays(x, seen, f"{path}[{i}]"))
    elif isinstance(obj, dict):
        for k, x in obj.items():
            out.update(_arrays(x, seen, f"{path}[{k!r}]"))
    elif hasattr(obj, "__dict__") and type(obj).__module__.startswith("redmax_ros"):
        for k, x in vars(obj).items():
            out.update(_arrays(x, seen, f"{path}.{k}"))
    return out


@pytest.mark.parametrize("name,overrides,solver", SCENES)
def test_stepping_never_writes_the_mechanism(name, overrides, solver, load_sim):
    """Every array reachable from the Mechanism (incl. the compiled catalogue hooks and friction model) is
    bitwise the same after 100 steps with prescriptions, torques and site forces; fields cannot be set."""
    sim = load_sim(name, overrides, solver=solver)
    m = sim.mech
    before = {k: v.copy() for k, v in _arrays(m).items()}
    assert len(before) > 20
    movable = [j for j in m.prescribable_joints if m.joint_index[j].nv]
    if movable:
        sim.prescribe_joints({movable[0]: np.full(m.joint_index[movable[0]].nv, 0.1)})
    if m.site_names:
        sim.set_site_forces({m.site_names[-1]: [0.0, 0.0, 0.5]})
    sim.step(100)
    after = _arrays(m)
    changed = [k for k, v in before.items() if not np.array_equal(v, after[k], equal_nan=True)]
    assert changed == []
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.q0 = m.q0.copy()
    assert isinstance(m, Mechanism) and not any(f.name.endswith("cache") for f in dataclasses.fields(m))


@pytest.mark.parametrize("name,overrides,backend", [("hand", [], DirectBackend), ("catalogue/spline_curve", [], DirectBackend),
                                                    ("klann", ["friction.joint_mu=0.4"], DirectBackend),
                                                    ("bridge", ["params.n_deck=12"], DataFreeBackend)])
def test_two_workspaces_of_one_mechanism_step_independently(name, overrides, backend):
    """Two backends on one Mechanism, stepped interleaved from different states, give bitwise the
    trajectories each gives alone (no state shared through the model)."""
    mech = compile_scene(load_scene(name, overrides))
    make = (lambda: backend(mech)) if backend is DirectBackend else (lambda: backend(mech, "pcg"))
    sim = Simulator.load(name, overrides)
    cmd = sim.commands
    s0 = sim.state
    s1 = dataclasses.replace(s0, v=s0.v + 0.05)

    def alone(state):
        b = make()
        b.at_state(state.q, state.t)
        out = []
        for _ in range(40):
            state, r = b.step(state, cmd, sim.dt)
            out.append(np.concatenate([state.q, state.v]))
        return np.array(out)

    ref0, ref1 = alone(s0), alone(s1)
    a, b = make(), make()
    a.at_state(s0.q, s0.t)
    b.at_state(s1.q, s1.t)
    xa, xb = s0, s1
    for k in range(40):
        xa, _ = a.step(xa, cmd, sim.dt)
        xb, _ = b.step(xb, cmd, sim.dt)
        assert np.array_equal(np.concatenate([xa.q, xa.v]), ref0[k])
        assert np.array_equal(np.concatenate([xb.q, xb.v]), ref1[k])


def test_auto_backend_switch_updates_sim_data():
    """solver: auto on a 60-link chain (48 < nv <= 100): PCG probes first (no pin.Data), then the Pinocchio
    pipeline (the compiled step, with the reference's pin.Data) takes over and Simulator.data is its pin.Data."""
    sim = Simulator.load("chain", ["params.n=60"], solver="auto")
    assert sim.backend.choice is None and sim.data is None
    sim.step(6)
    assert sim.backend.choice == "direct", sim.backend.reason
    assert sim.data is not None and sim.data is sim.backend.impl.workspace.data
    r = sim.step()
    assert r.diagnostics.solver in ("compiled", "direct", "qp")


def test_reset_and_set_state_reach_the_workspace():
    """Simulator.reset/set_state make the workspace's configuration-dependent J_rR that of the state, so a
    fresh load, a reset and a set_state to the initial state give bitwise the same 100 steps."""
    def run(sim):
        return np.array([np.concatenate([sim.step().q, sim.state.v]) for _ in range(100)])
    ref = run(Simulator.load("catalogue/spherical_exp"))
    sim = Simulator.load("catalogue/spherical_exp")
    s0 = copy.deepcopy(sim.state)
    sim.step(37)
    sim.reset()
    assert np.array_equal(run(sim), ref)
    sim.step(11)
    sim.set_state(s0)
    assert np.array_equal(run(sim), ref)
