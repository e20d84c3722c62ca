"""Prescribed DOFs held in the reduced system (deformable/reduction.py: unit_rows, hold, reactions) give the
KKT solution of A z + G^T lam = b, G z = g exactly: the same z and multipliers as the dense KKT solve."""
import numpy as np
import pytest
import scipy.sparse as sp

from redmax_ros.core.deformable import reduction
from redmax_ros.core.solvers import coupled


def _spd_csr(n, rng):
    M = sp.random(n, n, density=0.15, random_state=rng) + sp.eye(n)
    A = (M @ M.T + n * sp.eye(n)).tocsr()
    A.sort_indices()
    return A


def test_unit_rows_are_found_and_others_left_to_the_schur_complement():
    G = np.zeros((4, 6))
    G[0, 2] = 2.0  # unit row
    G[1, 4] = 1.0  # unit row, but a limit row touches DOF 4
    G[2, [0, 1]] = [1.0, -1.0]  # a loop row
    G[3, 5] = -1.0  # unit row
    C = np.zeros((1, 6))
    C[0, 4] = 1.0
    rows, cols, coef = reduction.unit_rows(G, C)
    assert rows.tolist() == [0, 3] and cols.tolist() == [2, 5] and coef.tolist() == [2.0, -1.0]


def test_held_dofs_reproduce_the_kkt_solution_and_its_multipliers():
    rng = np.random.default_rng(3)
    n = 40
    A = _spd_csr(n, rng)
    b = rng.standard_normal(n)
    dofs = np.array([3, 17, 31])
    coef = np.array([1.0, -2.0, 0.5])
    g = rng.standard_normal(3)
    G = np.zeros((3, n))
    G[np.arange(3), dofs] = coef
    K = np.block([[A.toarray(), G.T], [G, np.zeros((3, 3))]])
    ref = np.linalg.solve(K, np.concatenate([b, g]))
    ws = coupled.Workspace(A.indptr.astype(np.int64), A.indices.astype(np.int64), n)
    data, rhs = A.data.copy(), b.copy()
    saved, b_saved = reduction.hold(ws.indptr, ws.indices, ws.diag, ws.tpos, data, rhs, dofs, g / coef)
    held = sp.csr_matrix((data, A.indices, A.indptr), shape=(n, n)).toarray()
    assert np.allclose(held[dofs][:, dofs], np.eye(3)) and np.count_nonzero(held[dofs]) == 3
    z = np.linalg.solve(held, rhs)
    lam = -reduction.reactions(ws.indptr, ws.indices, dofs, saved, b_saved, z) / coef
    assert np.abs(z - ref[:n]).max() <= 1e-12 * np.abs(ref[:n]).max()
    assert np.abs(lam - ref[n:]).max() <= 1e-11 * max(1.0, np.abs(ref[n:]).max())


def test_the_next_steps_system_filled_at_the_end_of_a_step_is_used_only_for_its_own_state():
    """deformable_stages fills A_d, b_d for the next step when a step ends (its elastic energy at x+ is a
    by-product) and keeps it only for a step from that very DeformState with the same h: a run that goes on,
    a run restarted from an equal copy of the state, and a step with another h after it all equal fresh fills."""
    import dataclasses

    from redmax_ros.core import Simulator
    from redmax_ros.core.deformable.system import DeformState

    # frictionless floor: with floor_mu > 0 the contact solve is warm-started from the last step's contact
    # states (kept in the workspace, not in State), so a restarted run equals a continuing one only to the
    # staggered loop's tolerance, not bit for bit
    frictionless = ["params.mu=0"]
    sim = Simulator.load("starfish", overrides=frictionless)
    sim.step(20)
    s20 = sim.state
    sim.step(10)
    ref = sim.state
    copy = dataclasses.replace(s20, deform=DeformState.of(s20.deform.x, s20.deform.v))
    other = Simulator.load("starfish", overrides=frictionless)
    other.set_state(copy)  # a new DeformState: its system is filled afresh
    other.step(10)
    for a, b in ((ref.q, other.state.q), (ref.deform.x, other.state.deform.x), (ref.deform.v, other.state.deform.v)):
        assert np.array_equal(a, b)
    e_cont = sim.step(1).diagnostics.E_spring
    e_copy = other.step(1).diagnostics.E_spring
    assert e_cont == e_copy
    fresh = Simulator.load("starfish", overrides=frictionless)
    fresh.set_state(dataclasses.replace(sim.state, deform=DeformState.of(sim.state.deform.x, sim.state.deform.v)))
    sim.dt = fresh.dt = 5e-4  # the system kept for h = 1e-3 must not serve a step of 5e-4
    sim.step(3)
    fresh.step(3)
    assert np.array_equal(sim.state.q, fresh.state.q) and np.array_equal(sim.state.deform.x, fresh.state.deform.x)


def test_a_run_set_back_to_a_state_replays_a_fresh_run_from_it_bitwise_with_floor_friction():
    """The floor contacts' warm start follows the state it was found for: a simulator that ran on and is set
    back to an earlier state steps exactly as a freshly loaded one set to that state (no warm start from the
    other history)."""
    from redmax_ros.core import Simulator

    sim = Simulator.load("starfish")  # floor_mu 0.8
    sim.step(30)
    s30 = sim.state
    sim.step(15)
    sim.set_state(s30)
    sim.step(10)
    fresh = Simulator.load("starfish")
    fresh.set_state(s30)
    fresh.step(10)
    assert np.array_equal(sim.state.q, fresh.state.q)
    assert np.array_equal(sim.state.deform.x, fresh.state.deform.x)
    assert np.array_equal(sim.state.deform.v, fresh.state.deform.v)


def test_a_step_that_fails_after_its_solve_leaves_the_warm_start_as_it_was(monkeypatch):
    """A step that raises after the coupled solve (here: a StepError injected into the required forces) changes
    neither the state nor what the next step starts from: the retry and the steps after it equal a run that
    never failed, bit for bit, with floor friction (whose solve depends on its warm start)."""
    from redmax_ros.core import Simulator, StepError
    from redmax_ros.core.step import deformable_stages

    ref = Simulator.load("starfish")
    ref.step(35)
    sim = Simulator.load("starfish")
    sim.step(30)
    before = sim.state
    real = deformable_stages.required_forces

    def failing(*a, **k):
        raise StepError("injected")

    monkeypatch.setattr(deformable_stages, "required_forces", failing)
    with pytest.raises(StepError, match="injected"):
        sim.step()
    assert sim.state is before
    monkeypatch.setattr(deformable_stages, "required_forces", real)
    sim.step(5)
    assert np.array_equal(sim.state.q, ref.state.q)
    assert np.array_equal(sim.state.deform.x, ref.state.deform.x)
