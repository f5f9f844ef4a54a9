"""Configuration plumbing shared by every component.

Configs are frozen, keyword-only dataclasses with units in field names, validated in ``__post_init__`` (a clear
``ValueError`` naming the field; never a silent fix). This module turns them into dicts and back, and applies
``KEY=VALUE`` overrides from the CLI, sweep files and the web lab with the same validation.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

C = TypeVar("C")


#: magnitudes outside [TINY, HUGE] make squares, inverses and products overflow or vanish in float64; no physical
#: quantity in a 2D SLAM config comes near them, so validation refuses them with the field's name
TINY = 1e-100
HUGE = 1e100


def check_positive(obj: object, *names: str) -> None:
    """Raise ValueError unless each named field is a finite number in [1e-100, 1e100] (squares stay finite)."""
    for n in names:
        v = getattr(obj, n)
        if not (v >= TINY and v <= HUGE):
            raise ValueError(f"{type(obj).__name__}.{n} must be a number in [{TINY:g}, {HUGE:g}] (got {v!r})")


def check_nonnegative(obj: object, *names: str) -> None:
    """Raise ValueError unless each named field is 0 or a finite number up to 1e100."""
    for n in names:
        v = getattr(obj, n)
        if not (v >= 0 and v <= HUGE):
            raise ValueError(f"{type(obj).__name__}.{n} must be a number in [0, {HUGE:g}] (got {v!r})")


def check_probability(obj: object, *names: str, open_low: bool = False) -> None:
    """Raise ValueError unless each named field is in [0, 1] (or (0, 1] with ``open_low``)."""
    for n in names:
        v = getattr(obj, n)
        ok = (0 < v <= 1) if open_low else (0 <= v <= 1)
        if not ok:
            raise ValueError(f"{type(obj).__name__}.{n} must be in {'(0, 1]' if open_low else '[0, 1]'} (got {v!r})")


def to_dict(cfg: object) -> dict[str, Any]:
    """Nested plain dict of a config dataclass (tuples become lists)."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple | list):
            return [conv(e) for e in v]
        return v

    out = conv(cfg)
    assert isinstance(out, dict)
    return out


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Convert ``value`` (possibly a CLI string) to annotation ``tp``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None or (isinstance(value, str) and value.lower() == "none"):
            if len(args) < len(typing.get_args(tp)):
                return None
        return _coerce(value, args[0], where)
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise ValueError(f"{where} must be one of {list(typing.get_args(tp))} (got {value!r})")
        return value
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(f"{where} must be a table of fields (got {value!r})")
        try:
            return from_dict(tp, value, where=where)
        except ValueError as e:
            # name the full path of the field ("ScenarioConfig.sensor.range_std_m"), not just the inner class
            msg = str(e)
            prefix = f"{tp.__name__}."
            raise ValueError(f"{where}.{msg[len(prefix):]}" if msg.startswith(prefix) else msg) from None
    if origin is tuple:
        if isinstance(value, Mapping) or not isinstance(value, Iterable):  # a scalar or a table: name the field
            raise ValueError(f"{where} must be a list (got {value!r})")
        items: list[Any] = [v for v in value.split(",") if v.strip()] if isinstance(value, str) else list(value)
        targs = typing.get_args(tp)
        if (len(targs) == 2 and targs[1] is Ellipsis) or len(targs) <= 1:  # tuple[X, ...]: any length, one type
            inner = targs[0] if targs else Any
            return tuple(_coerce(v, inner, where) for v in items)
        if len(items) != len(targs):  # tuple[X, Y, Z]: one type per position
            raise ValueError(f"{where} must have {len(targs)} items (got {value!r})")
        return tuple(_coerce(v, t, where) for v, t in zip(items, targs, strict=True))
    try:
        if tp is bool:
            if isinstance(value, str):
                if value.lower() in ("1", "true", "yes", "on"):
                    return True
                if value.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError
            if value not in (0, 1):  # true/false (TOML, JSON) or 0/1; not 2 or 0.5
                raise ValueError
            return bool(value)
        if tp is int or tp is float:
            if isinstance(value, bool):  # `steps = true` is a mistake, not 1
                raise ValueError
            if tp is float:
                return float(value)
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            return int(value)
        if tp is str:
            return str(value)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{where} must be of type {tp.__name__} (got {value!r})") from None
    return value


