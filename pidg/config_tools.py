"""Dataclass configs <-> command line and JSON, with no dependency beyond the standard library.

Every leaf field of a (nested) dataclass config becomes a ``--section.field VALUE`` option, typed from its
annotation; the resolved config is written as JSON next to every run and read back from checkpoints.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any, TypeVar, Union, get_args, get_origin, get_type_hints

T = TypeVar("T")
_MISSING = object()
MISSING_OPTION = _MISSING  # default of options that override a config field only when given


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _strip_optional(tp: Any) -> tuple[Any, bool]:
    """(inner type, allows None) for ``X | None`` / ``Optional[X]``."""
    if get_origin(tp) in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(get_args(tp)) == 2:
            return args[0], True
    return tp, False


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
            choices = get_args(inner)
            for choice in choices:
                if str(choice) == text:
                    return choice
            raise ValueError(f"expected one of {', '.join(map(str, choices))}")
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


def _leaves(cls: type, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted name, type, default) of every leaf field of a dataclass type, nested dataclasses expanded."""
    hints = get_type_hints(cls)
    out = []
    for field in dataclasses.fields(cls):
        if not field.init:
            continue
        tp = hints[field.name]
        name = f"{prefix}{field.name}"
        inner, _ = _strip_optional(tp)
        if _is_dataclass_type(inner):
            out += _leaves(inner, name + ".")
        else:
            out.append((name, tp, field))
    return out


def add_config_arguments(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one ``--a.b`` option per leaf field of ``cls`` (defaults stay in the dataclass)."""
    group = parser.add_argument_group(f"{cls.__name__} options")
    for name, tp, field in _leaves(cls):
        default = field.default if field.default is not dataclasses.MISSING else "(computed)"
        if field.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            default = field.default_factory()  # type: ignore[misc]
        help_text = field.metadata.get("help", "")
        group.add_argument(f"--{name}", dest=f"cfg::{name}", default=_MISSING, metavar="VALUE",
                           help=f"{help_text} (default: {default})".strip())


def overrides_from_args(args: argparse.Namespace) -> dict[str, str]:
    """The ``--a.b VALUE`` options the user actually gave."""
    return {k[len("cfg::"):]: v for k, v in vars(args).items() if k.startswith("cfg::") and v is not _MISSING}


def apply_overrides(config: T, overrides: dict[str, str]) -> T:
    """A copy of ``config`` with dotted-name string overrides parsed by each field's type."""
    leaves = {name: tp for name, tp, _ in _leaves(type(config))}
    for name, text in overrides.items():
        if name not in leaves:
            close = [n for n in leaves if n.split(".")[-1] == name.split(".")[-1]]
            hint = f" (did you mean {', '.join(close)}?)" if close else ""
            raise ValueError(f"unknown option --{name}{hint}")
        config = _set(config, name.split("."), parse_value(str(text), leaves[name], name))
    return config


def _set(obj: Any, path: list[str], value: Any) -> Any:
    if len(path) == 1:
        return dataclasses.replace(obj, **{path[0]: value})
    child = getattr(obj, path[0])
    if child is None:  # an optional section that was off: build it from its defaults
        child = _strip_optional(get_type_hints(type(obj))[path[0]])[0]()
    return dataclasses.replace(obj, **{path[0]: _set(child, path[1:], value)})


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


def from_jsonable(cls: type[T], data: dict) -> T:
    """Rebuild a (nested) dataclass from ``to_jsonable`` output; unknown keys are an error, missing keys default."""
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown config keys {sorted(unknown)}")
    kwargs = {}
    for name, value in data.items():
        tp, _ = _strip_optional(hints[name])
        if value is None:
            kwargs[name] = None
        elif _is_dataclass_type(tp):
            kwargs[name] = from_jsonable(tp, value)
        elif tp is Path:
            kwargs[name] = Path(value)
        elif get_origin(tp) is tuple or (get_origin(tp) in (Union, types.UnionType) and isinstance(value, list)):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


def save_config(config: Any, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_jsonable(config), indent=2))


def load_config(cls: type[T], path: Path) -> T:
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: malformed JSON at line {err.lineno} column {err.colno}: {err.msg}") from None
    return from_jsonable(cls, data)
