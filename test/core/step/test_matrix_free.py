"""Matrix-free step (PCG + Projected Block Jacobi Preconditioner, Eq. (2)-(4), Alg. 1) and the
data-free direct solver (step.backends.DataFreeBackend), against the Pinocchio pipeline
(step.backends.DirectBackend) on the shipped scenes.

PCG solves are compared at rtol = 1e-10 (a relative residual of 1e-6, the default, gives a
solution error of up to cond(P^-1 A) x 1e-6); the default rtol is checked for its residual.
"""
import numpy as np
import pytest

import pinocchio as pin

from redmax_ros.core import SceneError, Simulator, State, StepError, compile_scene, list_scenes, load_scene
from redmax_ros.core.dynamics.springs import spring_forces
from redmax_ros.core.dynamics.stabilization import assemble_loops
from redmax_ros.core.dynamics.tree_kinematics import PIN_DATA_MAX_NV, Context, point_jac_kernel
from redmax_ros.core.solvers import recursive as rc
from redmax_ros.core.step.backends import AUTO_DIRECT_NV, DataFreeBackend, DirectBackend

SMALL = [s for s in list_scenes() if sum(j.nv for j in load_scene(s).joints) <= PIN_DATA_MAX_NV
         and not load_scene(s).prescribed_bodies]  # body-twist prescriptions: Pinocchio pipeline only
EXTRA = [("bridge", ["params.variant=flexy"]), ("chain", ["params.n=8", "params.springs=4"]),
         ("bridge", ["params.n_deck=12"]),
         ("chain", ["params.n=6", "params.springs=2", "bodies.link2.damping=3.0", "bodies.link4.damping=1.0",
                    "wrenches=[{name: w, body: link3, force: [1.0, 0.5, -2.0], torque: [0.1, 0.2, 0.3]}]"]),
         ("chain", ["params.n=5", "params.springs=1", "bodies.link1.damping={c: 0.05, form: twist}",  # issue 13 item 2
                    "bodies.link2.damping={c: 2.0, form: mass}", "bodies.link4.damping={c: 0.01, form: twist}"]),
         ("chain", ["params.n=6", "params.springs=3", "params.spring_d=0.5", "params.spring_rest=0.15",  # issue 13 item 6
                    "springs.brace0.implicit=false", "springs.brace2.implicit=false", "joints.j1.q0=0.4"])]


def _rel(a, b):
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


def _compare(name, overrides, warm=15, prepare=None, want=None):
    """One step from the same state: data-free direct and PCG (rtol 1e-10) vs stepper.step.
    ``want``: keep stepping (up to 300 steps) until the direct solve of the compared step is ``want``."""
    sim = Simulator.load(name, overrides, solver="direct")
    if any(getattr(sim.mech, k, None) is not None for k in ("friction", "extras", "collision")):
        with pytest.raises(SceneError, match="pcg"):
            Simulator.load(name, overrides, solver="pcg")
        return None
    if sim.mech.coriolis_implicit:  # direct pipeline only (docs/scenes.md, "Integrator"): compare the default step
        with pytest.raises(SceneError, match="integrator.coriolis"):
            Simulator.load(name, overrides, solver="pcg")
        overrides = list(overrides) + ["integrator={coriolis: explicit}"]
        sim = Simulator.load(name, overrides, solver="direct")
    if prepare:
        prepare(sim)
    sim.step(warm)
    m, cmd, h = sim.mech, sim.commands, sim.dt
    direct = DirectBackend(m)
    for _ in range(300):
        st = sim.state
        _, ref = direct.step(st, cmd, h)
        if want is None or ref.diagnostics.solver == want:
            break
        sim.step()
    _, dense = DataFreeBackend(m, "direct").step(st, cmd, h)
    pcg = DataFreeBackend(m, "pcg", rtol=1e-10)
    _, it = pcg.step(st, cmd, h)
    sim.pcg_stats = pcg.workspace.tree.last_stats
    scale_v = max(np.abs(ref.v).max(), 1e-3)
    for res, tol_v in ((dense, 1e-9), (it, 1e-6)):
        d = res.diagnostics
        assert np.abs(res.v - ref.v).max() <= tol_v * scale_v, (name, d.solver)
        assert np.abs(res.q - ref.q).max() <= 1.01 * h * tol_v * scale_v + 1e-12  # q+ = q + h v+
        assert np.abs(res.effort - ref.effort).max() <= 1e-6 * max(np.abs(ref.effort).max(), 1.0)
        for s, f in ref.site_forces.items():
            assert np.abs(res.site_forces[s] - f).max() <= 1e-6 * max(np.abs(f).max(), 1.0)
        rd = ref.diagnostics
        for k in ("E_kin", "E_pot", "E_spring"):
            assert abs(getattr(d, k) - getattr(rd, k)) <= 1e-8 * max(abs(rd.E_total), abs(getattr(rd, k)), 1.0), k
        assert abs(d.violation_pos - rd.violation_pos) <= 1e-9
    assert it.diagnostics.solver == "pcg" and it.diagnostics.residual < 1e-9
    return sim, ref, it


