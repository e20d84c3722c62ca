"""Who may make the loader read what (issue 17; docs/node.md "Security", docs/scenes.md "Limits").

With ``allowed_dirs`` (what the node's load_scene service uses) a scene comes from scenes/ or those
directories only: names resolve inside them, ``..`` above them, absolute paths elsewhere and symlinks
leaving them are refused (SceneNotFound, the same answer whether or not the file exists), and the
meshes and URDF a scene names must lie in the scene file's own directory. Always: size caps, YAML alias
bombs and deep nesting refused, and no error message quotes the file.
"""
import os
import shutil
import time
from pathlib import Path

import pytest

from redmax_ros.core import SceneError, SceneNotFound, Simulator, load_scene
from redmax_ros.core.scene import files
from redmax_ros.core.scene.loader import SCENES_DIR, list_scenes

DATA = Path(__file__).parent / "data"
MARKER = "MARKER_7f3a9c_SECRET"  # content that must never show up in a message
OUTSIDE = "outside the allowed scene directories"
PENDULUM = (SCENES_DIR / "pendulum.yaml").read_text()


@pytest.fixture()
def dirs(tmp_path):
    """allowed/ (an extra scene directory with a pendulum, a mesh scene and a URDF scene) and
    outside/ (a valid scene, a mesh, a URDF and a secret, none of which may be reached)."""
    allowed, outside = tmp_path / "allowed", tmp_path / "outside"
    (allowed / "meshes").mkdir(parents=True)
    outside.mkdir()
    (allowed / "extra_pendulum.yaml").write_text(PENDULUM.replace("name: pendulum", "name: extra_pendulum"))
    shutil.copy(SCENES_DIR / "catalogue" / "meshes" / "cube.obj", allowed / "meshes" / "cube.obj")
    shutil.copy(SCENES_DIR / "catalogue" / "mesh_cube.yaml", allowed / "mesh_cube.yaml")
    shutil.copy(DATA / "arm.urdf", allowed / "arm.urdf")
    shutil.copy(DATA / "urdf_arm.yaml", allowed / "urdf_arm.yaml")
    (outside / "secret.yaml").write_text(f"name: {MARKER}\n{MARKER}: [\n")
    (outside / "valid.yaml").write_text(PENDULUM)
    shutil.copy(SCENES_DIR / "catalogue" / "meshes" / "cube.obj", outside / "cube.obj")
    shutil.copy(DATA / "arm.urdf", outside / "arm.urdf")
    return allowed, outside


def refused(name, allowed_dirs):
    with pytest.raises(SceneNotFound) as ei:
        load_scene(name, allowed_dirs=allowed_dirs)
    return str(ei.value)


# ----------------------------------------------------------------------------------------------
# where a scene may come from


def test_traversal_and_paths_outside_are_refused(dirs):
    allowed, outside = dirs
    A = [str(allowed)]
    for name in ["../../etc/passwd", "../" * 12 + "etc/passwd", "catalogue/../../../etc/hosts", "../outside/valid",
                 "/etc/passwd", "/etc/hostname", str(outside / "valid.yaml"), str(outside / "valid"),
                 str(outside / "secret.yaml"), str(allowed / ".." / "outside" / "valid.yaml"),
                 str(allowed) + "/../outside/valid"]:
        msg = refused(name, A)
        assert OUTSIDE in msg and str(allowed) in msg, (name, msg)
        assert MARKER not in msg
    # the same answer whether or not the file exists (no oracle for files outside)
    exists = refused(str(outside / "valid.yaml"), A)
    missing = refused(str(outside / "no_such_file.yaml"), A)
    assert exists.replace("valid.yaml", "X") == missing.replace("no_such_file.yaml", "X")
    # even a '..' that would come back inside is refused for a name: '..' may not climb above the directory
    assert OUTSIDE in refused("../allowed/extra_pendulum", A)
    # the package's scenes are always allowed, the extra list may be empty
    assert OUTSIDE in refused("../redmax_ros/__init__", [])
    assert OUTSIDE in refused(str(outside / "valid.yaml"), [])


