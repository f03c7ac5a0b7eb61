"""Typed config trees: dataclass <-> JSON-able dict, and ``--a.b value`` command-line overrides.

Configs are nested dataclasses whose fields carry type hints (``int``, ``float``, ``bool``, ``str``,
``X | None``, ``tuple[int, ...]``, ``Literal[...]`` or another config dataclass). Overrides name a field by its dotted
path from the root (``--model.field.d_hidden 256``) and are parsed to the field's type; an unknown path or a
value that does not parse is a :class:`~depthnerf.errors.DepthnerfError` naming it. Loading a dict is strict too:
an unknown key is an error, never silently dropped, and a value of the wrong type (a string for a number, a name
outside a ``Literal``) is an error naming its path.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

from depthnerf.errors import DepthnerfError

T = TypeVar("T")


def to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-able dict of a config dataclass (tuples become lists)."""
    return dataclasses.asdict(cfg)


def _parse_value(text: str, hint: Any, where: str) -> Any:
    origin, args = get_origin(hint), get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if text.lower() in ("none", "null") and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _parse_value(text, inner[0], where)
    if origin is Literal:
        if text not in [str(a) for a in args]:
            raise DepthnerfError(f"{where}: {text!r} is not one of {', '.join(map(str, args))}")
        return next(a for a in args if str(a) == text)
    if origin is tuple:
        parts = [p for p in text.replace("(", "").replace(")", "").split(",") if p.strip()]
        elem = args[0] if args else str
        return tuple(_parse_value(p.strip(), elem, where) for p in parts)
    try:
        if hint is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(text)
        if hint in (int, float, str):
            return hint(text)
    except ValueError:
        raise DepthnerfError(f"{where}: cannot parse {text!r} as {hint.__name__}") from None
    raise DepthnerfError(f"{where}: fields of type {hint} cannot be overridden from the command line")


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """Coerce a JSON value into ``hint`` (nested dataclasses included), strictly."""
    if dataclasses.is_dataclass(hint):
        return from_dict(hint, value, where)
    origin, args = get_origin(hint), get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], where)
    if origin is Literal:
        if value not in args:
            raise DepthnerfError(f"{where}: {value!r} is not one of {', '.join(map(str, args))}")
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise DepthnerfError(f"{where}: expected a list, got {value!r}")
        elem = args[0] if args else Any
        return tuple(_coerce(v, elem, where) for v in value)
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint in (int, float, str, bool) and type(value) is not hint:  # bool is no int here, int no str
        raise DepthnerfError(f"{where}: expected {hint.__name__}, got {value!r}")
    return value


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config") -> T:
    """Build ``cls`` from a dict produced by :func:`to_dict`; unknown keys are an error."""
    if not isinstance(data, dict):
        raise DepthnerfError(f"{where}: expected a mapping for {cls.__name__}")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise DepthnerfError(f"{where}: unknown field(s) {', '.join(sorted(unknown))} for {cls.__name__}")
    kwargs = {k: _coerce(v, hints[k], f"{where}.{k}") for k, v in data.items()}
    return cls(**kwargs)


def apply_overrides(cfg: T, pairs: list[str]) -> T:
    """Return a copy of ``cfg`` with ``["--a.b", "value", ...]`` (or ``--a.b=value``) applied."""
    items: list[tuple[str, str]] = []
    i = 0
    while i < len(pairs):
        key = pairs[i]
        if not key.startswith("--"):
            raise DepthnerfError(f"unexpected argument {key!r} (overrides look like --section.field VALUE)")
        if "=" in key:
            key, value = key.split("=", 1)
            i += 1
        else:
            if i + 1 >= len(pairs):
                raise DepthnerfError(f"override {key} needs a value")
            value, i = pairs[i + 1], i + 2
        items.append((key[2:].replace("-", "_"), value))
    roots = {f.name for f in dataclasses.fields(cfg)} if dataclasses.is_dataclass(cfg) else set()
    for path, value in items:
        if "." not in path and path not in roots:  # most likely a flag misspelled, e.g. --max for --max-steps
            raise DepthnerfError(f"--{path.replace('_', '-')}: neither a flag of this command (--help lists them) "
                                 f"nor a config field (known: {', '.join(sorted(roots))})")
        try:
            cfg = _set_path(cfg, path.split("."), value, path)
        except DepthnerfError as err:  # a config's own check (``__post_init__``): name the flag that broke it
            if str(err).startswith(f"--{path}"):
                raise
            raise DepthnerfError(f"--{path} {value}: {err}") from None
    return cfg


def _set_path(node: Any, parts: list[str], value: str, full: str) -> Any:
    if not dataclasses.is_dataclass(node):
        raise DepthnerfError(f"--{full}: not a config field")
    names = {f.name for f in dataclasses.fields(node)}
    head = parts[0]
    if head not in names:
        raise DepthnerfError(f"--{full}: unknown field {head!r} (known: {', '.join(sorted(names))})")
    current = getattr(node, head)
    if len(parts) == 1:
        hint = get_type_hints(type(node))[head]
        if dataclasses.is_dataclass(hint):
            raise DepthnerfError(f"--{full}: is a section, name one of its fields")
        new = _parse_value(value, hint, f"--{full}")
    else:
        new = _set_path(current, parts[1:], value, full)
    return dataclasses.replace(node, **{head: new})


def flat_keys(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested dict as dotted keys: ``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (how CLI overrides name fields)."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flat_keys(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def differences(old: dict[str, Any], new: dict[str, Any]) -> dict[str, tuple[Any, Any]]:
    """The dotted keys (:func:`flat_keys`) whose values differ between two nested dicts, sorted:
    ``{key: (old value, new value)}``, None for a key one side lacks."""
    a, b = flat_keys(old), flat_keys(new)
    return {k: (a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}


NumberRules = dict[str, tuple[float, bool]]
"""Dotted attribute path -> ``(bound, inclusive)``: the value must be ``>= bound`` (inclusive) or ``> bound``."""


def broken_rule(cfg: Any, rules: NumberRules) -> tuple[str, Any, float, bool] | None:
    """The first of ``rules`` that ``cfg`` breaks, as ``(path, value, bound, inclusive)`` (NaN breaks every rule);
    None when it keeps them all."""
    for path, (bound, inclusive) in rules.items():
        value = cfg
        for name in path.split("."):
            value = getattr(value, name)
        if not (value >= bound if inclusive else value > bound) or value != value:  # value != value: NaN
            return path, value, bound, inclusive
    return None