@pytest.mark.parametrize("name", SMALL)
def test_shipped_scene_pcg_and_dataless_direct_equal_direct(name):
    _compare(name, [])


@pytest.mark.parametrize("name,overrides", EXTRA)
def test_more_scenes_equal_direct(name, overrides):
    _compare(name, overrides)


def test_hybrid_prescriptions_couplings_limits_equal_direct():
    """Hand: couplings (Eq. 8-10 as bilateral rows on the PCG path), prescribed elbow (reduced, Eq. 7),
    a prescribed fingertip along two axes (maximal), torques driving joints into their limits (Eq. 5:
    ProxSuite QP on the direct path, active set on the PCG path), a site force."""
    def prepare(sim):
        sim.prescribe_sites({"index_tip": [0.0, 0.0, 0.02]}, axes={"index_tip": ["x", "z"]})
        sim.set_joint_torques({"wrist": [3.0, 0.0], "index_mcp": [0.5, 0.0]})
        sim.set_site_forces({"thumb_tip": [0.0, 0.3, 0.0]})
    out = _compare("hand", [], warm=30, prepare=prepare, want="qp")
    _, ref, it = out
    assert ref.diagnostics.solver == "qp"  # a joint limit is active
    assert out[0].pcg_stats.get("active_limits", 0) >= 1


def test_default_rtol_residual_and_warm_start():
    sim = Simulator.load("umbrella", [], solver="pcg")
    r0 = sim.step()
    r = sim.step(5)
    d = r.diagnostics
    assert d.solver == "pcg" and d.residual < 1e-5
    assert d.iterations < r0.diagnostics.iterations  # warm starts (velocity, previous Z) pay off
    stats = sim.backend.workspace.tree.last_stats
    assert len(stats["solves"]) == 1 + 24  # Eq. (4): one RHS solve + one per loop row (8 loops x 3)


def test_bridge_rigid_pcg_converges_in_at_most_two_iterations():
    """Rigid towers: every cable joins a deck body to the world, the maximal stiffness is block
    diagonal over bodies and Alg. 1 is the exact inverse of the LHS (the paper's single iteration)."""
    for overrides in ([], ["params.scale=2"]):
        sim = Simulator.load("bridge", overrides, solver="pcg")
        ctx = sim.backend.workspace.tree
        for _ in range(15):
            r = sim.step()
            assert r.diagnostics.solver == "pcg"
            assert max(ctx.last_stats["solves"]) <= 2, ctx.last_stats
        # also from a cold start (no warm start at all)
        m, st = sim.mech, sim.state
        ctx.z_cache = None
        _, r = sim.backend.step(State(st.t, st.q, np.zeros_like(st.v)), sim.commands, sim.dt)
        assert max(ctx.last_stats["solves"]) <= 2


def test_pcg_fallback_to_direct_is_reported_and_correct():
    sim = Simulator.load("bridge", ["params.variant=flexy"], solver="direct")
    sim.step(10)
    m, st, cmd, h = sim.mech, sim.state, sim.commands, sim.dt
    _, ref = sim.backend.step(st, cmd, h)
    pcg = DataFreeBackend(m, "pcg", rtol=1e-12, max_iter=1)
    ctx = pcg.workspace.tree
    _, r = pcg.step(st, cmd, h)
    assert r.diagnostics.solver == "pcg->direct"
    assert "did not reach" in ctx.last_stats["fallback"]
    assert _rel(r.v, ref.v) < 1e-9


def test_step_error_leaves_state_unchanged():
    sim = Simulator.load("bridge", ["params.n_deck=10"], solver="pcg")
    sim.step(2)
    q, v, t = sim.state.q.copy(), sim.state.v.copy(), sim.time
    bad = sim.commands.joint_torques.copy()
    bad[3] = np.nan
    sim.commands.joint_torques = bad
    with pytest.raises(StepError, match="non-finite joint torques"):
        sim.step()
    assert np.array_equal(sim.state.q, q) and np.array_equal(sim.state.v, v) and sim.time == t
    with pytest.raises(StepError, match="time step"):
        sim.backend.step(sim.state, sim.commands, -1.0)


