"""Estimators by name: the single place that maps a CLI/web/sweep name to a config class and an estimator class.

``make_estimator(name, overrides, log_metadata)`` fills an estimator config's ``motion`` and ``sensor`` fields
(and ``gps_std_m``) from the log's recorded parameters (so a filter assumes the noise the data was made with)
and then applies overrides.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from slam2d.association.base import AssociationConfig, resolve_method
from slam2d.config import from_dict, to_dict, with_overrides
from slam2d.estimator import Estimator
from slam2d.filters.dead_reckoning import DeadReckoning, DeadReckoningConfig


@dataclass(frozen=True)
class EstimatorSpec:
    name: str
    config_cls: type
    factory: Callable[[Any], Estimator]
    description: str
    needs: str = ""
    """what the back end measures with: "scans" (lidar), "bearings" (landmark bearings), "ranges" (landmark ranges)
    or "" (odometry alone will do); a log without it is refused by the runner, rather than dead-reckoned under the
    estimator's name."""


ESTIMATORS: dict[str, EstimatorSpec] = {}

#: scalar sensor settings an estimator config inherits from the log's recorded scenario config, like ``sensor``
INHERITED_SCALARS = ("gps_std_m",)


def register_estimator(name: str, config_cls: type, factory: Callable[[Any], Estimator], description: str,
                       needs: str = "") -> None:
    """Make an estimator available by ``name`` to the runner, CLI, sweeps and web lab (``needs``: see
    :class:`EstimatorSpec`)."""
    ESTIMATORS[name] = EstimatorSpec(name, config_cls, factory, description, needs)


register_estimator("dead-reckoning", DeadReckoningConfig, DeadReckoning, "odometry integration only (baseline)")


#: the library's own back ends: name -> (module, config class, estimator class, description); imported on first use
#: so that filters/ and graph/ never import the lab (dependencies point one way)
_BUILTIN: dict[str, tuple[str, str, str, str]] = {
    "ekf": ("slam2d.filters.ekf_slam", "EKFConfig", "EKFSLAM",
            "EKF-SLAM: joint Gaussian over pose and landmarks, O(N^2) update"),
    "fastslam": ("slam2d.filters.fastslam", "FastSLAMConfig", "FastSLAM",
                 "FastSLAM 1.0: particles over paths, per-particle landmark EKFs, motion-model proposal"),
    "fastslam2": ("slam2d.filters.fastslam", "FastSLAM2Config", "FastSLAM",
                  "FastSLAM 2.0: FastSLAM with the proposal conditioned on the observations"),
    "graph": ("slam2d.graph.online", "GraphSLAMConfig", "GraphSLAM",
              "online graph SLAM with place-recognition loop closures (sparse LM)"),
    "lidar": ("slam2d.graph.lidar", "LidarSLAMConfig", "LidarSLAM",
              "lidar SLAM: scan-to-local-map ICP, keyframes, correlative+ICP verified loops, incremental pose graph"),
    "lidar-lifelong": ("slam2d.graph.lidar", "LifelongLidarConfig", "LidarSLAM",
                       "lidar SLAM, lifelong: localise against a static layer, dynamic points filtered, bounded map"),
    "range-only-ekf": ("slam2d.filters.range_only_ekf", "RangeOnlyEKFConfig", "RangeOnlyEKF",
                       "range-only EKF-SLAM: beacons placed by delayed trilateration, gated scalar range updates"),
    "range-only-graph": ("slam2d.graph.range_only", "RangeOnlyGraphConfig", "RangeOnlyGraph",
                         "batch graph SLAM for range-only beacons (dead reckoning until the final solve)"),
}


#: the built-in back ends' inputs beyond odometry (:attr:`EstimatorSpec.needs`)
_NEEDS = {"lidar": "scans", "lidar-lifelong": "scans", "ekf": "bearings", "fastslam": "bearings",
          "fastslam2": "bearings", "graph": "bearings", "range-only-ekf": "ranges", "range-only-graph": "ranges"}


def _load_builtin(names: Iterable[str] | None = None) -> None:
    """Register the built-in back ends (or those of ``names``) that are not registered yet (lazy: importing them
    costs time)."""
    import importlib

    for name in _BUILTIN if names is None else names:
        module, cfg_name, cls_name, description = _BUILTIN[name]
        if name not in ESTIMATORS:
            mod = importlib.import_module(module)
            register_estimator(name, getattr(mod, cfg_name), getattr(mod, cls_name), description, _NEEDS.get(name, ""))


def estimator_names() -> list[str]:
    _load_builtin()
    return sorted(ESTIMATORS)


def get_spec(name: str) -> EstimatorSpec:
    _load_builtin()
    if name not in ESTIMATORS:
        raise ValueError(f"unknown estimator {name!r}; valid estimators: {sorted(ESTIMATORS)}")
    return ESTIMATORS[name]


def specs_of(estimator: object) -> list[EstimatorSpec]:
    """The registered back ends ``estimator`` is an instance of, found by its class (``lidar`` and
    ``lidar-lifelong`` share one); empty for an estimator built outside the registry."""
    cls = type(estimator)
    _load_builtin(name for name, (module, _, cls_name, _) in _BUILTIN.items()
                  if (module, cls_name) == (cls.__module__, cls.__qualname__))  # imported already: no cost
    return [spec for spec in ESTIMATORS.values() if spec.factory is cls]


def make_config(name: str, overrides: Mapping[str, Any] | None = None,
                log_metadata: Mapping[str, Any] | None = None, *, has_ids: bool | None = None) -> Any:
    """The estimator's config: defaults, then the log's motion/sensor parameters, then ``overrides``.

    A log whose ``metadata['gps_role']`` is ``"evaluation"`` turns ``use_gps`` off (overrides may turn it back on).
    ``has_ids`` (whether the log's observations carry landmark ids, ``Log.obs_id >= 0``) resolves an ``auto``
    association method (:func:`slam2d.association.resolve_method`); without it ``auto`` stays and the back end
    resolves it at its first step with observations.
    """
    spec = get_spec(name)
    for what, arg in (("overrides", overrides), ("log_metadata", log_metadata)):
        if arg is not None and not isinstance(arg, Mapping):
            raise TypeError(f"make_estimator({name!r}): {what} must be a mapping (a dict), got {type(arg).__name__}")
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
    if meta.get("gps_role") == "evaluation" and "use_gps" in fields:
        # the log keeps GPS for scoring only (e.g. in its own frame): fuse it only when an override asks for it
        data["use_gps"] = False
    cfg = from_dict(spec.config_cls, data)
    cfg = with_overrides(cfg, overrides) if overrides else cfg
    if has_ids is not None and isinstance(getattr(cfg, "association", None), AssociationConfig):
        cfg = dataclasses.replace(cfg, association=resolve_method(cfg.association, has_ids))
    return cfg


def association_method(config: Any) -> str | None:
    """The association method an estimator config names (None for estimators that do not associate)."""
    assoc = getattr(config, "association", None)
    return assoc.method if isinstance(assoc, AssociationConfig) else None


def make_estimator(name: str, overrides: Mapping[str, Any] | None = None,
                   log_metadata: Mapping[str, Any] | None = None, *, has_ids: bool | None = None) -> Estimator:
    """Build the named estimator with :func:`make_config`."""
    return get_spec(name).factory(make_config(name, overrides, log_metadata, has_ids=has_ids))
