"""Config fields declared once: their command-line help and their valid values.

    elevation: float = option(0.0, "push elevation", ge=-90, le=90, unit="deg")

:func:`option` stores the declaration in the field's metadata; ``wbc_jax/cli.py`` generates the
flag from it and :func:`check_options` (called first by every job config's ``check()``) validates
the config against it, so a value is refused the same way from the command line and from Python,
in one line that names the flag and its valid range:

    --elevation must be a number in [-90, 90] deg, got 400

Declared: bounds (``ge``, ``gt``, ``le``, ``lt``; numbers are finite unless ``finite=False``), a
unit, ``choices``, ``ordered`` (a ``LO HI`` pair), ``nonempty`` (a list), ``input_file`` (exists,
a file, readable, UTF-8 text) and ``names`` (a callable ``robot name -> valid names``, e.g. the
pushable bodies; the owning layer supplies it, so this module imports no model). Types come from
the field's annotation. File entries (a contact, a scene object) declare theirs with
:func:`entry` and are checked with an ``owner`` that names them.

A group of flags that several jobs share (the controller's) is declared once, as a dataclass, and
held by each job's config as a :func:`nested` field: the command line, the checks, fingerprints and
summaries see its fields flat, as if declared in the job's config (:func:`flat_dict`, :func:`replace`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
import types
import typing
from collections.abc import Callable
from typing import Any

from wbc_jax.core import io, loader
from wbc_jax.core.loader import echo


@dataclasses.dataclass(frozen=True)
class Valid:
    """The valid values of one field (see the module docstring)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    unit: str = ""
    choices: tuple | None = None
    ordered: bool = False
    nonempty: bool = False
    input_file: bool = False
    names: Callable[[str], Any] | None = None
    finite: bool = True  # False: +-inf allowed (never NaN), e.g. a contact's activation "stop"

    def describe(self, integer: bool = False) -> str:
        """The valid range in words: ``a whole number in [1, 100]``, ``a number in (0, 600] s``."""
        kind = "a whole number" if integer else "a number"
        lo = f"[{_fmt(self.ge)}" if self.ge is not None else f"({_fmt(self.gt)}" if self.gt is not None else "(-inf"
        hi = f"{_fmt(self.le)}]" if self.le is not None else f"{_fmt(self.lt)})" if self.lt is not None else "inf)"
        unit = f" {self.unit}" if self.unit else ""
        return f"{kind} in {lo}, {hi}{unit}"

    def contains(self, x: float) -> bool:
        return (
            (self.ge is None or x >= self.ge)
            and (self.gt is None or x > self.gt)
            and (self.le is None or x <= self.le)
            and (self.lt is None or x < self.lt)
        )


def _fmt(x: float) -> str:
    return f"{int(x):,}" if x == int(x) and abs(x) >= 1e6 else f"{x:g}"


def option(
    default: Any,
    help: str,
    *,
    ge=None,
    gt=None,
    le=None,
    lt=None,
    unit: str = "",
    ordered: bool = False,
    nonempty: bool = False,
    input_file: bool = False,
    names=None,
    **cli: Any,
) -> Any:
    """A job-config field with its command-line help and its valid values (module docstring).

    ``cli`` entries shape the generated flag: ``choices`` (also checked), ``metavar``, ``nargs``,
    ``parse`` (the flag's values -> the field's value), ``show`` (the field's default -> the
    flag's default), ``flag`` (another flag name), ``positional`` (an argument, not a flag)."""
    if isinstance(default, (list, dict)):
        raise TypeError("mutable defaults are not allowed; use a tuple")
    valid = Valid(
        ge=ge,
        gt=gt,
        le=le,
        lt=lt,
        unit=unit,
        choices=tuple(cli["choices"]) if "choices" in cli else None,
        ordered=ordered,
        nonempty=nonempty,
        input_file=input_file,
        names=names,
    )
    return dataclasses.field(default=default, metadata={"help": help, "valid": valid, **cli})


def nested(default: Any) -> Any:
    """A field holding a shared group of flags (a frozen dataclass of :func:`option` fields): its
    fields are flags of the owning config, by their own names."""
    if not dataclasses.is_dataclass(default):
        raise TypeError("a nested field holds a dataclass instance")
    return dataclasses.field(default=default, metadata={"nested": True})