def test_universal_joint_kernel_matches_recursive_fallback():
    sim = Simulator.load("umbrella", ["params.ribs=2"], solver="pcg")
    sim.step(3)
    m = sim.mech
    ctx = sim.workspace.tree
    rng = np.random.default_rng(3)
    v = rng.normal(size=m.nv)
    ctx.invalidate()
    ws = ctx.fk(sim.state.q, v)
    ref = rc.update_kinematics(ctx.topo, rc.make_workspace(ctx.topo), sim.state.q, v)
    for f in ("R", "p", "St", "I", "ov"):
        assert np.abs(getattr(ws, f) - getattr(ref, f)).max() < 1e-13, f
    assert np.abs(rc.bias_acceleration(ctx.topo, ws) - rc.bias_acceleration(ctx.topo, ref)).max() < 1e-12


def _assemble_loops_pinocchio(m, q, tol=1e-12, max_iter=100):
    """Reference loop assembly on Pinocchio's pin.Data: least-norm Newton on phi = S (x_a - x_b) with the
    frame Jacobians (the Pinocchio implementation the data-free one replaced)."""
    data = m.model.createData()
    S, ab = m.loop_select, m.loop_ab
    fid = lambda s: int(m.site_fid[s])  # noqa: E731
    for _ in range(max_iter):
        pin.computeJointJacobians(m.model, data, q)
        pin.updateFramePlacements(m.model, data)
        X, J = [], []
        for a, b in ab:
            xa, xb = (data.oMf[fid(s)].translation if fid(s) >= 0 else m.site_local[s] for s in (a, b))
            Ja, Jb = (pin.getFrameJacobian(m.model, data, fid(s), pin.LOCAL_WORLD_ALIGNED)[:3] if fid(s) >= 0
                      else np.zeros((3, m.nv)) for s in (a, b))
            X.append(xa - xb)
            J.append(Ja - Jb)
        phi, G = S @ np.concatenate(X), S @ np.vstack(J)
        if np.abs(phi).max() < tol:
            break
        q = pin.integrate(m.model, q, m.to_reduced(np.linalg.lstsq(G if m.T is None else G @ m.T, -phi, rcond=None)[0]))
    return q


def test_data_free_loop_assembly_matches_pinocchio():
    for name in ("fourbar", "klann_leg", "umbrella"):
        m = compile_scene(load_scene(name, ["params.ribs=2"] if name == "umbrella" else []))
        rng = np.random.default_rng(0)
        q = m.q0.copy()
        q[:m.nv] += 1e-3 * rng.normal(size=m.nv) if m.nq == m.nv else 0.0
        a, b = assemble_loops(Context(m), q.copy()), _assemble_loops_pinocchio(m, q.copy())
        assert np.abs(a - b).max() < 1e-9, name


@pytest.mark.parametrize("name, overrides", [("fourbar", []), ("umbrella", ["params.ribs=2"]),
                                             ("bridge", ["params.variant=rigid"])])
def test_loop_jacobian_kernel_matches_site_jacobians(name, overrides):
    """Context.loop_jacobian (tree_kinematics.loop_jacobian_kernel, one call) against the rows it replaced,
    P (J_a - J_b) per loop from the loop sites' point Jacobians, to round-off; and G qdot is the loops' phi_dot
    (finite difference of Context.loop_rows' phi along qdot)."""
    m = compile_scene(load_scene(name, overrides))
    ctx = Context(m)
    rng = np.random.default_rng(1)
    q = m.q0.copy()
    if m.nq == m.nv:
        q += 1e-2 * rng.normal(size=m.nv)
    ctx.fk(q)
    G = ctx.loop_jacobian()
    t = ctx.topo
    X = rc.site_positions(ctx.ws, ctx.loop_site_jid, ctx.loop_site_local)
    J = np.zeros((len(X), 3, m.nv))
    point_jac_kernel(t.parents, t.idx_v, t.nv_j, ctx.ws.St, ctx.loop_site_jid, X, J)
    G_ref = np.concatenate([P @ (J[ka] - J[kb]) for (ka, kb), P in zip(ctx.loop_ends, ctx.loop_axes)])
    assert G.shape == G_ref.shape and np.abs(G - G_ref).max() <= 1e-14 * max(1.0, np.abs(G_ref).max())
    if m.nq == m.nv:
        v, eps = rng.normal(size=m.nv), 1e-6
        phi = [ctx.fk(q + s * eps * v) is not None and ctx.loop_rows()[1] for s in (1.0, -1.0)]
        assert np.abs((phi[0] - phi[1]) / (2 * eps) - G @ v).max() <= 1e-6 * max(1.0, np.abs(G @ v).max())


