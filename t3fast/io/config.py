"""Configurations as dataclasses, loaded from YAML/JSON files and ``key=value`` overrides.

A configuration is a (possibly nested) dataclass whose fields all have defaults::

    @dataclass
    class ModelConfig:
        hidden: list[int] = field(default_factory=lambda: [128, 128])

    @dataclass
    class Config:
        model: ModelConfig = field(default_factory=ModelConfig)
        train: TrainConfig = field(default_factory=TrainConfig)

    cfg = load_config(Config, "stage1.yaml", ["train.lr=3e-4", "model.hidden=[64,64]", "train.amp=false"])

Values are coerced to the declared field types (nested dataclasses, ``int``, ``float``,
``bool``, ``str``, ``Path``, ``list[T]``, ``tuple[T, ...]``, ``dict[str, T]``, ``Literal``,
``Optional[T]``); an unknown key raises :class:`ConfigError` naming the key and the valid ones.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml

from t3fast.errors import ConfigError

__all__ = ["ConfigError", "config_to_dict", "load_config", "save_config"]

T = TypeVar("T")

_TRUE = {"true", "yes", "on", "1"}
_FALSE = {"false", "no", "off", "0"}


def load_config(
    cls: type[T],
    source: str | Path | Mapping[str, Any] | None = None,
    overrides: Iterable[str] = (),
) -> T:
    """Build ``cls`` from its defaults, then ``source``, then ``overrides`` (later wins).

    Args:
        cls: the configuration dataclass.
        source: a ``.yaml``/``.yml``/``.json`` path, a mapping, or None for the defaults.
        overrides: ``"dotted.key=value"`` strings; the value is parsed as YAML
            (``[64,64]``, ``false``, ``null``) and then coerced to the field's type.
    """
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise TypeError(f"load_config needs a dataclass type, got {cls!r}")
    raw = _read_source(source)
    for item in overrides:
        _apply_override(raw, item)
    return _build(cls, raw, prefix="")


def config_to_dict(cfg: Any) -> Any:
    """Plain (YAML/JSON-serialisable) form of a configuration: dicts, lists, scalars."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, Mapping):
        return {str(k): config_to_dict(v) for k, v in cfg.items()}
    if isinstance(cfg, list | tuple):
        return [config_to_dict(v) for v in cfg]
    if isinstance(cfg, Path):
        return str(cfg)
    return cfg


def save_config(cfg: Any, path: str | Path) -> None:
    """Write ``cfg`` as JSON when ``path`` ends in ``.json``, else as YAML."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = config_to_dict(cfg)
    if path.suffix == ".json":
        path.write_text(json.dumps(data, indent=2) + "\n")
    else:
        path.write_text(yaml.safe_dump(data, sort_keys=False))


def _read_source(source: str | Path | Mapping[str, Any] | None) -> dict[str, Any]:
    if source is None:
        return {}
    if isinstance(source, Mapping):
        return _deep_copy_dict(source)
    path = Path(source)
    if path.suffix not in (".json", ".yaml", ".yml"):
        raise ConfigError(f"config file {path} must end in .yaml, .yml or .json")
    text = path.read_text()
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (ValueError, yaml.YAMLError) as exc:
        reason = " ".join(str(exc).split())
        raise ConfigError(f"config file {path} is not valid {path.suffix[1:].upper()}: {reason}") from exc
    if data is None:  # an empty YAML file
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping at the top, got {type(data).__name__}")
    return data


def _deep_copy_dict(data: Mapping[str, Any]) -> dict[str, Any]:
    return {k: _deep_copy_dict(v) if isinstance(v, Mapping) else v for k, v in data.items()}


class _OverrideText(str):
    """An override's value as typed; parsed as YAML only where the field is not a string."""


def _apply_override(raw: dict[str, Any], item: str) -> None:
    """Set ``raw[a][b][c] = value`` for ``"a.b.c=value"``; types are checked later by :func:`_build`."""
    key, sep, text = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"override {item!r} must look like 'section.key=value'")
    *parents, leaf = key.split(".")
    node = raw
    for i, part in enumerate(parents):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"override {item!r}: '{'.'.join(parents[: i + 1])}' is not a section")
        node = child
    node[leaf] = _OverrideText(text.strip())


