"""The ``deformables:`` scene section (issue 15 point 3), mesh files through meshio, the shipped string and
starfish scenes, describe() and the runner's columns (point 4)."""
import copy

import numpy as np
import pytest

from redmax_ros.core import SceneError, Simulator
from redmax_ros.core.deformable import meshes
from redmax_ros.core.deformable.mesh_io import read_tets, write_tets
from redmax_ros.core.scene.loader import scene_from_dict
from redmax_ros.runner import csv_header, csv_row

BASE = {"name": "t", "gravity": [0, 0, -9.81], "dt": 1e-3,
        "bodies": [{"name": "link", "shape": {"type": "box", "size": [0.1, 0.1, 0.1]}, "density": 500}],
        "joints": [{"name": "j", "type": "revolute", "parent": "world", "child": "link", "axis": "y"}],
        "deformables": [{"name": "rope", "type": "string", "n": 5, "start": [0, 0, 0], "end": [1, 0, 0], "mass": 0.1,
                         "stiffness": 100, "attachments": [{"body": "world", "vertices": [0]},
                                                           {"body": "link", "vertices": [-1]}]}]}


def _with(**changes):
    raw = copy.deepcopy(BASE)
    raw["deformables"][0].update(changes)
    return raw


@pytest.mark.parametrize("change, where, what", [
    ({"type": "cloth"}, "deformables.rope.type", "unknown deformable type"),
    ({"n": 1}, "deformables.rope.n", "integer from 2"),
    ({"stiffness": -1}, "deformables.rope", "positive"),
    ({"young": 1e5}, "deformables.rope", "type fem"),
    ({"attachments": [{"body": "nobody", "vertices": [0]}]}, "attachments[0]", "unknown body 'nobody'"),
    ({"attachments": [{"body": "link", "vertices": [7]}]}, "attachments[0]", "vertex indices"),
    ({"attachments": [{"body": "link"}]}, "attachments[0]", "either 'vertices' or 'inside"),
    ({"rayleigh": {"gamma": 1}}, "deformables.rope.rayleigh", "unknown key"),
])
def test_bad_entries_are_named(change, where, what):
    with pytest.raises(SceneError) as e:
        scene_from_dict(_with(**change), "<t>")
    assert where in str(e.value) and what in str(e.value)


def test_fem_entries_checked():
    raw = copy.deepcopy(BASE)
    raw["deformables"] = [{"name": "pad", "type": "fem", "mesh": {"box": {"size": [0.1, 0.1, 0.1], "cells": [1, 1, 1]}},
                           "young": 1e5, "poisson": 0.5, "density": 100}]
    with pytest.raises(SceneError, match=r"deformables.pad.poisson.*\(-1, 0.5\)"):
        scene_from_dict(raw, "<t>")
    raw["deformables"][0]["poisson"] = 0.3
    raw["deformables"][0]["attachments"] = [{"body": "link", "inside": True}]
    raw["deformables"][0]["pos"] = [5, 0, 0]  # far from the link: nothing inside
    with pytest.raises(SceneError, match="no vertex lies inside body 'link'"):
        Simulator(scene_from_dict(raw, "<t>"))
    raw["deformables"][0]["attachments"] = [{"body": "link", "vertices": [0]}, {"body": "world", "vertices": [0]}]
    with pytest.raises(SceneError, match="vertex 0 is attached twice"):
        Simulator(scene_from_dict(raw, "<t>"))


@pytest.mark.parametrize("suffix", [".msh", ".vtk", ".vtu"])
def test_mesh_file_via_meshio(tmp_path, suffix):
    x, t = meshes.box_tets([0, 0, 0], [0.1, 0.1, 0.1], (1, 1, 2))
    path = tmp_path / f"pad{suffix}"
    write_tets(path, x, t)
    x2, t2 = read_tets(path)
    assert np.allclose(x2, x) and np.array_equal(t2, t)
    raw = copy.deepcopy(BASE)
    raw["deformables"] = [{"name": "pad", "type": "fem", "mesh": {"file": path.name}, "young": 1e5, "poisson": 0.3,
                           "density": 100, "pos": [0, 0, -0.2]}]
    spec = scene_from_dict(raw, str(tmp_path / "s.yaml"), base_dir=tmp_path)
    assert spec.deformables[0].vertices.shape == (len(x), 3)
    (tmp_path / "bad.vtu").write_text("not a mesh")
    raw["deformables"][0]["mesh"] = {"file": "bad.vtu"}
    with pytest.raises(SceneError, match="deformables.pad.mesh"):
        scene_from_dict(raw, str(tmp_path / "s.yaml"), base_dir=tmp_path)


def test_describe_and_runner_columns():
    sim = Simulator(scene_from_dict(BASE, "<t>"))
    d = sim.describe()
    assert d.deformables == [("rope", "string", 5, 4)]
    header = csv_header(sim)
    assert header[-3:] == ["E_def_kin", "E_def_elastic", "attach_violation"]
    res = sim.step(10)
    row = csv_row(sim, res)
    assert len(row) == len(header) and np.all(np.isfinite(row))
    assert sim.deformable_positions()["rope"].shape == (5, 3)
    assert sim.deformable_surfaces()["rope"].shape == (4, 2)


def test_starfish_scene():
    sim = Simulator.load("starfish")
    d = sim.describe()
    assert len(d.joint_names) == 21  # the free core + 20 arm joints
    name, kind, nvert, ntet = d.deformables[0]
    assert kind == "fem" and 200 <= nvert <= 250
    dm = sim.deformables
    free = np.setdiff1d(dm.floor_vertices, dm.attach.vertex)
    q_arm = []
    for _ in range(3):
        r = sim.step(100)
        q_arm.append(sim.state.q[7])
        x = sim.deformable_positions()["body"]
        assert x[free, 2].min() >= -1e-9  # free vertices never below the floor
        assert r.diagnostics.violation_pos <= 1e-8
    assert max(np.abs(q_arm)) > 0.1  # the gait moves the arms
    assert len(sim.deformable_surfaces()["body"]) > 0


def test_coupled_solve_reports_its_kkt_residual():
    """The coupled KKT solve's stationarity residual |A z + G^T lam + C^T mu - b| / |b| is round-off
    (Diagnostics.residual, what /diagnostics and solver_stats report)."""
    sim = Simulator.load("catalogue/string")
    for _ in range(20):
        res = sim.step(1)
        assert res.diagnostics.residual < 1e-10