def from_dict(cls: type[C], data: Mapping[str, Any], *, where: str | None = None) -> C:
    """Build config ``cls`` from a (possibly nested) dict; unknown keys raise ValueError naming them."""
    where = where or cls.__name__
    assert dataclasses.is_dataclass(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown field(s) {unknown} in {where}; valid fields: {sorted(names)}")
    hints = _field_types(cls)
    kwargs = {k: _coerce(v, hints[k], f"{where}.{k}") for k, v in data.items()}
    return cls(**kwargs)


def _optional_config(tp: Any) -> type | None:
    """The config class ``X`` of an annotation ``X | None``, else None."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1 and len(args) == 2 and isinstance(inner[0], type) and dataclasses.is_dataclass(inner[0]):
            return inner[0]
    return None


def leaf_paths(cls: type, prefix: str = "") -> dict[str, str]:
    """Map every dotted leaf path of a config class to itself, e.g. ``sensor.range_std_m``. An optional sub-config
    (``layers: LayersConfig | None``) is a path itself (``layers=none`` switches it off) and so are its fields."""
    out: dict[str, str] = {}
    hints = _field_types(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        path = prefix + f.name
        if dataclasses.is_dataclass(tp):
            out.update(leaf_paths(tp, path + "."))  # type: ignore[arg-type]
        elif (sub := _optional_config(tp)) is not None:
            out[path] = path
            out.update(leaf_paths(sub, path + "."))
        else:
            out[path] = path
    return out


def resolve_key(cls: type, key: str) -> str | None:
    """Resolve ``key`` (a dotted path or an unambiguous leaf name) to a dotted path in ``cls``; None if absent."""
    paths = leaf_paths(cls)
    if key in paths:
        return key
    matches = [p for p in paths if p.rsplit(".", 1)[-1] == key]
    if len(matches) > 1:
        raise ValueError(f"ambiguous key {key!r}: use one of {matches}")
    return matches[0] if matches else None


def with_overrides(cfg: C, overrides: Mapping[str, Any]) -> C:
    """Return ``cfg`` with dotted/leaf-name overrides applied and validated (a new object)."""
    data = to_dict(cfg)
    refuse = getattr(cfg, "refuse_override", None)  # a config may refuse a field before nested values are checked
    for key, value in overrides.items():
        path = resolve_key(type(cfg), key)
        if path is None:
            valid = sorted(leaf_paths(type(cfg)))
            raise ValueError(f"unknown key {key!r} for {type(cfg).__name__}; valid keys: {valid}")
        if refuse is not None and (why := refuse(path)):
            raise ValueError(why)
        node = data
        parts = path.split(".")
        for i, p in enumerate(parts[:-1]):
            if node[p] is None:
                off = ".".join(parts[: i + 1])
                raise ValueError(f"{type(cfg).__name__}.{off} is off (None) here, so {key!r} cannot be set")
            node = node[p]
        node[parts[-1]] = value
    return from_dict(type(cfg), data)


def parse_set_args(items: Iterable[str]) -> dict[str, str]:
    """Parse ``KEY=VALUE`` strings (from repeated ``--set``)."""
    out: dict[str, str] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        if not k.strip():
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        out[k.strip()] = v.strip()
    return out


def split_overrides(overrides: Mapping[str, Any], *classes: type) -> list[dict[str, Any]]:
    """Route each override to the first config class that knows the key; unknown keys raise ValueError."""
    routed: list[dict[str, Any]] = [{} for _ in classes]
    for k, v in overrides.items():
        for i, cls in enumerate(classes):
            if resolve_key(cls, k) is not None:
                routed[i][k] = v
                break
        else:
            valid = sorted({p for cls in classes for p in leaf_paths(cls)})
            raise ValueError(f"unknown key {k!r}; valid keys: {valid}")
    return routed
