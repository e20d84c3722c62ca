"""Reading the files of a scene within limits (docs/scenes.md, "Limits"; docs/node.md, "Security").

* **Where** (used by loader.py and bodies.py): ``real`` (symlinks resolved), ``inside`` (a real path
  in a real directory), ``climbs`` (a relative path whose ``..`` leave its base directory).
* **How large**: ``read_capped`` reads a regular file of at most ``limit`` bytes (never blocks on a
  FIFO or a device, never reads more than ``limit`` + 1 bytes even if the file grows meanwhile);
  ``check_size`` for files another library reads by path (URDF, read by Pinocchio).
* **How far a YAML document expands**: ``parse_yaml`` parses with ``yaml.SafeLoader`` and refuses a
  document nested deeper than MAX_YAML_DEPTH or with more than MAX_YAML_NODES nodes once every alias
  is expanded (a "billion laughs" document has ~90 aliases but 10^9 expanded nodes: counting aliases
  alone would not stop it; its parsed form shares the repeated lists, the blow-up comes when
  anything walks or prints it), and a recursive alias.

No file content goes into an error message: a YAML syntax error is reported by its problem (quoted
fragments replaced by ``(...)``) and line/column, never by PyYAML's snippet of the offending line.
Problems are raised as :class:`FileProblem` (a message without the file's name); the callers turn
them into a SceneError naming the file and the entry.
"""
from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import yaml

MiB = 1024 * 1024
MAX_SCENE_BYTES = 4 * MiB  # a scene YAML file
MAX_MESH_BYTES = 64 * MiB  # a file a scene names: OBJ mesh, URDF
MAX_YAML_NODES = 1_000_000  # nodes of a YAML document (scene file or override value), aliases expanded
MAX_YAML_DEPTH = 64  # nesting of collections, aliases expanded
MAX_BODIES = 25_000  # bodies (and joints) of a scene, as written or as a builder makes them; the largest builder count
MAX_ENTRIES = 200_000  # entries of any other list section of a scene (sites, springs, loops, contacts, ...)


class FileProblem(ValueError):
    """A file cannot be used (too large, not a regular file, unreadable, not valid YAML, ...)."""


# ----------------------------------------------------------------------------------------------
# where


def real(p) -> Path:
    """``p`` with every symlink resolved (``os.path.realpath``; the file need not exist)."""
    return Path(os.path.realpath(os.fspath(p)))


def inside(path: Path, root: Path) -> bool:
    """True if the real path ``path`` is the real directory ``root`` or lies below it."""
    return path == root or root in path.parents


def climbs(rel: str) -> bool:
    """True if the relative path ``rel`` leaves its base directory by ``..`` (lexically)."""
    norm = os.path.normpath(rel)
    return norm == os.pardir or norm.startswith(os.pardir + os.sep)


# ----------------------------------------------------------------------------------------------
# how large


def _size_problem(size: int, limit: int) -> str:
    return f"file is {size} bytes, above the limit of {limit} bytes ({limit / MiB:g} MiB)"