def test_symlinks_leaving_the_allowed_directories_are_refused(dirs):
    allowed, outside = dirs
    A = [str(allowed)]
    (allowed / "link.yaml").symlink_to(outside / "valid.yaml")
    (allowed / "secret_link.yaml").symlink_to(outside / "secret.yaml")
    (allowed / "sub").symlink_to(outside, target_is_directory=True)
    (allowed / "dangling.yaml").symlink_to(outside / "missing.yaml")
    for name in ["link", "link.yaml", str(allowed / "link.yaml"), "secret_link", "sub/valid", "sub/secret.yaml",
                 str(allowed / "sub" / "valid.yaml"), "dangling"]:
        msg = refused(name, A)
        assert OUTSIDE in msg and MARKER not in msg, (name, msg)
    # a symlink that stays inside is followed
    (allowed / "alias_of_pendulum.yaml").symlink_to(allowed / "extra_pendulum.yaml")
    assert load_scene("alias_of_pendulum", allowed_dirs=A).name == "extra_pendulum"
    # without allowed_dirs (offline use) the same symlink loads as before
    assert load_scene(str(allowed / "link.yaml")).name == "pendulum"


def test_scenes_in_an_allowed_extra_directory_load(dirs):
    allowed, _ = dirs
    A = [str(allowed)]
    assert load_scene("extra_pendulum", allowed_dirs=A).name == "extra_pendulum"
    assert load_scene("extra_pendulum.yaml", allowed_dirs=A).name == "extra_pendulum"
    assert load_scene(str(allowed / "extra_pendulum.yaml"), allowed_dirs=A).name == "extra_pendulum"
    assert load_scene("hand", allowed_dirs=A).name == "hand"  # scenes/ is always allowed
    assert load_scene("catalogue/gear", allowed_dirs=[]).name == "gear"
    assert load_scene(str(SCENES_DIR / "pendulum.yaml"), allowed_dirs=[]).name == "pendulum"
    sim = Simulator.load("extra_pendulum", ["dt=0.002"], allowed_dirs=A)
    assert sim.dt == 0.002
    # the meshes and the URDF in the scene's own directory
    assert load_scene("mesh_cube", allowed_dirs=A).bodies[0].name == "brick"
    assert load_scene("urdf_arm", allowed_dirs=A).urdf == str(allowed / "arm.urdf")
    # an unknown name: NOT_FOUND listing what may be loaded, the extra directory's scenes too
    msg = refused("no_such_scene", A)
    assert "no such scene" in msg and "extra_pendulum" in msg and "pendulum" in msg
    assert "extra_pendulum" in list_scenes([allowed])
    # only .yaml / .yml files, even inside
    (allowed / "notes.txt").write_text(f"{MARKER}\n")
    msg = refused("notes.txt", A)
    assert "not a scene file" in msg and MARKER not in msg


def test_a_bad_allowed_directory_is_named(dirs):
    allowed, outside = dirs
    with pytest.raises(SceneError, match="does not exist or is not a directory") as ei:
        load_scene("pendulum", allowed_dirs=[str(outside / "nope")])
    assert str(outside / "nope") in str(ei.value)
    with pytest.raises(SceneError, match="does not exist or is not a directory"):
        load_scene("pendulum", allowed_dirs=[str(outside / "valid.yaml")])


def test_unusable_names_are_refused_without_a_traceback(dirs):
    allowed, _ = dirs
    for name in ["a\0b", "x" * 5000, "/" + "y" * 5000]:
        with pytest.raises(SceneNotFound):
            load_scene(name, allowed_dirs=[str(allowed)])


def test_offline_use_keeps_any_path(dirs):
    _, outside = dirs
    assert load_scene(str(outside / "valid.yaml")).name == "pendulum"
    assert Simulator.load(str(outside / "valid.yaml")).scene_name == "pendulum"


# ----------------------------------------------------------------------------------------------
# the files a scene names


def _mesh_scene(d: Path, name: str, mesh_file: str) -> str:
    text = (SCENES_DIR / "catalogue" / "mesh_cube.yaml").read_text().replace("file: meshes/cube.obj",
                                                                              f"file: {mesh_file}")
    (d / f"{name}.yaml").write_text(text)
    return name