def is_nested(field: dataclasses.Field) -> bool:
    """``field`` holds a shared group of flags (:func:`nested`)."""
    return bool(field.metadata.get("nested"))


def flat_fields(obj) -> list[dataclasses.Field]:
    """The fields of config ``obj`` that are flags: its own and those of its nested groups."""
    out = []
    for field in dataclasses.fields(obj):
        out += flat_fields(getattr(obj, field.name)) if is_nested(field) else [field]
    return out


def flat_dict(obj) -> dict:
    """The fields of config ``obj`` by name, its nested groups' fields among them (JSON-ready values
    as ``dataclasses.asdict`` gives them)."""
    out = {}
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        if is_nested(field):
            out.update(flat_dict(value))
        else:
            out[field.name] = dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
    return out


def replace(obj, **changes):
    """``dataclasses.replace`` by flat names: a name of a nested group's field changes it there."""
    own = {}
    groups: dict[str, dict] = {}
    nested_names = {}
    for field in dataclasses.fields(obj):
        if is_nested(field):
            for inner in _flat_names(getattr(obj, field.name)):
                nested_names[inner] = field.name
    for name, value in changes.items():
        if name in nested_names:
            groups.setdefault(nested_names[name], {})[name] = value
        else:
            own[name] = value
    for group, values in groups.items():
        own[group] = replace(getattr(obj, group), **values)
    return dataclasses.replace(obj, **own)


def from_flat(cls: type, values: dict):
    """A config of type ``cls`` from flat field values (:func:`flat_dict`); names it lacks are left out."""
    obj = cls()
    known = set(_flat_names(obj))
    return replace(obj, **{k: v for k, v in values.items() if k in known})


def _flat_names(obj) -> list[str]:
    return [field.name for field in flat_fields(obj)]


def entry(default: Any = dataclasses.MISSING, **valid: Any) -> Any:
    """A field of a file entry (no flag; no default: required) with its valid values
    (:class:`Valid`'s fields)."""
    if isinstance(default, (list, dict)):
        raise TypeError("mutable defaults are not allowed; use a tuple")
    return dataclasses.field(default=default, metadata={"valid": Valid(**valid)})


def flag_name(field: dataclasses.Field) -> str:
    """The command-line name of a config field: ``--push-onset``, or its ``flag``, or for a
    positional argument its upper-case name (``RUN_DIR``)."""
    if field.metadata.get("positional"):
        return field.name.upper()
    return field.metadata.get("flag", "--" + field.name.replace("_", "-"))


def field_type(owner: type, field: dataclasses.Field) -> tuple[type, bool, bool]:
    """(scalar type, is a tuple, may be None) of a config field: ``float | None`` -> (float,
    False, True), ``tuple[float, ...]`` -> (float, True, False)."""
    hint = _hint(owner, field.name)
    optional = False
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional = len(args) < len(typing.get_args(hint))
        hint = args[0]
    if typing.get_origin(hint) is tuple:
        inner = [a for a in typing.get_args(hint) if a is not Ellipsis]
        return (inner[0] if inner else float), True, optional
    return hint, False, optional


def _hint(owner: type, name: str):
    """The annotation of field ``name`` of ``owner`` or of one of its nested groups."""
    hints = _hints(owner)
    if name in hints:
        return hints[name]
    for field in dataclasses.fields(owner):
        if is_nested(field):
            try:
                return _hint(type(field.default), name)
            except KeyError:
                continue
    raise KeyError(name)


@functools.lru_cache(maxsize=64)
def _hints(cls: type) -> dict:
    return typing.get_type_hints(cls)


