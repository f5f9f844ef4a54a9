"""Estimators by name: the single place that maps a CLI/web/sweep name to a config class and an estimator class.

``make_estimator(name, overrides, log_metadata)`` fills an estimator config's ``motion`` and ``sensor`` fields
(and ``gps_std_m``) from the log's recorded parameters (so a filter assumes the noise the data was made with)
and then applies overrides.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from slam2d.config import from_dict, to_dict, with_overrides
from slam2d.filters.base import Estimator
from slam2d.filters.dead_reckoning import DeadReckoning, DeadReckoningConfig


@dataclass(frozen=True)
class EstimatorSpec:
    name: str
    config_cls: type
    factory: Callable[[Any], Estimator]
    description: str


ESTIMATORS: dict[str, EstimatorSpec] = {}

#: scalar sensor settings an estimator config inherits from the log's recorded scenario config, like ``sensor``
INHERITED_SCALARS = ("gps_std_m",)


def register_estimator(name: str, config_cls: type, factory: Callable[[Any], Estimator], description: str) -> None:
    """Make an estimator available by ``name`` to the runner, CLI, sweeps and web lab."""
    ESTIMATORS[name] = EstimatorSpec(name, config_cls, factory, description)


register_estimator("dead-reckoning", DeadReckoningConfig, DeadReckoning, "odometry integration only (baseline)")


def _load_builtin() -> None:
    """Import the modules that register further estimators (kept lazy to avoid import cycles)."""
    import importlib

    for mod in _BUILTIN_MODULES:
        importlib.import_module(mod)


#: modules whose import registers more estimators; each back end adds its own line here
_BUILTIN_MODULES: list[str] = [
    "slam2d.filters.ekf_slam",
]


def estimator_names() -> list[str]:
    _load_builtin()
    return sorted(ESTIMATORS)


def get_spec(name: str) -> EstimatorSpec:
    _load_builtin()
    if name not in ESTIMATORS:
        raise ValueError(f"unknown estimator {name!r}; valid estimators: {sorted(ESTIMATORS)}")
    return ESTIMATORS[name]


def make_config(name: str, overrides: Mapping[str, Any] | None = None,
                log_metadata: Mapping[str, Any] | None = None) -> Any:
    """The estimator's config: defaults, then the log's motion/sensor parameters, then ``overrides``."""
    spec = get_spec(name)
    cfg = spec.config_cls()
    meta = log_metadata or {}
    fields = {f.name for f in dataclasses.fields(cfg)}
    data = to_dict(cfg)
    for key in ("motion", "sensor"):
        if key in fields and isinstance(meta.get(key), Mapping):
            known = set(data[key])
            data[key].update({k: v for k, v in meta[key].items() if k in known})
    recorded = meta.get("config")
    for key in INHERITED_SCALARS:
        if key in fields and isinstance(recorded, Mapping) and recorded.get(key) is not None:
            data[key] = recorded[key]
    cfg = from_dict(spec.config_cls, data)
    return with_overrides(cfg, overrides) if overrides else cfg


def make_estimator(name: str, overrides: Mapping[str, Any] | None = None,
                   log_metadata: Mapping[str, Any] | None = None) -> Estimator:
    """Build the named estimator with :func:`make_config`."""
    return get_spec(name).factory(make_config(name, overrides, log_metadata))