def test_rhs_kernel_matches_its_parts_and_pinocchio():
    """tree_forces.rhs (one rhs_kernel call) against the calls it replaced (bias_wrench_kernel, einsum I ov,
    spring_wrench_kernel, rhs_sum_kernel) to round-off on a chain with springs, body damping and a wrench, the
    rigid bridge and the hand (joint springs); and without springs b = M v + h (tau - nle(q, v)) from Pinocchio
    (crba, rnea at zero acceleration)."""
    from redmax_ros.core.dynamics import tree_forces as tf
    for scene, overrides in (EXTRA[3], ("chain", ["params.n=5"]), ("bridge", ["params.variant=rigid"]), ("hand", [])):
        m = compile_scene(load_scene(scene, overrides))
        ctx = Context(m)
        rng = np.random.default_rng(2)
        q = pin.integrate(m.model, m.q0, 0.3 * rng.normal(size=m.nv))
        v, tau, h = rng.normal(size=m.nv), rng.normal(size=m.nv), 1e-3
        ws = ctx.fk(q, v)
        springs = None
        if len(m.spring_ab):
            X, fs = ctx.spring_state(h)[:2]
            springs = (fs, X)
        b = tf.rhs(ctx, q, v, tau, h, None, springs)
        t = ctx.topo
        W = np.empty((t.njoints, 6))
        tf.bias_wrench_kernel(t.parents, t.idx_v, t.nv_j, ws.St, ws.ov, ws.v, ws.R, ws.p, ws.c_local, ws.I,
                              ctx.gravity, h, np.empty((t.njoints, 6)), W)
        W += np.einsum("jab,jb->ja", ws.I, ws.ov)
        ext = np.zeros((t.njoints, 6))
        if springs is not None:
            sa = ctx.spring_arrays
            rc.spring_wrench_kernel(ctx.spring_ja, sa.a, ctx.spring_jb, sa.b, X, fs, ext)
        for j, com, fw in zip(ctx.wrench_jid, ctx.wrench_com, ctx.wrench_fw):
            x = ws.R[j] @ com + ws.p[j]
            ext[j] += np.concatenate([fw[:3], np.cross(x, fw[:3]) + fw[3:]])
        f_r = tau - m.stiffness * pin.difference(m.model, m.q_rest, q) if m.has_stiffness else tau
        b_ref = np.empty(m.nv)
        tf.rhs_sum_kernel(t.parents, t.idx_v, t.nv_j, ws.St, W, ext, h, ctx.armature, v, f_r, np.empty_like(ws.tmp6),
                          b_ref)
        assert np.abs(b - b_ref).max() <= 1e-13 * np.abs(b_ref).max()
        if springs is None and not len(ctx.wrench_jid):
            data = m.model.createData()
            M = pin.crba(m.model, data, q)
            M = np.triu(M) + np.triu(M, 1).T + np.diag(m.armature if m.has_armature else np.zeros(m.nv))
            nle = pin.rnea(m.model, data, q, v, np.zeros(m.nv))
            b_pin = M @ v + h * (f_r - nle)
            assert np.abs(b - b_pin).max() <= 1e-12 * np.abs(b_pin).max()


@pytest.mark.parametrize("name, overrides", [("chain", ["params.n=6", "params.springs=3", "params.spring_rest=0.15",
                                                        "joints.j1.q0=0.4"]),
                                             ("bridge", ["params.variant=flexy"]), ("hand", [])])
def test_tree_spring_energy_equals_pin_data_spring_energy(name, overrides):
    """energy.tree_energies' E_spring (springs.point_spring_energy_kernel from the placements + joint springs)
    against energy.energies on pin.Data (springs.spring_energy on pin's site positions), to round-off."""
    from redmax_ros.core.dynamics.energy import energies, tree_energies
    from redmax_ros.core.step.workspace import Workspace
    m = compile_scene(load_scene(name, overrides))
    rng = np.random.default_rng(4)
    q = pin.integrate(m.model, m.q0, 0.1 * rng.normal(size=m.nv))
    v = rng.normal(size=m.nv)
    e_tree = tree_energies(Context(m), q, v)
    e_pin = energies(m, Workspace(m, pin_data=True), q, v)
    assert e_tree[2] == pytest.approx(e_pin[2], rel=1e-12, abs=1e-15)
    assert len(m.spring_ab) or m.has_stiffness  # the scene has springs to compare


