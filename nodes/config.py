"""Typed node parameters: a dataclass per plugin, checked before anything is spawned.

``parse_config(Config, params, where)`` accepts exactly the dataclass's fields
with their annotated types (int, float, bool, str, list[X], dict[str, X],
Optional[X], Literal[...]); an unknown key, a wrong type or a failed
``__post_init__`` check raises :class:`ConfigError` with one line naming the
node and the parameter.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Literal


class ConfigError(ValueError):
    """A node parameter that does not fit the node's config dataclass (one-line message)."""


@dataclasses.dataclass(frozen=True)
class NoConfig:
    """Nodes without parameters."""


def _type_label(tp: Any) -> str:
    if typing.get_origin(tp) is Literal:
        return " | ".join(repr(a) for a in typing.get_args(tp))
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, path: str) -> Any:
    """Return value converted to tp (only int -> float widening) or raise ConfigError."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arm in args:
            if arm is type(None):
                continue
            try:
                return _coerce(value, arm, path)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{path} must be {' or '.join(_type_label(a) for a in args)}, got {type(value).__name__} {value!r:.60}")
    if origin is Literal:
        if value in args and type(value) in {type(a) for a in args}:
            return value
        raise ConfigError(f"{path} must be one of {', '.join(repr(a) for a in args)}, got {value!r:.60}")
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif tp is str:
        if isinstance(value, str):
            return value
    elif origin is list or tp is list:
        if isinstance(value, (list, tuple)):
            item = args[0] if args else Any
            return [_coerce(v, item, f"{path}[{i}]") for i, v in enumerate(value)]
    elif origin is dict or tp is dict:
        if isinstance(value, dict):
            kt, vt = args if args else (Any, Any)
            return {_coerce(k, kt, f"{path} key"): _coerce(v, vt, f"{path}[{k!r}]") for k, v in value.items()}
    else:  # pragma: no cover - a config author used a type we do not support
        raise ConfigError(f"{path}: unsupported parameter type {tp}")
    raise ConfigError(f"{path} must be {_type_label(tp)}, got {type(value).__name__} {value!r:.60}")


def parse_config(config_cls: type, params: dict | None, where: str) -> Any:
    """Build ``config_cls`` from launch-file params; ``where`` names the node in errors."""
    params = {} if params is None else params
    if not isinstance(params, dict):
        raise ConfigError(f"{where}: params must be a mapping, got {type(params).__name__}")
    fields = {f.name: f for f in dataclasses.fields(config_cls)}
    unknown = sorted(set(params) - set(fields))
    if unknown:
        known = ", ".join(sorted(fields)) or "(none)"
        raise ConfigError(f"{where}: unknown parameter {unknown[0]!r} (known: {known})")
    hints = typing.get_type_hints(config_cls)
    kwargs = {}
    for name, f in fields.items():
        if name in params:
            kwargs[name] = _coerce(params[name], hints[name], f"{where}: parameter {name!r}")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{where}: missing required parameter {name!r} ({_type_label(hints[name])})")
    try:
        return config_cls(**kwargs)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def config_help(config_cls: type) -> list[dict]:
    """Parameters of a config class for `uuomocap launch --list-plugins` style help."""
    hints = typing.get_type_hints(config_cls)
    out = []
    for f in dataclasses.fields(config_cls):
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = "(required)"
        out.append({"name": f.name, "type": _type_label(hints[f.name]), "default": default})
    return out
