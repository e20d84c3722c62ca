"""The package's layering, read from its imports (ast), so that it stays as docs/architecture.md draws it:

* no import cycle among the modules of ``redmax_ros`` and ``redmax_bench``;
* no import of a private name (``_x``) from another module;
* no import inside a function, except of optional dependencies (the line says ``# optional:``) and of
  the modules listed in OPTIONAL_MODULES (MuJoCo, matplotlib, Exudyn, ROS packages for the
  benchmarks that may run without them);
* the core imports no ROS package, and the layers of the core import only downwards:
  geometry -> scene -> model -> solvers -> dynamics -> friction -> step -> simulator;
* the node, the runner, the logging, the sweeps (redmax_ros/sweep/) and the benchmarks use the core through its
  public API (``redmax_ros.core`` and the public names of its sub-packages), never the reverse.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("redmax_ros", "redmax_bench")
OPTIONAL_MODULES = ("mujoco", "matplotlib", "exudyn", "ray", "rclpy", "redmax_msgs", "sensor_msgs", "std_msgs",
                    "diagnostic_msgs", "rosgraph_msgs", "visualization_msgs", "geometry_msgs", "builtin_interfaces",
                    "rcl_interfaces", "zstandard", "lz4")
ROS_MODULES = OPTIONAL_MODULES[4:] + ("rosidl_runtime_py", "ament_index_python")
# layers of redmax_ros.core, bottom first; a module may import its own layer and the ones below
CORE_LAYERS = [("errors", "jit", "linalg", "spatial"), ("geometry",), ("deformable",), ("scene",), ("model",), ("solvers",),
               ("dynamics",), ("friction",), ("step",), ("simulator",)]


def _modules():
    mods = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


MODULES = _modules()


def _imports(name, path):
    """(imported module or None, [names], lineno, inside a function, source line) per import statement."""
    tree = ast.parse(path.read_text(), str(path))
    lines = path.read_text().splitlines()
    parents = {c: n for n in ast.walk(tree) for c in ast.iter_child_nodes(n)}
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        inside, p = False, node
        while p in parents:
            p = parents[p]
            if isinstance(p, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                inside = True
                break
        line = lines[node.lineno - 1]
        if isinstance(node, ast.Import):
            for a in node.names:
                out.append((a.name, [], node.lineno, inside, line))
            continue
        if node.level:
            base = name.split(".") if is_pkg else name.split(".")[:-1]
            base = base[:len(base) - (node.level - 1)]
            mod = ".".join(base + ([node.module] if node.module else []))
        else:
            mod = node.module
        out.append((mod, [a.name for a in node.names], node.lineno, inside, line))
    return out


def _targets(mod, names):
    """The project modules an import statement loads."""
    if mod is None or mod.split(".")[0] not in PACKAGES:
        return []
    found = [f"{mod}.{n}" for n in names if f"{mod}.{n}" in MODULES]
    if len(found) < len(names) and mod in MODULES:
        found.append(mod)
    return found


IMPORTS = {name: _imports(name, path) for name, path in MODULES.items()}


def _graph():
    g = {m: set() for m in MODULES}
    for m, imps in IMPORTS.items():
        for mod, names, *_ in imps:
            g[m].update(t for t in _targets(mod, names) if t != m)
    return g


def _cycles(g):
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(g[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_modules_found():
    assert "redmax_ros.core.simulator" in MODULES and "redmax_ros.node.main" in MODULES
    assert "redmax_bench.cli" in MODULES


def test_no_import_cycles():
    assert _cycles(_graph()) == []


def test_no_private_names_imported_from_other_modules():
    bad = []
    for m, imps in IMPORTS.items():
        for mod, names, lineno, _, _ in imps:
            if mod is None or mod.split(".")[0] not in PACKAGES:
                continue
            bad += [f"{m}:{lineno} imports {n} from {mod}" for n in names
                    if n.startswith("_") and n != "__future__" and f"{mod}.{n}" not in MODULES]
            if mod.rsplit(".", 1)[-1].startswith("_") and mod.rsplit(".", 1)[-1] != "__init__":
                bad.append(f"{m}:{lineno} imports private module {mod}")
    assert bad == []


def test_no_imports_inside_functions_except_optional_dependencies():
    bad = []
    for m, imps in IMPORTS.items():
        for mod, names, lineno, inside, line in imps:
            if not inside:
                continue
            top = (mod or names[0]).split(".")[0]
            if top in OPTIONAL_MODULES or "# optional:" in line:
                continue
            bad.append(f"{m}:{lineno}: {line.strip()}")
    assert bad == []


def _core_layer(module):
    parts = module.split(".")
    if parts[:2] != ["redmax_ros", "core"] or len(parts) < 3:
        return None
    for i, names in enumerate(CORE_LAYERS):
        if parts[2] in names:
            return i
    raise AssertionError(f"{module} is in no layer of CORE_LAYERS")


def test_core_layers_import_only_downwards():
    bad = []
    for m, imps in IMPORTS.items():
        lm = _core_layer(m)
        if lm is None:
            continue
        for mod, names, lineno, _, _ in imps:
            top = (mod or "").split(".")[0]
            if top in ROS_MODULES:
                bad.append(f"{m}:{lineno} imports ROS package {mod}")
            for t in _targets(mod, names):
                lt = _core_layer(t)
                if t.split(".")[0] in PACKAGES and not t.startswith("redmax_ros.core"):
                    bad.append(f"{m}:{lineno} imports {t} (above the core)")
                elif lt is not None and lt > lm:
                    bad.append(f"{m}:{lineno} imports {t} (layer {CORE_LAYERS[lt]} above {CORE_LAYERS[lm]})")
    assert bad == []


@pytest.mark.parametrize("client", ["redmax_ros.node", "redmax_ros.logging", "redmax_ros.runner", "redmax_ros.sweep"])
def test_node_runner_and_logging_use_only_the_core_facade(client):
    """Thin clients: the node, the runner, the logging and the sweeps import the core only as ``redmax_ros.core``."""
    bad = []
    for m, imps in IMPORTS.items():
        if not (m == client or m.startswith(client + ".")):
            continue
        for mod, names, lineno, _, _ in imps:
            if mod and mod.startswith("redmax_ros.core."):
                bad.append(f"{m}:{lineno} imports {mod}")
    assert bad == []


def test_every_package_folder_is_a_regular_package():
    """Each folder of Python modules has an __init__.py, so setuptools' find_packages (setup.py: pip and
    colcon installs) ships it; a namespace folder would work in the source tree only."""
    missing = [str(d.relative_to(ROOT)) for pkg in PACKAGES for d in [ROOT / pkg, *(ROOT / pkg).rglob("*")]
               if d.is_dir() and d.name != "__pycache__" and any(d.glob("*.py")) and not (d / "__init__.py").exists()]
    assert missing == []