def test_large_scene_compiles_and_runs_without_pin_data():
    """nv > PIN_DATA_MAX_NV: compile_scene (loop assembly, spring rest lengths) and the Simulator
    (poses, spring segments, stepping) never create a pin.Data."""
    sim = Simulator.load("bridge", ["params.n_deck=130"], solver="direct")
    assert sim.mech.nv == 130 > PIN_DATA_MAX_NV and sim.data is None
    r = sim.step(2)
    assert r.diagnostics.solver == "direct" and r.diagnostics.violation_pos < 1e-9
    poses = sim.body_poses()
    assert len(poses) == len(sim.mech.bodies)
    segs = sim.spring_segments()
    assert len(segs) == len(sim.mech.spring_names)
    sim2 = Simulator.load("bridge", ["params.n_deck=130"], solver="pcg")
    sim2.backend.rtol = 1e-10
    r2 = sim2.step(2)
    assert r2.diagnostics.solver == "pcg" and _rel(r2.v, r.v) < 1e-6


def test_auto_rule():
    small = Simulator.load("chain", [], solver="auto")
    assert small.mech.nv <= AUTO_DIRECT_NV and small.backend.choice == "direct" and small.data is not None
    sim = Simulator.load("bridge", ["params.scale=2"])  # scene key solver: auto
    assert sim.backend.choice is None and sim.data is None
    sim.step(6)
    assert sim.backend.choice == "pcg", sim.backend.reason
    assert sim.step().diagnostics.solver == "pcg"


def test_scaling_scene_dofs():
    def nv(name, ov):
        return sum(j.nv for j in load_scene(name, ov).joints)
    assert [nv("bridge", [f"params.scale={s}"]) for s in (1, 2, 16)] == [80, 160, 1280]
    assert [nv("bridge", ["params.variant=flexy", f"params.scale={s}"]) for s in (1, 16)] == [60, 960]
    assert [nv("umbrella", [f"params.ribs={r}"]) for r in (10, 16, 22, 32, 46)] == [241, 385, 529, 769, 1105]
    with pytest.raises(SceneError, match="variant"):
        load_scene("bridge", ["params.variant=wobbly"])


def test_runner_solver_option(tmp_path):
    from redmax_ros.runner import main
    out = tmp_path / "b.csv"
    assert main(["bridge", "--solver", "pcg", "--set", "params.n_deck=110", "--duration", "0.03", "--quiet",
                 "--out", str(out)]) == 0
    rows = np.loadtxt(out, delimiter=",", skiprows=1)
    assert rows.shape[0] == 4 and np.all(np.isfinite(rows))


@pytest.mark.parametrize("name,overrides", [("bridge", []), EXTRA[5]])
def test_spring_state_equals_spring_forces_and_the_lhs_matrices(name, overrides):
    """Context.spring_state (one compiled call) against what it replaces: jac_positions, springs.spring_forces,
    the end points X[a], X[b] and C = h D + h^2 K as MatrixFreeSystem.refresh forms it, bytes equal (the second
    scene has explicit dampers, which need the site velocities)."""
    sim = Simulator.load(name, overrides, solver="pcg")
    sim.step(3)
    ctx, m, h = sim.backend.workspace.tree, sim.mech, sim.dt
    rws = ctx.fk(sim.state.q, sim.state.v)
    X = ctx.jac_positions()
    V = None
    if ctx.spring_arrays.needs_velocities:
        ov = rws.ov[ctx.jac_jid]
        V = ov[:, :3] + np.cross(ov[:, 3:], X)
    f, K, D, _ = spring_forces(m, X, V, ctx.spring_arrays)
    sa = ctx.spring_arrays
    want = (X, f, K, D, X[sa.a], X[sa.b], np.ascontiguousarray(h * D + h * h * K))
    X2, f2, K2, D2, (pa, pb), C = ctx.spring_state(h, V)
    for a, b in zip(want, (X2, f2, K2, D2, pa, pb, C)):
        assert a.shape == b.shape and a.tobytes() == b.tobytes()