def test_mesh_and_urdf_outside_the_scene_directory_are_refused(dirs):
    allowed, outside = dirs
    A = [str(allowed)]
    (allowed / "meshes" / "escape.obj").symlink_to(outside / "cube.obj")
    cases = {
        _mesh_scene(allowed, "up", "../outside/cube.obj"): "must lie inside the scene file's directory",
        _mesh_scene(allowed, "deep_up", "meshes/../../outside/cube.obj"): "must lie inside the scene file's directory",
        _mesh_scene(allowed, "absolute", str(outside / "cube.obj")): "an absolute path is not allowed",
        _mesh_scene(allowed, "absolute_inside", str(allowed / "meshes" / "cube.obj")): "an absolute path is not allowed",
        _mesh_scene(allowed, "symlinked", "meshes/escape.obj"): "must lie inside the scene file's directory",
    }
    for name, problem in cases.items():
        with pytest.raises(SceneError) as ei:
            load_scene(name, allowed_dirs=A)
        msg = str(ei.value)
        assert problem in msg and "bodies[0] 'brick'" in msg and f"{name}.yaml" in msg, (name, msg)
    # offline, the same scenes load as before (absolute paths, '..')
    for name in cases:
        assert load_scene(str(allowed / f"{name}.yaml")).bodies[0].name == "brick"
    # a composite body's mesh part too
    (allowed / "part.yaml").write_text(
        "name: part\nbodies:\n  - name: b\n    parts:\n"
        "      - {shape: {type: mesh, file: ../outside/cube.obj, scale: 0.1}, density: 1000}\n"
        "joints:\n  - {name: j, type: revolute, parent: world, child: b}\n")
    with pytest.raises(SceneError, match="parts\\[0\\].*must lie inside the scene file's directory"):
        load_scene("part", allowed_dirs=A)
    # URDF
    for name, ref in [("urdf_up", "../outside/arm.urdf"), ("urdf_abs", str(outside / "arm.urdf"))]:
        (allowed / f"{name}.yaml").write_text(f"name: {name}\nurdf: {{file: {ref}}}\n")
        with pytest.raises(SceneError, match="urdf.*(must lie inside|absolute path is not allowed)"):
            load_scene(name, allowed_dirs=A)
        assert load_scene(str(allowed / f"{name}.yaml")).urdf  # offline: as before


def test_overrides_cannot_point_files_outside(dirs):
    allowed, outside = dirs
    A = [str(allowed)]
    for ov, problem in [(f"bodies.brick.shape.file={outside / 'cube.obj'}", "an absolute path is not allowed"),
                        ("bodies.brick.shape.file=../outside/cube.obj", "must lie inside the scene file's directory")]:
        with pytest.raises(SceneError, match=problem):
            load_scene("mesh_cube", [ov], allowed_dirs=A)
        assert load_scene(str(allowed / "mesh_cube.yaml"), [ov]).bodies[0].name == "brick"  # offline: as before
    with pytest.raises(SceneError, match="urdf.*absolute path is not allowed"):
        load_scene("urdf_arm", [f"urdf={{file: {outside / 'arm.urdf'}}}"], allowed_dirs=A)


def test_requests_are_shown_as_text(dirs):
    allowed, _ = dirs
    msg = refused("../x\nFAKE LOG LINE", [str(allowed)])
    assert "\n" not in msg
    msg = refused("nope\nFAKE", [str(allowed)])
    assert msg.startswith("'nope\\nFAKE'")


def test_named_file_must_be_a_path():
    with pytest.raises(SceneError, match="'shape.file' must be a file path"):
        from redmax_ros.core import scene_from_dict
        scene_from_dict({"bodies": [{"name": "b", "shape": {"type": "mesh", "file": [1]}, "mass": 1.0}],
                         "joints": [{"name": "j", "type": "revolute", "parent": "world", "child": "b"}]})


# ----------------------------------------------------------------------------------------------
# size caps


