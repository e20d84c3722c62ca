"""Malformed scenes raise SceneError naming the file, the entry and the problem (never a bare
KeyError or a traceback from deep inside)."""
from pathlib import Path

import pytest

from redmax_ros.core import SceneError, Simulator, load_scene

BAD = sorted((Path(__file__).parent / "data" / "bad_scenes").glob("*.yaml"))


def expectation(path):
    first = path.read_text().splitlines()[0]
    assert first.startswith("# expect: "), f"{path.name} must start with '# expect: ...'"
    return [p.strip() for p in first[len("# expect: "):].split("|")]


def test_corpus_covers_the_listed_cases():
    names = {p.stem for p in BAD}
    for case in ("unknown_joint_type", "missing_parent", "cycle", "negative_mass", "inertia_not_pd", "zero_axis",
                 "unknown_site_in_spring", "duplicate_names", "wrong_vector_length", "overconstrained_loop"):
        assert case in names


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_scene_raises_scene_error_naming_file_entry_problem(path):
    with pytest.raises(SceneError) as ei:
        Simulator.load(str(path))
    msg = str(ei.value)
    assert path.name in msg
    for part in expectation(path):
        assert part in msg, (part, msg)


def test_unknown_scene_name_lists_known_scenes():
    with pytest.raises(SceneError, match="known scenes: .*pendulum"):
        load_scene("no_such_scene")


@pytest.mark.parametrize("override, text", [
    ("params.nope=3", "unknown parameter"),
    ("joints.ghost.q0=1", "no entry named 'ghost'"),
    ("dt=-1", "'dt' must be positive"),
    ("dt", "expected key=value"),
    ("params.n=0", "'n' must be an integer >= 1"),
])
def test_bad_overrides_are_scene_errors(override, text):
    with pytest.raises(SceneError, match=text):
        Simulator.load("chain", [override])


def test_numeric_strings_are_numbers_in_builder_params():
    """YAML 1.1 reads 1e3 as a string; builders get numbers."""
    from redmax_ros.core import Simulator as S
    sim = S.load("chain", ["params.joint_stiffness=1e3", "params.n=2"])
    assert sim.mech.stiffness.tolist() == [1000.0, 1000.0]