def read_capped(path, limit: int) -> bytes:
    """The bytes of the regular file ``path`` if it has at most ``limit`` bytes; FileProblem otherwise.

    Opened without following a final symlink (pass a ``real`` path) and without blocking (a FIFO or
    a device is refused, not waited on); at most ``limit`` + 1 bytes are read."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(os.fspath(path), flags)
    except OSError as e:
        raise FileProblem(f"cannot open: {e.strerror}") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileProblem("not a regular file")
        if st.st_size > limit:
            raise FileProblem(_size_problem(st.st_size, limit))
        try:
            data = f.read(limit + 1)
        except OSError as e:
            raise FileProblem(f"cannot read: {e.strerror}") from None
    if len(data) > limit:
        raise FileProblem(_size_problem(len(data), limit))
    return data


def check_size(path, limit: int) -> None:
    """FileProblem unless ``path`` is a regular file of at most ``limit`` bytes (for files that
    another library reads by path)."""
    try:
        st = os.stat(os.fspath(path))
    except OSError as e:
        raise FileProblem(f"cannot open: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise FileProblem("not a regular file")
    if st.st_size > limit:
        raise FileProblem(_size_problem(st.st_size, limit))


# ----------------------------------------------------------------------------------------------
# YAML


class _Limit(yaml.YAMLError):
    def __init__(self, problem, mark=None):
        super().__init__(problem)
        self.problem, self.problem_mark = problem, mark


class _LimitedLoader(yaml.SafeLoader):
    """SafeLoader whose composer refuses nesting deeper than MAX_YAML_DEPTH while composing (PyYAML's
    composer recurses once per level: "[[[[...]]]]" would otherwise end in a RecursionError)."""

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        if not self.check_event(yaml.SequenceStartEvent, yaml.MappingStartEvent):
            return super().compose_node(parent, index)
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise _Limit(f"nested deeper than {MAX_YAML_DEPTH} levels", self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _measure(root) -> None:
    """Refuse a composed document that expands (aliases followed) to more than MAX_YAML_NODES nodes
    or deeper than MAX_YAML_DEPTH, or has a recursive alias. Linear in the composed size (each node's
    expanded size and height are computed once)."""
    memo = {}  # id(node) -> (expanded node count, height: levels of collections, 0 for a scalar)
    on_path = set()
    too_deep = f"nested deeper than {MAX_YAML_DEPTH} levels (aliases expanded)"

    def visit(node, depth):  # depth: the level of ``node`` if it is a collection (the root's is 1)
        key = id(node)
        if key in memo:
            count, height = memo[key]
            if depth - 1 + height > MAX_YAML_DEPTH:
                raise _Limit(too_deep, node.start_mark)
            return count, height
        if key in on_path:
            raise _Limit("recursive alias (a collection that contains itself)", node.start_mark)
        if isinstance(node, yaml.ScalarNode):
            memo[key] = (1, 0)
            return 1, 0
        if depth > MAX_YAML_DEPTH:
            raise _Limit(too_deep, node.start_mark)
        on_path.add(key)
        children = node.value if isinstance(node, yaml.SequenceNode) else [x for kv in node.value for x in kv]
        count, height = 1, 1
        for child in children:
            c, h = visit(child, depth + 1)
            count += c
            height = max(height, h + 1)
            if count > MAX_YAML_NODES:
                raise _Limit(f"more than {MAX_YAML_NODES} nodes with its aliases expanded "
                             "(an alias bomb?)", node.start_mark)
        on_path.discard(key)
        memo[key] = (count, height)
        return count, height

    visit(root, 1)


_QUOTED = re.compile(r"'[^'\n]*'|\"[^\"\n]*\"")
_GRAMMAR = re.compile(r"'(<[a-z ]+>|[\[\]{},:?-])'")  # PyYAML's token names ('<block end>') and indicators


def _unquote(m):
    return m.group(0) if _GRAMMAR.fullmatch(m.group(0)) else "(...)"


def _describe(e: yaml.YAMLError) -> str:
    """A YAML error as its problem and position, without the snippet of the file PyYAML adds (and
    with quoted fragments of the file, such as a tag, an alias or a character, replaced by (...);
    PyYAML's own token names and indicators stay)."""
    if isinstance(e, yaml.reader.ReaderError):
        return f"not valid YAML: not UTF-8/UTF-16 text or an unacceptable character at byte {e.position}"
    problem = getattr(e, "problem", None) or getattr(e, "context", None) or type(e).__name__
    problem = _QUOTED.sub(_unquote, str(problem))[:200]
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
    return f"not valid YAML: {problem}{where}"


def parse_yaml(data):
    """The document in ``data`` (bytes or str) as Python data, by ``yaml.SafeLoader`` within the
    limits above; FileProblem (no file content in its message) when it is not valid YAML, has more
    than one document or exceeds a limit."""
    loader = None
    try:
        loader = _LimitedLoader(data)  # reads the first bytes: a ReaderError here already
        node = loader.get_single_node()
        if node is None:
            return None
        _measure(node)
        return loader.construct_document(node)
    except yaml.YAMLError as e:
        raise FileProblem(_describe(e)) from None
    except (ValueError, TypeError, OverflowError, RecursionError) as e:  # a value the constructor cannot
        # convert (an integer of more than 4300 digits, a date such as 2020-13-45); its message may quote it
        raise FileProblem(f"not valid YAML: a value cannot be converted ({type(e).__name__})") from None
    finally:
        if loader is not None:
            loader.dispose()