def _build(cls: type[T], raw: Any, prefix: str) -> T:
    if dataclasses.is_dataclass(raw) and isinstance(raw, cls):
        return raw
    if not isinstance(raw, Mapping):
        raise ConfigError(f"'{prefix or cls.__name__}' must be a mapping of {cls.__name__} fields, got {raw!r}")
    upgrade = getattr(cls, "upgrade", None)
    if upgrade is not None:  # keys of earlier versions, e.g. in a checkpoint's config
        raw = upgrade(raw)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = [k for k in raw if k not in fields]
    if unknown:
        where = f"in '{prefix}'" if prefix else f"in {cls.__name__}"
        raise ConfigError(
            f"unknown config key '{prefix}{unknown[0]}' {where}; valid keys: {', '.join(sorted(fields))}"
        )
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, f in fields.items():
        if name in raw:
            kwargs[name] = _coerce(raw[name], hints[name], f"{prefix}{name}")
        elif _is_dataclass_type(hints[name]) and not _has_default(f):
            # a nested section without a default, absent from the source: build it from its own defaults
            kwargs[name] = _build(hints[name], {}, f"{prefix}{name}.")
    try:
        return cls(**kwargs)
    except TypeError as exc:  # e.g. a field without a default that the source did not set
        raise ConfigError(f"cannot build {cls.__name__} at '{prefix or '<root>'}': {exc}") from exc


def _has_default(f: dataclasses.Field) -> bool:
    return f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Convert ``value`` to the annotated type ``tp`` or raise :class:`ConfigError` naming ``key``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if isinstance(value, _OverrideText):
        if tp in (str, Path) or (origin is typing.Literal and str(value) in args):
            return tp(value) if tp in (str, Path) else str(value)
        if origin not in (typing.Union, types.UnionType):  # a union tries each member on the text
            value = yaml.safe_load(value)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        return _coerce_union(value, args, key)
    if origin is typing.Literal:
        if value in args:
            return value
        raise ConfigError(f"'{key}' must be one of {list(args)}, got {value!r}")
    if _is_dataclass_type(tp):
        return _build(tp, value, f"{key}.")
    if origin in (list, tuple, dict):
        return _coerce_container(value, origin, args, key)
    if tp in (bool, int, float, str, Path):
        return _coerce_scalar(value, tp, key)
    raise ConfigError(f"'{key}': unsupported field type {tp!r}")


def _coerce_union(value: Any, args: tuple[Any, ...], key: str) -> Any:
    if value is None or (isinstance(value, str) and value.lower() in ("none", "null")):
        if type(None) in args:
            return None
    errors = []
    for arg in args:
        if arg is type(None):
            continue
        try:
            return _coerce(value, arg, key)
        except ConfigError as exc:
            errors.append(str(exc))
    raise ConfigError(f"'{key}': {value!r} fits none of the allowed types ({'; '.join(errors)})")


def _coerce_container(value: Any, origin: type, args: tuple[Any, ...], key: str) -> Any:
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"'{key}' must be a mapping, got {value!r}")
        vt = args[1] if args else Any
        return {k: _coerce(v, vt, f"{key}.{k}") for k, v in value.items()}
    if not isinstance(value, list | tuple):
        raise ConfigError(f"'{key}' must be a list, got {value!r}")
    if origin is tuple and args and args[-1] is not Ellipsis:
        if len(args) != len(value):
            raise ConfigError(f"'{key}' must have {len(args)} items, got {len(value)}")
        return tuple(_coerce(v, t, f"{key}[{i}]") for i, (v, t) in enumerate(zip(value, args)))
    et = args[0] if args else Any
    items = [_coerce(v, et, f"{key}[{i}]") for i, v in enumerate(value)]
    return tuple(items) if origin is tuple else items


def _coerce_scalar(value: Any, tp: type, key: str) -> Any:
    try:
        if tp is bool:
            return _to_bool(value)
        if tp is int:
            return _to_int(value)
        if tp is float:
            if isinstance(value, bool):
                raise ValueError("a bool is not a number")
            return float(value)  # also parses "3e-4", which YAML 1.1 leaves as a string
        if isinstance(value, Mapping | list | tuple) or value is None:
            raise ValueError(f"expected a {tp.__name__}")
        return tp(value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"'{key}' must be {tp.__name__}, got {value!r} ({exc})") from None


def _to_bool(value: Any) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in _TRUE | _FALSE:
        return value.strip().lower() in _TRUE
    raise ValueError("expected true/false")


def _to_int(value: Any) -> int:
    if isinstance(value, bool):
        raise ValueError("a bool is not an integer")
    if isinstance(value, int):
        return value
    if isinstance(value, str) and value.strip().lstrip("+-").isdigit():
        return int(value)
    number = float(value)  # accepts "1e4" and 10.0 but not 2.5
    if not number.is_integer():
        raise ValueError("not an integer")
    return int(number)
