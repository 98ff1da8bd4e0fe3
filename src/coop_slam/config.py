"""One loader for the typed configuration of every module.

Each module defines a dataclass with defaults (and optional ``validate(self)`` raising ConfigError).
``load_config`` builds it from a mapping (YAML section, ROS private params) and rejects unknown keys
and values of the wrong type with a message naming the key, so a typo never passes silently.
"""

from __future__ import annotations

import dataclasses
import os
import typing
from typing import Any, Mapping, TypeVar

import yaml

from .errors import ConfigError

C = TypeVar("C")


def _coerce(name: str, value: Any, typ: Any) -> Any:
    origin = typing.get_origin(typ)
    if typ is Any:
        return value
    if origin is typing.Union:  # Optional[X]
        args = [a for a in typing.get_args(typ) if a is not type(None)]
        if value is None:
            return None
        return _coerce(name, value, args[0])
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key '{name}': expected a list, got {value!r}")
        (item_type, *_) = typing.get_args(typ) or (Any,)
        items = [_coerce(f"{name}[{i}]", v, item_type) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if dataclasses.is_dataclass(typ):
        if not isinstance(value, Mapping):
            raise ConfigError(f"config key '{name}': expected a mapping, got {value!r}")
        return load_config(typ, value, prefix=f"{name}.")
    if typ is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"config key '{name}': expected true/false, got {value!r}")
    if typ is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise ConfigError(f"config key '{name}': expected a number, got {value!r}")
    if typ is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"config key '{name}': expected an integer, got {value!r}")
    if typ is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"config key '{name}': expected a string, got {value!r}")
    return value


def load_config(cls: type[C], values: Mapping[str, Any] | None = None, prefix: str = "") -> C:
    """Build dataclass ``cls`` from ``values``; missing keys keep their defaults."""
    values = dict(values or {})
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {', '.join(prefix + k for k in unknown)} for {cls.__name__}; "
            f"known keys: {', '.join(sorted(fields))}"
        )
    kwargs = {k: _coerce(prefix + k, v, hints[k]) for k, v in values.items()}
    for k, v in kwargs.items():  # a mapping field merges with its default key by key
        default = (
            fields[k].default_factory
            if fields[k].default_factory is not dataclasses.MISSING
            else None
        )
        if hints[k] is dict and isinstance(v, Mapping) and default is not None:
            kwargs[k] = merge_overrides(default(), v)
    obj = cls(**kwargs)
    validate = getattr(obj, "validate", None)
    if callable(validate):
        validate()
    return obj


def load_yaml_config(
    cls: type[C],
    path: str | os.PathLike | None,
    section: str | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> C:
    """Load ``cls`` from a YAML file (optionally one top-level section of it), with ``overrides``
    (e.g. a node's ROS private params) on top key by key (:func:`merge_overrides`). No ``path``:
    the defaults with the overrides. The one loader of every config file: nodes and tools alike."""
    data: Any = {}
    if path:
        data = read_yaml_mapping(path)
        if section is not None:
            if section not in data:
                stray = sorted(set(data) & {f.name for f in dataclasses.fields(cls)})
                if stray:
                    raise ConfigError(
                        f"config file {path}: {', '.join(stray)} belong to section '{section}'; "
                        f"put them under '{section}:'"
                    )
            data = data.get(section) or {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"config file {path}: expected a mapping at '{section or 'top level'}'")
    values = merge_overrides(data, overrides or {})
    return load_config(cls, values, prefix=f"{section}." if section else "")


def read_yaml_mapping(path: str | os.PathLike, what: str = "config file") -> dict:
    """A YAML file's top-level mapping (empty file: {}); ConfigError naming ``what`` and why."""
    try:
        with open(path, encoding="utf-8") as fh:
            data = yaml.safe_load(fh) or {}
    except FileNotFoundError:
        raise ConfigError(f"{what} not found: {path}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{what} {path} is not valid YAML: {exc}") from None
    if not isinstance(data, Mapping):
        raise ConfigError(f"{what} {path}: expected a mapping at the top level")
    return dict(data)


def merge_overrides(values: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict:
    """``values`` with ``overrides`` on top, section by section: a ROS param ``~global_ba/x``
    arrives as ``{'global_ba': {'x': ...}}`` and must change that key, not replace the section."""
    out = dict(values)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge_overrides(out[key], value)
        else:
            out[key] = value
    return out


def with_values(obj: C, overrides: Mapping[str, Any], prefix: str = "") -> C:
    """A copy of config ``obj`` with ``overrides`` (nested like its sections) on top, loaded and
    validated as a file would be."""
    values = merge_overrides(dataclasses.asdict(obj), overrides)
    return load_config(type(obj), values, prefix=prefix)


def require(condition: bool, message: str) -> None:
    """Raise ConfigError(message) unless condition holds (for ``validate`` methods)."""
    if not condition:
        raise ConfigError(message)
