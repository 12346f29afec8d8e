"""The one loader of the jobs' input files (task files, gains, envelopes, held-out sets, summaries):
JSON or YAML with limits, so a hostile file fails in one short line within seconds.

    read_data(path, what)   -> value   by suffix: .json, .yaml / .yml
    parse_json(text, ...)   -> value   nesting at most MAX_DEPTH
    parse_yaml(text, ...)   -> value   safe tags only; nesting and expanded size (aliases) capped
    echo(value)             -> str     a value's repr cut to ECHO_CHARS, for error messages

The file's size is capped before it is read (:func:`wbc_jax.core.io.read_text`, ``io.MAX_FILE_BYTES``).
YAML aliases are allowed, but the document they expand to is counted (a 400-byte "billion laughs"
file expands to 10^9 nodes) and refused above MAX_NODES; a recursive alias is refused.
"""

from __future__ import annotations

import json
import pathlib
import re
from typing import Any

import numpy as np

from wbc_jax.core import io

MAX_DEPTH = 32  # nesting levels: a task file needs 5, a summary 6
MAX_YAML_BYTES = 2**20  # YAML files are task files (2 kB); PyYAML parses about 1 MB/s
MAX_NODES = 200_000  # values of a YAML document with its aliases expanded
ECHO_CHARS = 80  # longest value echoed in an error message

_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.S)


def echo(value: Any, limit: int = ECHO_CHARS) -> str:
    """``repr(value)`` cut to ``limit`` characters (a hostile value may expand to megabytes)."""
    text = reprlib_repr(value, limit)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _cut(text: str, limit: int = ECHO_CHARS) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def reprlib_repr(value: Any, limit: int) -> str:
    """A repr that stops early on long containers (never builds the full text of a huge value)."""
    import reprlib

    short = reprlib.Repr()
    short.maxlevel, short.maxlist, short.maxdict, short.maxtuple = 3, 8, 8, 8
    short.maxstring = short.maxother = limit
    return short.repr(value)


def read_data(path, what: str) -> Any:
    """The value of a JSON (``.json``) or YAML (``.yaml``, ``.yml``) file, within the limits; one
    line naming ``what`` and the file otherwise."""
    path = pathlib.Path(path)
    if path.suffix not in (".json", ".yaml", ".yml"):
        raise ValueError(f"{what} file {path}: unknown format {path.suffix!r}; valid: .json, .yaml, .yml")
    text = io.read_text(path, what, io.MAX_FILE_BYTES if path.suffix == ".json" else MAX_YAML_BYTES)
    return parse_json(text, path, what) if path.suffix == ".json" else parse_yaml(text, path, what)


def _too_deep(what: str, path, depth: int) -> ValueError:
    return ValueError(f"{what} file {path} nests {depth} levels deep; at most {MAX_DEPTH} are read")


def parse_json(text: str, path, what: str) -> Any:
    """JSON ``text`` of ``path``; nesting checked before parsing (Python's parser recurses)."""
    brackets = np.frombuffer(_STRING.sub("", text).encode("utf-8", "replace"), np.uint8)
    step = (
        (brackets == ord("[")).astype(np.int32)
        + (brackets == ord("{"))
        - (brackets == ord("]"))
        - (brackets == ord("}"))
    )
    depth = int(np.cumsum(step).max(initial=0))
    if depth > MAX_DEPTH:
        raise _too_deep(what, path, depth)
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{what} file {path} is not valid JSON: {err}") from None
    except (ValueError, RecursionError) as err:  # e.g. an integer of more than 4300 digits
        raise ValueError(f"{what} file {path} is not valid JSON: {_cut(str(err))}") from None


def parse_yaml(text: str, path, what: str) -> Any:
    """YAML ``text`` of ``path`` (safe tags; ``1e3`` read as a number), within the limits."""
    import yaml

    try:
        return yaml.load(text, Loader=_loader_class(path, what))
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        at = f" (line {where.line + 1}, column {where.column + 1})" if where is not None else ""
        raise ValueError(
            f"{what} file {path} is not valid YAML{at}: {_cut(str(getattr(err, 'problem', None) or err))}"
        ) from None
    except RecursionError:
        raise _too_deep(what, path, MAX_DEPTH + 1) from None


def _loader_class(path, what: str):
    import yaml

    class Loader(yaml.SafeLoader):
        """PyYAML's safe loader that reads ``1e3`` as a number (YAML 1.1 wants ``1.0e+3``: its plain
        ``1e3`` is a string, a trap for every number of a task file), with the nesting depth counted
        while composing and the expanded size counted before constructing."""

        depth = 0

        def compose_node(self, parent, index):
            self.depth += 1
            if self.depth > MAX_DEPTH:
                raise _too_deep(what, path, self.depth)
            try:
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1

        def construct_document(self, node):
            _check_expanded(node, path, what)
            return super().construct_document(node)

    exponent = re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$")
    Loader.add_implicit_resolver("tag:yaml.org,2002:float", exponent, list("-+0123456789"))
    return Loader


def _check_expanded(root, path, what: str) -> None:
    """Refuse a YAML node graph whose expansion (every alias replaced by its anchor's value) holds
    more than MAX_NODES values or nests deeper than MAX_DEPTH, or that refers to itself. Iterative,
    memoised per node: linear in the composed graph however large its expansion."""
    import yaml

    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    stack = [(root, False)]
    open_nodes: set[int] = set()
    while stack:
        node, done = stack.pop()
        key = id(node)
        if isinstance(node, yaml.ScalarNode) or key in size and not done:
            size.setdefault(key, 1)
            depth.setdefault(key, 0)
            continue
        children = [c for pair in node.value for c in pair] if isinstance(node, yaml.MappingNode) else node.value
        if done:
            open_nodes.discard(key)
            size[key] = 1 + sum(size[id(c)] for c in children)
            depth[key] = 1 + max((depth[id(c)] for c in children), default=0)
            if size[key] > MAX_NODES:
                raise ValueError(
                    f"{what} file {path} expands to more than {MAX_NODES:,} values (YAML aliases "
                    "counted expanded); at most that many are read"
                )
            if depth[key] > MAX_DEPTH:
                raise _too_deep(what, path, depth[key])
            continue
        if key in open_nodes:
            raise ValueError(f"{what} file {path}: a YAML alias refers to a value that contains it (recursive)")
        open_nodes.add(key)
        stack.append((node, True))
        for child in children:
            if id(child) in open_nodes:
                raise ValueError(f"{what} file {path}: a YAML alias refers to a value that contains it (recursive)")
            if id(child) not in size:
                stack.append((child, False))


def read_json(path, what: str):
    """The JSON value of ``path`` (:func:`wbc_jax.core.io.read_text`); one line naming the file when it is not JSON."""
    return parse_json(io.read_text(path, what), path, what)


def is_gains_file(path) -> bool:
    """Is ``path`` a gains file: a JSON object whose keys are exactly the gain names
    (constants.GAIN_FIELDS)? (Reading it as gains, with its values checked: control.gains.load_gains.)"""
    from wbc_jax.core.constants import GAIN_FIELDS

    path = pathlib.Path(path)
    if path.suffix != ".json" or not path.is_file():
        return False
    try:
        values = read_json(path, "gains")
    except (ValueError, OSError):
        return False
    return isinstance(values, dict) and set(values) == set(GAIN_FIELDS)
