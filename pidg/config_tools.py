"""Dataclass configs <-> command line and JSON, with the standard library only.

One source of truth per setting: a config field's type annotation is its parser and validator (``Literal`` fields
take their choices from the annotation; numeric fields are finite and, when annotated ``Annotated[int, Range(1)]``,
within their range; :func:`validate_config` checks both from ``__post_init__``, so Python callers, the command
line and saved JSON get the same checks), and the string literal right below the field (the nerfstudio / tyro
convention) is its documentation and its ``--help`` text. Every leaf field of a nested config becomes a
``--section.field VALUE`` option; the resolved config is written as JSON next to every run and read back by
:func:`from_jsonable`, the one deserializer (nested dataclasses, tuples, paths, unions), so config classes need no
per-class fixes for JSON.

Why not tyro (the dataclass CLI nerfstudio and gsplat use)? It was tried on ``TrainConfig``: it would change every
documented command (``--data.time-source`` with dashes, ``--flag/--no-flag`` booleans, ``400 400`` instead of
``400x400``), prints multi-line boxed errors where pidg gives one line naming the option, does not read configs
back from JSON, and adds four packages; what it offered that this module lacked (field docstrings as help text,
choices shown) is ~60 lines here.
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import json
import math
import textwrap
import types
import typing
from pathlib import Path
from typing import Annotated, Any, TypeVar, Union, get_args, get_origin, get_type_hints

T = TypeVar("T")
_MISSING = object()
MISSING_OPTION = _MISSING  # default of options that override a config field only when given


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a numeric config field allows (``Annotated[float, Range(0, 1)]``); bounds are inclusive unless
    ``lo_open`` / ``hi_open``; None: unbounded. Tuples of numbers are checked element by element."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, x: float) -> bool:
        above = self.lo is None or (x > self.lo if self.lo_open else x >= self.lo)
        below = self.hi is None or (x < self.hi if self.hi_open else x <= self.hi)
        return above and below

    def describe(self) -> str:
        if self.hi is None:
            return "any number" if self.lo is None else f"{'>' if self.lo_open else '>='} {self.lo:g}"
        if self.lo is None:
            return f"{'<' if self.hi_open else '<='} {self.hi:g}"
        return f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"


POSITIVE = Range(0, lo_open=True)
NON_NEGATIVE = Range(0)
AT_LEAST_ONE = Range(1)
UNIT = Range(0, 1)  # a share or weight in [0, 1]


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """Resolved field annotations of a class, ``Annotated`` extras stripped (cached: configs are validated on
    every construction)."""
    return get_type_hints(cls)


@functools.cache
def field_ranges(cls: type) -> dict[str, Range]:
    """Field name -> its declared ``Range`` (``Annotated[..., Range(...)]``, also inside ``X | None``)."""
    out = {}
    for name, tp in get_type_hints(cls, include_extras=True).items():
        candidates = [tp] + list(get_args(tp) if get_origin(tp) in (Union, types.UnionType) else [])
        for candidate in candidates:
            if get_origin(candidate) is Annotated:
                out.update({name: extra for extra in candidate.__metadata__ if isinstance(extra, Range)})
    return out


def _numbers(value: Any) -> list[float]:
    """The numeric leaves of a value (a number or nested tuples/lists of numbers; bools are not numbers)."""
    if isinstance(value, bool):
        return []
    if isinstance(value, (int, float)):
        return [value]
    if isinstance(value, (tuple, list)):
        return [x for v in value for x in _numbers(v)]
    return []


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _strip_optional(tp: Any) -> tuple[Any, bool]:
    """(inner type, allows None) for ``X | None`` / ``Optional[X]``."""
    if get_origin(tp) in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(get_args(tp)) == 2:
            return args[0], True
    return tp, False


def literal_choices(tp: Any) -> tuple[Any, ...]:
    """The values a ``Literal[...]`` (or ``Literal[...] | None``) annotation allows; () for other types."""
    inner, _ = _strip_optional(tp)
    return get_args(inner) if get_origin(inner) is typing.Literal else ()


# ---------------------------------------------------------------------------------------------------------------
# documentation and validation from the class itself
# ---------------------------------------------------------------------------------------------------------------
@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """Field name -> the string literal written right below it in the class body ("" where there is none)."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError, SyntaxError):  # no source (e.g. built in an interactive session)
        return {}
    body = next((node.body for node in ast.walk(tree) if isinstance(node, ast.ClassDef) and node.name == cls.__name__), [])
    docs = {}
    for node, following in zip(body, body[1:] + [None]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            is_doc = isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
            docs[node.target.id] = " ".join(str(following.value.value).split()) if is_doc else ""  # type: ignore[union-attr]
    return docs


def validate_config(config: Any) -> None:
    """Raise ValueError naming the field if a ``Literal`` field holds a value its annotation does not allow, a
    number is NaN or infinite, or a number lies outside its declared ``Range``.

    Config classes call it from ``__post_init__``, so Python callers get the same checks as the command line.
    """
    cls = type(config)
    hints, ranges = _hints(cls), field_ranges(cls)
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        where = f"{cls.__name__}.{f.name}"
        choices = literal_choices(hints[f.name])
        if choices and value not in choices and not (value is None and _strip_optional(hints[f.name])[1]):
            raise ValueError(f"{where} must be one of {', '.join(map(str, choices))}, got {value!r}")
        numbers = _numbers(value)
        if any(isinstance(x, float) and not math.isfinite(x) for x in numbers):
            raise ValueError(f"{where} must be a finite number, got {value!r}")
        bounds = ranges.get(f.name)
        if bounds is not None and not all(bounds.contains(x) for x in numbers):
            raise ValueError(f"{where} must be {bounds.describe()}, got {value!r}")


# ---------------------------------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------------------------------
def parse_value(text: str, tp: Any, name: str) -> Any:
    """Parse a command-line string into a value of annotation ``tp``; errors name the option."""
    inner, optional = _strip_optional(tp)
    if optional and text.lower() in ("none", "null"):
        return None
    origin = get_origin(inner)
    try:
        if inner is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError("expected true/false")
        if inner in (int, float, str):
            return inner(text)
        if inner is Path:
            return Path(text)
        if origin is typing.Literal:
            for choice in get_args(inner):
                if str(choice) == text:
                    return choice
            raise ValueError(f"expected one of {', '.join(map(str, get_args(inner)))}")
        if origin in (tuple, list):
            args = get_args(inner)
            sep = text.replace(",", " ")
            if args and all(a is int for a in args if a is not Ellipsis):
                sep = sep.replace("x", " ")  # sizes: "400x400"
            parts = [p for p in sep.split() if p]
            if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
                return tuple(parse_value(p, args[0], name) for p in parts)
            if origin is tuple:
                if len(parts) != len(args):
                    raise ValueError(f"expected {len(args)} values")
                return tuple(parse_value(p, a, name) for p, a in zip(parts, args))
            return [parse_value(p, args[0] if args else str, name) for p in parts]
        if origin in (Union, types.UnionType):  # e.g. float | tuple[int, int]: first parse that works
            for option in get_args(inner):
                try:
                    return parse_value(text, option, name)
                except ValueError:
                    continue
            raise ValueError(f"cannot parse as {inner}")
    except ValueError as err:
        raise ValueError(f"--{name}: cannot use {text!r}: {err}") from None
    raise TypeError(f"--{name}: unsupported option type {inner}")


def _leaves(cls: type, prefix: str = "") -> list[tuple[str, Any, dataclasses.Field, type]]:
    """(dotted name, type, field, owning class) of every leaf field of a dataclass type, nested ones expanded."""
    hints = _hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp = hints[f.name]
        name = f"{prefix}{f.name}"
        inner, _ = _strip_optional(tp)
        if _is_dataclass_type(inner):
            out += _leaves(inner, name + ".")
        else:
            out.append((name, tp, f, cls))
    return out


def _takes_several(tp: Any) -> bool:
    """Whether an option may be given as several words: a tuple or list, or a union with one (a resolution of one
    int or three: ``--...finest_resolution 32 32 64`` as well as ``32,32,64`` or ``32``)."""
    inner = _strip_optional(tp)[0]
    options = get_args(inner) if get_origin(inner) in (Union, types.UnionType) else (inner,)
    return any(get_origin(a) in (tuple, list) for a in options)


def _metavar(tp: Any) -> str:
    inner, optional = _strip_optional(tp)
    choices = literal_choices(inner) or ((True, False) if inner is bool else ())
    text = "{" + ",".join(str(c).lower() if isinstance(c, bool) else str(c) for c in choices) + "}" if choices else "VALUE"
    return text + ("|none" if optional and choices else "")


def _default_text(f: dataclasses.Field, owner: type) -> str:
    bounds = field_ranges(owner).get(f.name)
    return (f"{bounds.describe()}; " if bounds is not None else "") + f"default: {_default_value(f)}"


def _default_value(f: dataclasses.Field) -> str:
    if "command_line_default" in f.metadata:  # a field the commands fill in before the others (e.g. the preset)
        return str(f.metadata["command_line_default"])
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        value = f.default_factory()  # type: ignore[misc]
    else:
        return "required"
    if isinstance(value, tuple):
        return " ".join(map(str, value)) if value else "()"
    return str(value).lower() if isinstance(value, bool) else str(value)


def add_config_arguments(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one ``--a.b`` option per leaf field of ``cls``, grouped by section, with the field's docstring as help
    (defaults stay in the dataclass: an option that is not given changes nothing)."""
    groups: dict[str, argparse._ArgumentGroup] = {}
    for name, tp, f, owner in _leaves(cls):
        section = name.split(".")[0] if "." in name else ""
        if section not in groups:
            title = f"--{section}.* options" if section else f"{cls.__name__} options"
            summary = (inspect.getdoc(owner) or "").split("\n\n")[0].replace("\n", " ") if section else ""
            groups[section] = parser.add_argument_group(title, summary or None)
        doc = field_docs(owner).get(f.name, "")
        # several values as separate words (``--data.splits train val test``) or one (``train,val,test``)
        several = _takes_several(tp)
        groups[section].add_argument(
            f"--{name}", dest=f"cfg::{name}", default=_MISSING, metavar=_metavar(tp), nargs="+" if several else None,
            help=f"{doc} ({_default_text(f, owner)})".strip().replace("%", "%%"),
        )


def undocumented_options(cls: type) -> list[str]:
    """Options of ``cls`` without a docstring (the test suite keeps this empty)."""
    return [name for name, _, f, owner in _leaves(cls) if not field_docs(owner).get(f.name)]


def _is_numeric(tp: Any) -> bool:
    inner, _ = _strip_optional(tp)
    if inner in (int, float):
        return True
    if get_origin(inner) in (tuple, list, Union, types.UnionType):
        return any(_is_numeric(a) for a in get_args(inner) if a is not Ellipsis)
    return False


def unbounded_numeric_options(cls: type) -> list[str]:
    """Numeric options of ``cls`` without a declared ``Range`` (the test suite keeps this empty)."""
    return [name for name, tp, f, owner in _leaves(cls) if _is_numeric(tp) and f.name not in field_ranges(owner)]


def overrides_from_args(args: argparse.Namespace) -> dict[str, str]:
    """The ``--a.b VALUE`` options the user actually gave."""
    return {
        k[len("cfg::"):]: " ".join(v) if isinstance(v, list) else v
        for k, v in vars(args).items() if k.startswith("cfg::") and v is not _MISSING
    }


def apply_overrides(config: T, overrides: dict[str, str]) -> T:
    """A copy of ``config`` with dotted-name string overrides parsed by each field's type; an error names the
    option and the value."""
    leaves = {name: tp for name, tp, _, _ in _leaves(type(config))}
    for name, text in overrides.items():
        if name not in leaves:
            close = [n for n in leaves if n.split(".")[-1] == name.split(".")[-1]]
            hint = f" (did you mean {', '.join(close)}?)" if close else ""
            raise ValueError(f"unknown option --{name}{hint}")
        value = parse_value(str(text), leaves[name], name)
        try:
            config = _set(config, name.split("."), value)
        except ValueError as err:
            raise ValueError(f"--{name} {text}: {err}") from None
    return config


def config_differences(old: Any, new: Any) -> list[tuple[str, Any, Any]]:
    """(dotted name, old value, new value) of every leaf field that differs between two configs of one class."""
    out = []
    for name, _, _, _ in _leaves(type(old)):
        a, b = old, new
        for part in name.split("."):
            a, b = getattr(a, part, None), getattr(b, part, None)
        if a != b:
            out.append((name, a, b))
    return out


def _set(obj: Any, path: list[str], value: Any) -> Any:
    if len(path) == 1:
        return dataclasses.replace(obj, **{path[0]: value})
    child = getattr(obj, path[0])
    if child is None:  # an optional section that was off: build it from its defaults
        child = _strip_optional(_hints(type(obj))[path[0]])[0]()
    return dataclasses.replace(obj, **{path[0]: _set(child, path[1:], value)})


# ---------------------------------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------------------------------
def to_jsonable(obj: Any) -> Any:
    """Dataclasses, paths and tuples -> plain JSON types."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (tuple, list)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    return obj


def _from_json_value(value: Any, tp: Any, where: str) -> Any:
    """A JSON value as annotation ``tp`` wants it (nested dataclasses, tuples of tuples, paths, unions)."""
    inner, optional = _strip_optional(tp)
    if value is None:
        if optional or inner is type(None):
            return None
        raise ValueError(f"{where}: null is not allowed")
    origin, args = get_origin(inner), get_args(inner)
    if _is_dataclass_type(inner):
        if not isinstance(value, dict):
            raise ValueError(f"{where}: expected an object, got {value!r}")
        return from_jsonable(inner, value, where)
    if inner is Path:
        return Path(value)
    if inner is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if inner in (int, float, str, bool) and (not isinstance(value, inner) or (inner is int and isinstance(value, bool))):
        raise ValueError(f"{where}: expected {inner.__name__}, got {value!r}")
    if origin is tuple and isinstance(value, list):
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_from_json_value(v, args[0], where) for v in value)
        if len(args) != len(value):
            raise ValueError(f"{where}: expected {len(args)} values, got {value!r}")
        return tuple(_from_json_value(v, a, where) for v, a in zip(value, args))
    if origin in (Union, types.UnionType):  # the first option the value fits
        for option in args:
            if get_origin(option) is tuple and isinstance(value, list):
                return _from_json_value(value, option, where)
            if isinstance(option, type) and isinstance(value, option):
                return value
        return value
    if origin is typing.Literal and value not in args:
        raise ValueError(f"{where} must be one of {', '.join(map(str, args))}, got {value!r}")
    return value


def from_jsonable(cls: type[T], data: dict, where: str | None = None) -> T:
    """Rebuild a (nested) dataclass from ``to_jsonable`` output; unknown keys are an error, missing keys default."""
    where = where or cls.__name__
    hints = _hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{where}: unknown config keys {sorted(unknown)}")
    return cls(**{name: _from_json_value(value, hints[name], f"{where}.{name}") for name, value in data.items()})


def save_config(config: Any, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_jsonable(config), indent=2))


def load_config(cls: type[T], path: Path) -> T:
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: malformed JSON at line {err.lineno} column {err.colno}: {err.msg}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object with the config's sections")
    try:
        return from_jsonable(cls, data)
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: {err}") from None
