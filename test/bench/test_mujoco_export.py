"""MuJoCo export of compiled scenes (benchmarks only): each exported model has our mass matrix and
gravity torques at a sample configuration to 1e-9, and a few RK4 steps at tiny h agree with RK4 on
pin.aba. Skipped, with the reason printed, when the ``bench`` extra (mujoco) is not installed."""
import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import Simulator, Workspace
from redmax_ros.core.step import baselines

try:
    import mujoco  # noqa: F401
    HAVE_MUJOCO = True
except ImportError:  # pragma: no cover
    HAVE_MUJOCO = False
    print("test_mujoco_export: mujoco is not installed (pip install -e .[bench]); skipping")

pytestmark = pytest.mark.skipif(not HAVE_MUJOCO, reason="mujoco is not installed (pip install -e .[bench])")

SCENES = [("pendulum", []), ("chain", ["params.n=6", "params.springs=2", "params.joint_stiffness=0.3"]),
          ("branching", []), ("fourbar", []), ("mass_springs", ["params.attach=corners"]), ("hand", []),
          ("klann_leg", []), ("klann", [])]


def _optional(name, overrides=()):
    try:
        Simulator.load(name, list(overrides))
    except Exception:  # noqa: BLE001 - scene not shipped on this branch
        return []
    return [(name, list(overrides))]


SCENES += _optional("bridge") + _optional("umbrella")


@pytest.mark.parametrize("scene,overrides", SCENES, ids=[s for s, _ in SCENES])
def test_mass_matrix_and_gravity_match(scene, overrides):
    from redmax_bench.mujoco_export import export
    m = Simulator.load(scene, overrides).mech
    ex = export(m, 1e-3)
    rng = np.random.default_rng(1)
    q = pin.integrate(m.model, m.q0, 0.4 * rng.normal(size=m.nv))
    data = m.model.createData()
    M = pin.crba(m.model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    g = pin.computeGeneralizedGravity(m.model, data, q)
    Mj, gj = ex.mass_matrix_and_gravity(q)
    scale = max(1.0, float(np.abs(M).max()), float(np.abs(g).max()))  # large scenes: relative to their size
    assert np.abs(M - Mj).max() <= 1e-9 * scale
    assert np.abs(g - gj).max() <= 1e-9 * scale
    assert np.abs(pin.difference(m.model, q, ex.q(ex.qpos(q)))).max() < 1e-12


@pytest.mark.parametrize("scene,overrides", [("chain", ["params.n=3", "params.springs=1", "params.joint_damping=0.01"]),
                                             ("branching", []), ("mass_springs", ["params.d=1"])])
def test_few_steps_match_rk4(scene, overrides):
    """Springs (tendons), dampers, joints and the free-joint velocity map: 50 MuJoCo RK4 steps at
    h = 1e-5 against RK4 on pin.aba with the same forces."""
    from redmax_bench.mujoco_export import export
    m = Simulator.load(scene, overrides).mech
    h, n = 1e-5, 50
    ex = export(m, h, "rk4")
    d = ex.make_data()
    q0, v0 = m.q0.copy(), m.to_reduced(m.v0) + 0.3
    d.qpos[:] = ex.qpos(q0)
    d.qvel[:] = ex.qvel(q0, v0)
    mujoco.mj_step(ex.model, d, nstep=n)
    data = Workspace(m, pin_data=True)
    q, v = q0, v0
    for _ in range(n):
        q, v = baselines.rk4(m, data, q, v, h)
    assert np.abs(pin.difference(m.model, q, ex.q(d.qpos))).max() < 1e-9
    assert np.abs(v - ex.v(q, d.qvel)).max() < 1e-7


def test_core_does_not_import_mujoco():
    import pathlib
    core = pathlib.Path(__file__).resolve().parents[2] / "redmax_ros" / "core"
    for f in core.rglob("*.py"):
        assert "import mujoco" not in f.read_text(), f"{f.name} imports mujoco (benchmark-only dependency)"


PASSIVE = [("chain", ["params.n=4", "params.springs=2", "params.joint_stiffness=2.0", "params.joint_damping=0.05",
                      "joints.j1.rest=0.3", "joints.j2.rest=-0.2"]),
           ("mass_springs", ["params.d=2.0", "params.attach=corners"])] + _optional("bridge", ["params.n_deck=8"])


@pytest.mark.parametrize("scene,overrides", PASSIVE, ids=[s for s, _ in PASSIVE])
def test_passive_forces_match(scene, overrides):
    """Joint springs (with non-zero rest: MjSpec's default unit for springref is degrees), joint
    dampers and spring tendons: MuJoCo's qfrc_passive equals our applied forces at a random state."""
    from redmax_bench.mujoco_export import export
    m = Simulator.load(scene, overrides).mech
    ex = export(m, 1e-3)
    rng = np.random.default_rng(2)
    q = pin.integrate(m.model, m.q0, 0.05 * rng.normal(size=m.nv))
    v = 0.2 * rng.normal(size=m.nv)
    d = ex.make_data()
    d.qpos[:] = ex.qpos(q)
    d.qvel[:] = ex.qvel(q, v)
    mujoco.mj_forward(ex.model, d)
    f = baselines.applied_force(m, Workspace(m, pin_data=True), q, v)
    fj = ex.vel_map(q).T @ d.qfrc_passive
    assert np.abs(f - fj).max() <= 1e-9 * max(1.0, float(np.abs(f).max()))