def test_files_above_the_size_caps_are_refused(dirs):
    allowed, _ = dirs
    big = allowed / "big.yaml"
    with open(big, "wb") as f:  # sparse: the cap is checked before anything is read
        f.truncate(files.MAX_SCENE_BYTES + 1)
    with pytest.raises(SceneError) as ei:
        load_scene("big", allowed_dirs=[str(allowed)])
    assert "big.yaml" in str(ei.value) and f"above the limit of {files.MAX_SCENE_BYTES} bytes (4 MiB)" in str(ei.value)
    with pytest.raises(SceneError, match="above the limit"):  # offline too
        load_scene(str(big))
    # exactly at the cap: not refused for its size (a YAML comment of 4 MiB is an empty document)
    with open(big, "wb") as f:
        f.write(b"#" * (files.MAX_SCENE_BYTES - 1) + b"\n")
    with pytest.raises(SceneError, match="top level must be a mapping"):
        load_scene("big", allowed_dirs=[str(allowed)])
    # a mesh above its cap
    with open(allowed / "meshes" / "huge.obj", "wb") as f:
        f.truncate(files.MAX_MESH_BYTES + 1)
    _mesh_scene(allowed, "huge_mesh", "meshes/huge.obj")
    with pytest.raises(SceneError) as ei:
        load_scene("huge_mesh", allowed_dirs=[str(allowed)])
    msg = str(ei.value)
    assert "bodies[0] 'brick'" in msg and "huge.obj" in msg and f"above the limit of {files.MAX_MESH_BYTES} bytes (64 MiB)" in msg


def test_a_fifo_is_refused_not_waited_on(dirs):
    allowed, _ = dirs
    os.mkfifo(allowed / "fifo.yaml")
    os.mkfifo(allowed / "meshes" / "fifo.obj")
    _mesh_scene(allowed, "fifo_mesh", "meshes/fifo.obj")
    t0 = time.monotonic()
    with pytest.raises(SceneNotFound, match="no such scene"):  # by name: not a scene file
        load_scene("fifo", allowed_dirs=[str(allowed)])
    with pytest.raises(SceneError, match="not a regular file"):  # by path, offline
        load_scene(str(allowed / "fifo.yaml"))
    with pytest.raises(SceneError, match="mesh file not found"):
        load_scene("fifo_mesh", allowed_dirs=[str(allowed)])
    assert time.monotonic() - t0 < 10  # nothing waited for a writer


# ----------------------------------------------------------------------------------------------
# YAML alias bombs and nesting


BILLION_LAUGHS = """\
a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]
b: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]
c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]
d: &d [*c,*c,*c,*c,*c,*c,*c,*c,*c]
e: &e [*d,*d,*d,*d,*d,*d,*d,*d,*d]
f: &f [*e,*e,*e,*e,*e,*e,*e,*e,*e]
g: &g [*f,*f,*f,*f,*f,*f,*f,*f,*f]
h: &h [*g,*g,*g,*g,*g,*g,*g,*g,*g]
i: &i [*h,*h,*h,*h,*h,*h,*h,*h,*h]
"""