def check_options(obj, owner: str | None = None, robot: str | None = None) -> None:
    """Raise ValueError, in one line naming the field and its valid values, for the first field of
    the dataclass ``obj`` outside its declaration (types, bounds, choices, order, input files,
    names on ``robot``, default the config's own ``robot`` field, checked first). Fields are named
    as flags (``--push-onset``), or with ``owner`` as keys of a file entry (``contact 'hand': mu``)."""
    hints = _hints(type(obj))
    fields = sorted(dataclasses.fields(obj), key=lambda f: f.name != "robot")  # the robot first: names need it
    for field in fields:
        if is_nested(field):
            check_options(getattr(obj, field.name), owner, robot or getattr(obj, "robot", None))
            continue
        valid = field.metadata.get("valid")
        if valid is None:
            continue
        value = getattr(obj, field.name)
        hint = hints[field.name]
        flag = flag_name(field) if owner is None else f"{owner}: {field.name}"
        if valid.choices is not None and not isinstance(value, tuple) and value is not None:
            if not isinstance(value, (str, int, float)) or value not in valid.choices:
                raise ValueError(f"{flag} must be one of {list(valid.choices)}, got {echo(value)}")
            continue
        if not _type_ok(value, hint):
            raise ValueError(f"{flag} must be {_type_words(hint)}, got {echo(value)}")
        if value is None:
            continue
        values = value if isinstance(value, tuple) else (value,)
        if valid.nonempty and not values:
            raise ValueError(f"{flag}: give at least one value")
        for v in values if valid.choices is not None else ():
            if v not in valid.choices:
                raise ValueError(f"{flag} must be among {list(valid.choices)}, got {echo(v)}")
        integer = _only(hint, int)
        for v in _numbers(value):
            if math.isnan(v) or (valid.finite and math.isinf(v)) or not valid.contains(v):
                shown = f"{v:g}" if isinstance(v, float) else echo(v)
                raise ValueError(f"{flag} must be {valid.describe(integer)}, got {shown}")
        if valid.ordered and len(values) == 2 and values[0] > values[1]:
            raise ValueError(f"{flag} LO HI must be ordered (LO <= HI), got {list(values)}")
        if valid.input_file:  # a file, or each of a list of files
            for v in values:
                check_input_file(v, flag)
        if valid.names is not None:
            known = list(valid.names(robot or obj.robot))
            for v in values:
                if v not in known:
                    raise ValueError(f"{flag} {echo(v)} is not a valid name here; valid: {known}")


def check_input_file(path, flag: str) -> None:
    """An input file named by ``flag`` exists, is a file, is readable, is not too large and is
    UTF-8 text (each problem in one line naming the flag and the file)."""
    if path is None:
        return
    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{flag} file {path} does not exist")
    if not path.is_file():
        raise ValueError(f"{flag} {path} is not a file (a directory?)")
    if path.suffix in (".json", ".yaml", ".yml"):  # read as the job will: within the loader's limits
        loader.read_data(path, flag)
    else:
        io.read_text(path, flag)


# ---- types from annotations ------------------------------------------------------------------


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _type_ok(value, hint) -> bool:
    """``value`` has the type ``hint`` (float, int, str, bool, None, unions, tuples, dataclasses)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, a) for a in typing.get_args(hint))
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_type_ok(v, args[0]) for v in value)
        return len(value) == len(args) and all(_type_ok(v, a) for v, a in zip(value, args, strict=True))
    if hint is type(None):
        return value is None
    if hint is float:
        return _is_number(value)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is Any:
        return True
    return isinstance(value, hint)


def _type_words(hint) -> str:
    """What ``hint`` asks for, in words."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_words(a) for a in typing.get_args(hint))
    if origin is tuple:
        args = typing.get_args(hint)
        plural = {float: "numbers", int: "whole numbers", str: "names"}.get(args[0]) or f"({_type_words(args[0])})"
        return f"a list of {plural}" if len(args) == 2 and args[1] is Ellipsis else f"a list of {len(args)} {plural}"
    words = {float: "a number", int: "a whole number", str: "text", bool: "true or false", type(None): "null"}
    return words.get(hint, f"a {getattr(hint, '__name__', hint)} mapping")


def _numbers(value):
    if isinstance(value, tuple):
        for v in value:
            yield from _numbers(v)
    elif _is_number(value):
        yield value


def _only(hint, kind) -> bool:
    """Every number ``hint`` allows is of type ``kind``."""
    args = [a for a in typing.get_args(hint) if a not in (type(None), Ellipsis)]
    return all(_only(a, kind) for a in args) if args else hint is kind
