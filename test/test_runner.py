"""redmax_run writes the CSV the issue specifies, with rows equal to stepping the Simulator directly."""
import numpy as np

from redmax_ros import runner
from redmax_ros.core import Simulator


def read(path):
    header = path.read_text().splitlines()[0].split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def test_hand_csv_columns_and_values(tmp_path, capsys):
    out = tmp_path / "hand.csv"
    rc = runner.main(["hand", "--duration", "0.05", "--out", str(out), "--set", "params.pip=0.5",
                      "--quiet"])
    assert rc == 0
    header, rows = read(out)
    sim = Simulator.load("hand", ["params.pip=0.5"])
    d = sim.describe()
    expect = (["t"] + [f"q:{n}" for n in d.position_names] + [f"v:{n}" for n in d.velocity_names]
              + ["E_kin", "E_pot", "E_spring", "E_total", "violation", "tau:elbow"])
    assert header == expect
    assert "q:wrist[1]" in header and "v:index_mcp[0]" in header
    assert rows.shape == (51, len(header))
    for k in range(1, 51):
        r = sim.step()
        assert np.array_equal(rows[k, 1:1 + d.nq], r.q)  # bitwise: same code path, %.17g
        assert rows[k, header.index("tau:elbow")] == r.effort[sim.mech.joint_index["elbow"].idx_v]
    text = capsys.readouterr().out
    assert "steps/s" in text and "energy" in text and "violation" in text


def test_site_force_columns_and_errors(tmp_path, capsys):
    scene = tmp_path / "p.yaml"
    scene.write_text("""
units: SI
bodies:
  - {name: l1, shape: {type: box, size: [0.05, 0.05, 0.5]}, density: 1000}
  - {name: l2, shape: {type: box, size: [0.05, 0.05, 0.5]}, density: 1000}
joints:
  - {name: j1, type: revolute, axis: y, parent: world, child: l1, body_placement: {pos: [0, 0, -0.25]}, q0: 0.3}
  - {name: j2, type: revolute, axis: y, parent: l1, child: l2, placement: {pos: [0, 0, -0.25]},
     body_placement: {pos: [0, 0, -0.25]}, q0: 0.5}
sites: [{name: tip, body: l2, pos: [0, 0, -0.25]}]
prescribed: {sites: {tip: {velocity: [0.1, 0.0, 0.05], axes: [x, z]}}}   # planar: 2 rows
""")
    out = tmp_path / "p.csv"
    assert runner.main([str(scene), "--duration", "0.01", "--out", str(out), "--quiet"]) == 0
    header, rows = read(out)
    assert header[-3:] == ["f:tip[0]", "f:tip[1]", "f:tip[2]"]
    assert np.all(np.isfinite(rows[1:, -3:])) and np.all(rows[1:, -2] == 0.0)  # no force along y
    # the tip moves with the commanded in-plane velocity
    sim = Simulator.load(str(scene))
    r = sim.step()
    J = sim.mech  # tip velocity from the new state: finite difference of positions over one step
    import pinocchio as pin
    d = J.model.createData()
    fid = J.site_fid[J.site_index["tip"]]
    pin.forwardKinematics(J.model, d, J.q0)
    x0 = pin.updateFramePlacement(J.model, d, fid).translation.copy()
    pin.forwardKinematics(J.model, d, r.q)
    x1 = pin.updateFramePlacement(J.model, d, fid).translation.copy()
    assert np.allclose((x1 - x0) / sim.dt, [0.1, 0.0, 0.05], atol=1e-3)
    assert runner.main(["no_such_scene"]) == 2
    assert "no such scene" in capsys.readouterr().err


def test_body_wrench_columns(tmp_path):
    """catalogue/body_twist: w:<body>[0..5] columns = StepResult.body_wrenches, bitwise."""
    out = tmp_path / "b.csv"
    assert runner.main(["catalogue/body_twist", "--duration", "0.01", "--out", str(out), "--quiet"]) == 0
    header, rows = read(out)
    assert header[-6:] == [f"w:lower[{i}]" for i in range(6)]
    sim = Simulator.load("catalogue/body_twist")
    for k in range(1, 11):
        assert np.array_equal(rows[k, -6:], sim.step().body_wrenches["lower"])


def test_controller_commands_each_step(tmp_path):
    """--controller file.py:fn: fn(t, state) is called before every step and its torque applied, as setting
    the same torque on the Simulator by hand; bad commands are reported (exit 2)."""
    ctl = tmp_path / "ctl.py"
    ctl.write_text("def pd(t, state):\n    return {'joint_torques': {'hinge': -5.0 * state.q[0] - 0.5 * state.v[0]}}\n"
                   "def bad(t, state):\n    return {'joint_torque': {}}\n")
    out = tmp_path / "p.csv"
    assert runner.main(["pendulum", "--duration", "0.02", "--out", str(out), "--quiet", "--controller", f"{ctl}:pd"]) == 0
    header, rows = read(out)
    sim = Simulator.load("pendulum")
    for k in range(1, 21):
        sim.set_joint_torques({"hinge": -5.0 * sim.state.q[0] - 0.5 * sim.state.v[0]})
        assert rows[k, header.index("q:hinge")] == sim.step().q[0]
    assert runner.main(["pendulum", "--duration", "0.01", "--out", str(out), "--quiet", "--controller", f"{ctl}:bad"]) == 2
    assert runner.main(["pendulum", "--quiet", "--controller", f"{ctl}:nope"]) == 2


def test_every_kth_row_is_the_single_step(tmp_path, capsys):
    """--every 7 over 50 steps (hand, elbow prescribed; and the chain under BDF2, whose unrecorded steps skip
    their energies): rows after steps 7, 14, ..., 49 and the last, 50, bitwise the single steps' numbers; the
    summary counts the 50 steps."""
    for scene, sets, cols in (("hand", ["params.pip=0.5"], ["tau:elbow"]), ("chain", ["integrator.scheme=bdf2"], [])):
        out = tmp_path / f"{scene}.csv"
        args = [scene, "--duration", "0.05", "--dt", "0.001", "--every", "7", "--out", str(out), "--quiet"]
        for s in sets:
            args += ["--set", s]
        assert runner.main(args) == 0
        header, rows = read(out)
        steps = [7 * i for i in range(1, 8)] + [50]
        assert rows.shape[0] == 1 + len(steps)
        sim = Simulator.load(scene, sets + ["dt=0.001"])
        singles = [sim.step() for _ in range(50)]
        for row, k in zip(rows[1:], steps):
            res = singles[k - 1]
            assert row[0] == res.t and np.array_equal(row[1:1 + len(res.q)], res.q)
            assert row[header.index("E_total")] == res.diagnostics.E_total
            for c in cols:
                assert row[header.index(c)] == res.effort[sim.mech.joint_index["elbow"].idx_v]
        assert f"{scene}: 50 steps" in capsys.readouterr().out
    assert runner.main(["hand", "--every", "0", "--quiet", "--out", str(tmp_path / "x.csv")]) == 2