def _laughs_under_description():
    """The same nine levels inside an allowed key: without the limit, ``str(description)`` would
    build a 10^9-element repr."""
    lines = ["name: bomb", "description:", "  - &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    lines += [f"  - &l{i} [" + ", ".join([f"*l{i - 1}"] * 10) + "]" for i in range(1, 10)]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("text", [BILLION_LAUGHS, _laughs_under_description()], ids=["classic", "in_description"])
def test_alias_bombs_are_refused_quickly(dirs, text):
    allowed, _ = dirs
    assert text.count("*") < 100  # fewer than 100 aliases: a limit on the alias count would not stop it
    (allowed / "bomb.yaml").write_text(text)
    t0 = time.monotonic()
    with pytest.raises(SceneError) as ei:
        load_scene("bomb", allowed_dirs=[str(allowed)])
    assert time.monotonic() - t0 < 10  # milliseconds in fact; expanding it would take hours
    msg = str(ei.value)
    assert "bomb.yaml" in msg and f"more than {files.MAX_YAML_NODES} nodes with its aliases expanded" in msg
    assert "lol" not in msg


def test_recursive_aliases_and_deep_nesting_are_refused(dirs):
    allowed, _ = dirs
    cases = {
        "recursive": ("name: r\ndescription: &a [1, *a]\n", "recursive alias"),
        "deep": ("name: d\ndescription: " + "[" * 100000 + "]" * 100000 + "\n", "nested deeper than 64 levels"),
        "deep_by_alias": ("name: d\nx: &a " + "[" * 40 + "]" * 40 + "\ndescription: " + "[" * 40 + "*a" + "]" * 40 + "\n",
                          "nested deeper than 64 levels (aliases expanded)"),
    }
    for name, (text, problem) in cases.items():
        (allowed / f"{name}.yaml").write_text(text)
        with pytest.raises(SceneError) as ei:
            load_scene(name, allowed_dirs=[str(allowed)])
        assert problem in str(ei.value), (name, str(ei.value))
    with pytest.raises(SceneError, match="override .*recursive alias"):  # override values: the same limits
        load_scene("pendulum", ["description=&a [1, *a]"])


def test_moderate_anchors_and_aliases_still_work(dirs):
    allowed, _ = dirs
    text = PENDULUM.replace("gravity: [0, 0, -9.81]", "gravity: &g [0, 0, -9.81]") + \
        "wrenches:\n  - {name: w, body: link, force: *g}\n"
    (allowed / "anchors.yaml").write_text(text)
    spec = load_scene("anchors", allowed_dirs=[str(allowed)])
    assert spec.wrenches[0].force.tolist() == [0.0, 0.0, -9.81]


# ----------------------------------------------------------------------------------------------
# no file content in messages


@pytest.mark.parametrize("content", [
    f"{MARKER}: [unclosed\n",
    f"a: 1\n  {MARKER}: ] :\n",
    f"x: !!python/object/apply:os.system ['{MARKER}']\n",
    f"x: !{MARKER} 1\n",
    f"x: *{MARKER}\n",
    f"x: &{MARKER} 1\nx2: &{MARKER} 2\n",
    f"%{MARKER} 1\n--- 1\n",
    f'x: "\\q{MARKER}"\n',
    f"{MARKER}\tx: 1\n",
    f"{MARKER}: 1\n---\n{MARKER}: 2\n",
], ids=["unclosed", "mapping_values", "python_tag", "unknown_tag", "undefined_alias", "duplicate_anchor",
        "directive", "escape", "tab", "two_documents"])
def test_yaml_errors_do_not_quote_the_file(dirs, content):
    allowed, _ = dirs
    (allowed / "marker.yaml").write_text(content)
    with pytest.raises(SceneError) as ei:
        load_scene("marker", allowed_dirs=[str(allowed)])
    msg = str(ei.value)
    assert "marker.yaml" in msg and MARKER not in msg, msg
    assert "line " in msg or "top level" in msg, msg  # the position instead of the snippet


def test_binary_and_unconvertible_content_is_not_quoted(dirs):
    allowed, _ = dirs
    (allowed / "binary.yaml").write_bytes(MARKER.encode() + b": \xff\xfe\x00\x01\n")
    (allowed / "bigint.yaml").write_text(f"dt: 1{'0' * 5000}\n")
    (allowed / "date.yaml").write_text("dt: 2020-13-45\n")
    for name in ["binary", "bigint", "date"]:
        with pytest.raises(SceneError) as ei:
            load_scene(name, allowed_dirs=[str(allowed)])
        msg = str(ei.value)
        assert "not valid YAML" in msg and MARKER not in msg and "00000" not in msg, msg


def test_mesh_errors_do_not_quote_the_file(dirs):
    allowed, _ = dirs
    (allowed / "meshes" / "bad.obj").write_text(f"v 0 0 0\nv {MARKER} 0 0\n")
    (allowed / "meshes" / "bad_face.obj").write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 {MARKER}\n")
    for mesh in ["bad", "bad_face"]:
        _mesh_scene(allowed, mesh, f"meshes/{mesh}.obj")
        with pytest.raises(SceneError) as ei:
            load_scene(mesh, allowed_dirs=[str(allowed)])
        msg = str(ei.value)
        assert f"{mesh}.obj:2" in msg or f"{mesh}.obj:4" in msg, msg
        assert MARKER not in msg


def test_outside_secret_never_opened_so_never_quoted(dirs):
    allowed, outside = dirs
    for name in [str(outside / "secret.yaml"), "../outside/secret"]:
        assert MARKER not in refused(name, [str(allowed)])
    # offline, the same file is read; its syntax error is still reported by position only
    with pytest.raises(SceneError) as ei:
        load_scene(str(outside / "secret.yaml"))
    assert "not valid YAML" in str(ei.value) and MARKER not in str(ei.value)
